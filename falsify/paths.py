"""Where the files read at run time live: the bundled configs, sensor presets and return models.

Installed, they are package data in falsify/configs; in a source checkout, the configs/ folder
beside falsify/. The bundled weights live with the network (falsify.models.runner.WEIGHTS_DIR).
"""

from __future__ import annotations

from pathlib import Path

_HERE = Path(__file__).resolve().parent
CONFIGS = _HERE / "configs" if (_HERE / "configs").is_dir() else _HERE.parent / "configs"
SENSOR_PRESETS = CONFIGS / "sensors"
RETURN_MODELS = CONFIGS / "returns"  # fitted sensor return models (falsify.jobs.fit_returns)


def config_path(path: str | Path) -> Path:
    """The config a user names: the file itself where it exists, else the bundled config of
    that name, so `configs/ci.toml` (or `ci.toml`) works from any directory."""
    path = Path(path)
    if path.exists() or path.is_absolute():
        return path
    parts = path.parts[1:] if path.parts[:1] == ("configs",) else path.parts
    bundled = CONFIGS.joinpath(*parts) if parts else CONFIGS
    return bundled if bundled.is_file() else path
