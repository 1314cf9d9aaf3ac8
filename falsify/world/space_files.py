"""What a space config names on disk: user meshes as car models or actors (`[car_models.NAME]`,
`[actors.NAME]` with a SemanticKITTI `class`) and real scans as backgrounds
(`[dims.background] real = [...]`), each read from its table with errors that name the key.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from falsify.errors import ConfigError
from falsify.world.space_dims import MAX_VALUES

CAR_FILE_KEYS = {"file", "scale", "forward", "up"}
ACTOR_FILE_KEYS = CAR_FILE_KEYS | {"class"}
# The SemanticKITTI classes a user's actor may declare: the things a road holds.
ACTOR_CLASSES = ("car", "truck", "bus", "other-vehicle", "motorcycle", "bicycle", "person",
                 "bicyclist", "motorcyclist", "other-object")


@dataclass(frozen=True)
class UserCar:
    """A car model or actor the user brings as a mesh file, with the raw SemanticKITTI id its
    points carry (car for `[car_models.*]`)."""

    name: str
    file: Path
    scale: float = 1.0
    forward: str = "+x"
    up: str = "+z"
    semantic: int = 10


@dataclass(frozen=True)
class RealScan:
    """A real scan a background may be: its KITTI .bin and where its labels come from (a
    SemanticKITTI .label, a KITTI object frame's label_2 boxes, or none)."""

    name: str
    bin: Path
    label: Path | None = None
    kind: str = "none"   # "semantickitti", "object" or "none" (unlabelled)
    # The scan turned by this about the sensor's vertical axis before it is projected (rings
    # still from the stored order): a front-view sensor sees another slice of the 360 degrees.
    yaw_deg: float = 0.0



def read_real_backgrounds(spec: dict, where: str, base_dir: Path) -> tuple[RealScan, ...]:
    """`real = [...]` (KITTI .bin files, folders of them, SemanticKITTI roots or sequence
    folders, KITTI object directories; relative to the config's folder) and optional
    `sequences = ["08", ...]`: the scans in order, each with where its labels come from."""
    key = "dims.background"
    extra = sorted(set(spec) - {"real", "sequences", "per_sequence"})
    if extra:
        raise ConfigError(f"{where}{key}: unknown key {extra[0]!r} beside real; allowed: real, "
                          "sequences, per_sequence")
    paths = spec["real"]
    if (not isinstance(paths, list) or not paths
            or not all(isinstance(p, str) and p for p in paths)):
        raise ConfigError(f"{where}{key}.real: expected a non-empty list of paths (KITTI .bin "
                          "scans, folders, SemanticKITTI roots or sequences)")
    sequences = spec.get("sequences")
    if sequences is not None and (not isinstance(sequences, list) or not sequences or not all(
            isinstance(q, str) for q in sequences)):
        raise ConfigError(f"{where}{key}.sequences: expected a non-empty list of sequence ids "
                          "such as [\"00\", \"08\"]")
    per_sequence = spec.get("per_sequence")
    if per_sequence is not None and (isinstance(per_sequence, bool)
                                     or not isinstance(per_sequence, int) or per_sequence < 1):
        raise ConfigError(f"{where}{key}.per_sequence: expected an integer >= 1 (scans taken "
                          f"evenly spaced from each folder of scans), got {per_sequence!r}")
    from falsify.errors import FalsifyError
    from falsify.paths import expand_data_path
    from falsify.world.real_scans import evenly_per_folder, real_scans
    expanded = [expand_data_path(p, f"{where}{key}.real") for p in paths]
    resolved = [p if Path(p).is_absolute() else str(base_dir / p) for p in expanded]
    try:
        found = real_scans(resolved, sequences)
    except FalsifyError as exc:
        raise ConfigError(f"{where}{key}.real: {exc}") from None
    if per_sequence is not None:
        found = evenly_per_folder(found, per_sequence)
    if len(found) > MAX_VALUES:
        raise ConfigError(f"{where}{key}.real: {len(found)} scans; at most {MAX_VALUES}")
    return tuple(RealScan(*f) for f in found)



def read_user_cars(raw: Any, where: str, base_dir: Path, builtin: tuple[str, ...],
               table: str = "car_models") -> dict:
    """`[car_models.NAME]` (cars) or `[actors.NAME]` (with a SemanticKITTI `class`) tables as
    UserCars; ConfigError names a bad key, a taken name or a missing class."""
    if not isinstance(raw, dict):
        raise ConfigError(f"{where}{table}: expected tables like [{table}.mine] file = ...")
    keys = ACTOR_FILE_KEYS if table == "actors" else CAR_FILE_KEYS
    out: dict[str, UserCar] = {}
    for name, spec in raw.items():
        key = f"{table}.{name}"
        if name in builtin:
            raise ConfigError(f"{where}{key}: {name!r} is a built-in or declared model; choose "
                              "another name")
        if not isinstance(spec, dict) or "file" not in spec:
            raise ConfigError(f"{where}{key}: needs file = 'path/to/mesh' (OBJ, STL, PLY, GLB)")
        extra = sorted(set(spec) - keys)
        if extra:
            raise ConfigError(f"{where}{key}: unknown key {extra[0]!r}; allowed: "
                              f"{', '.join(sorted(keys))}")
        semantic = 10
        if table == "actors":
            cls = spec.get("class")
            if cls not in ACTOR_CLASSES:
                raise ConfigError(f"{where}{key}.class: " + (
                    "missing" if cls is None else repr(cls)) + "; a user's actor declares its "
                    f"SemanticKITTI class, one of: {', '.join(ACTOR_CLASSES)}")
            from falsify.semantic import RAW_ID
            semantic = RAW_ID[cls]
        scale = spec.get("scale", 1.0)
        if isinstance(scale, bool) or not isinstance(scale, int | float) or not (
                math.isfinite(scale) and scale > 0):
            raise ConfigError(f"{where}{key}.scale: {scale!r} must be a finite number > 0")
        for axis_key in ("forward", "up"):
            v = spec.get(axis_key, "+x" if axis_key == "forward" else "+z")
            if v not in ("+x", "-x", "+y", "-y", "+z", "-z"):
                raise ConfigError(f"{where}{key}.{axis_key}: {v!r}; allowed: +x, -x, +y, -y, "
                                  "+z, -z")
        file = Path(spec["file"])
        if not file.is_absolute():
            file = base_dir / file
        out[name] = UserCar(name, file, float(scale), spec.get("forward", "+x"),
                            spec.get("up", "+z"), semantic)
    return out
