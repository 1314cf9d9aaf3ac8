"""Errors a user can fix: the CLI turns them into one clear line and exit code 2."""


class FalsifyError(Exception):
    """Bad input from the user (config, file, option); exit code 2."""


class ConfigError(FalsifyError):
    """A config key or value is wrong; the message names the key and the allowed values."""
