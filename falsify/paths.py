"""Where the files read at run time live: the bundled configs, sensor presets and return models,
and the user's own data, named in configs as `${VARIABLE}` paths read from the environment.

Installed, they are package data in falsify/configs; in a source checkout, the configs/ folder
beside falsify/. The bundled weights live with the network (falsify.models.runners.WEIGHTS_DIR).
"""

from __future__ import annotations

import hashlib
import os
import re
from pathlib import Path

from falsify.errors import FalsifyError

_HERE = Path(__file__).resolve().parent
CONFIGS = _HERE / "configs" if (_HERE / "configs").is_dir() else _HERE.parent / "configs"
SENSOR_PRESETS = CONFIGS / "sensors"
RETURN_MODELS = CONFIGS / "returns"  # fitted sensor return models (falsify.jobs.fit_returns)


def config_path(path: str | Path) -> Path:
    """The config a user names: the file itself where it exists, else the bundled config of
    that name, so `configs/ci.toml`, `ci.toml` or `ci` works from any directory (a folder of
    that name, say a run's `--out ci`, does not hide it)."""
    path = Path(path)
    if path.is_file() or path.is_absolute():
        return path
    parts = path.parts[1:] if path.parts[:1] == ("configs",) else path.parts
    if parts:
        bundled = CONFIGS.joinpath(*parts)
        for candidate in (bundled, bundled.with_name(bundled.name + ".toml")):
            if candidate.is_file():
                return candidate
    return path


def bundled_configs() -> list[str]:
    """The names of the bundled space configs (`falsify grid NAME`)."""
    return sorted(p.stem for p in CONFIGS.glob("*.toml"))


# The data sets shipped configs name, by the variable that says where a user keeps each.
DATA_VARIABLES = {
    "SEMANTICKITTI": (
        "a SemanticKITTI root (the folder holding sequences/SS/velodyne/*.bin and "
        "sequences/SS/labels/*.label): download KITTI odometry's Velodyne scans and "
        "SemanticKITTI's labels (semantic-kitti.org), unpack both into one folder DIR, then "
        "`export SEMANTICKITTI=DIR`"),
    "KITTI_OBJECT": (
        "a KITTI 3D object folder (velodyne/, label_2/, calib/, image_2/ of KITTI's object "
        "benchmark, cvlibs.net/datasets/kitti): unpack it into DIR, then "
        "`export KITTI_OBJECT=DIR`"),
}
_VARIABLE = re.compile(r"\$\{([A-Za-z_][A-Za-z0-9_]*)\}")


def expand_data_path(text: str, where: str) -> str:
    """A data path with each `${NAME}` replaced by that environment variable and a leading `~`
    by the home folder; FalsifyError naming `where` and saying how to get the data when a
    variable is unset or empty."""
    def value(match: re.Match) -> str:
        name = match.group(1)
        found = os.environ.get(name, "")
        if not found:
            how = DATA_VARIABLES.get(name, f"the folder it names: `export {name}=DIR`")
            raise FalsifyError(f"{where}: ${{{name}}} is not set; it must name {how} "
                               "(or write the path into the config)")
        return found
    return os.path.expanduser(_VARIABLE.sub(value, text))


def sensor_digest(path: str | Path, error: type[FalsifyError] = FalsifyError) -> str:
    """sha256 of a user's sensor TOML and of the fitted return model it names (a `.json`
    relative to the TOML), the files whose bytes decide its scans: a run's config hash and a
    dataset's index hold it, so a changed file is another sensor."""
    from falsify.fileio import parse_toml, read_bytes

    path = Path(path)
    text = read_bytes(path, "sensor", error)
    digest = hashlib.sha256(text)
    returns = parse_toml(text, path, "sensor TOML", error).get("returns")
    if isinstance(returns, str) and returns.endswith(".json"):
        digest.update(read_bytes(path.parent / returns, "sensor returns", error))
    return digest.hexdigest()
