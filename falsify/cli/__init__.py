"""The `falsify` command line."""

from falsify.cli.commands import main

__all__ = ["main"]
