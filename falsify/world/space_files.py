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
    key: str = ""   # where the config declares it ("cfg.toml: actors.mine"), for its errors


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


# `[dims.background] labels`: whether each real scan must have labels (the default asks it of
# scans in a SemanticKITTI sequence only; a bare .bin may have none).
LABEL_MODES = ("required", "optional")
SHOWN = 3   # missing label files named in an error, before "and N more"


def read_real_backgrounds(spec: dict, where: str, base_dir: Path) -> tuple[RealScan, ...]:
    """`real = [...]` (KITTI .bin files, folders of them, SemanticKITTI roots or sequence
    folders, KITTI object directories; relative to the config's folder), optional
    `sequences = ["08", ...]`, `per_sequence = N` (N evenly spaced scans of each sequence, at
    most as many as the shortest holds) and `labels`: unset, a scan of a SemanticKITTI sequence
    must have its .label; "required", every scan must have labels; "optional", scans may have
    none (SemanticKITTI's test sequences 11-21; their real cars go unscored). The scans in
    order, each with where its labels come from."""
    key = "dims.background"
    allowed = ("real", "sequences", "per_sequence", "labels")
    extra = sorted(set(spec) - set(allowed))
    if extra:
        raise ConfigError(f"{where}{key}: unknown key {extra[0]!r} beside real; allowed: "
                          f"{', '.join(allowed)}")
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
    labels = spec.get("labels")
    if labels is not None and labels not in LABEL_MODES:
        raise ConfigError(f"{where}{key}.labels: {labels!r}; allowed: \"required\" (every scan "
                          "has labels), \"optional\" (scans may have none; their real_iou and "
                          "real_recall are left empty); unset, scans of a SemanticKITTI sequence "
                          "need their .label")
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
        _check_per_sequence(found, per_sequence, f"{where}{key}")
        found = evenly_per_folder(found, per_sequence)
    if len(found) > MAX_VALUES:
        raise ConfigError(f"{where}{key}.real: {len(found)} scans; at most {MAX_VALUES}")
    scans = tuple(RealScan(*f) for f in found)
    if labels != "optional":
        _check_labels(scans, labels == "required", f"{where}{key}")
    return scans


def _check_per_sequence(found: list[tuple[str, Path, Path | None, str]], k: int,
                        where: str) -> None:
    """ConfigError naming the first sequence (folder of scans) that holds fewer scans than the
    `k` per_sequence asks of each, with how many it holds: fewer would pass unsaid."""
    from falsify.world.real_scans import scans_per_folder
    counts = scans_per_folder(found)
    short = [(folder, n) for folder, n in counts.items() if n < k]
    if short:
        folder, n = short[0]
        what = (f"sequence {folder.parent.name}" if folder.name == "velodyne"
                else f"folder {folder.name}")
        raise ConfigError(f"{where}.per_sequence: {k} scans asked of each sequence, but {what} "
                          f"({folder}) holds {n} scan{'s' * (n != 1)}; allowed: 1 to "
                          f"{min(counts.values())}, the most the shortest one named holds (or "
                          f"leave {what} out)")


def _check_labels(scans: tuple[RealScan, ...], every: bool, where: str) -> None:
    """ConfigError naming the label files missing for scans that need them (a SemanticKITTI
    sequence's; every scan's when `every`): unlabelled, a scan's real cars would be scored as
    background, unsaid."""
    from falsify.world.real_scans import sequence_label
    missing: list[str] = []
    no_folder: dict[Path, int] = {}   # a sequence without labels/: named once, its scans counted
    for r in scans:
        if r.kind != "none":
            continue
        want = sequence_label(r.bin)
        if want is not None and not want.parent.is_dir():
            no_folder[want.parent] = no_folder.get(want.parent, 0) + 1
        elif want is not None:
            missing.append(str(want))
        elif every:
            missing.append(f"{r.bin.with_suffix('.label')} (or ../labels/{r.bin.stem}.label)")
    if not missing and not no_folder:
        return
    n = len(missing) + sum(no_folder.values())
    named = [f"{folder}/ (no such folder: {c} scan{'s' * (c != 1)})"
             for folder, c in no_folder.items()] + missing
    more = f", and {len(named) - SHOWN} more" if len(named) > SHOWN else ""
    raise ConfigError(
        f"{where}.real: {n} of {len(scans)} scans {'has' if n == 1 else 'have'} no labels, so "
        f"the cars in {'it' if n == 1 else 'them'} would be scored as background: missing "
        f"{'; '.join(named[:SHOWN])}{more}. Restore the label files, leave those scans out "
        "(sequences = [...], or name the scans), or, for scans that have none (SemanticKITTI's "
        "test sequences 11-21), set labels = \"optional\" in [dims.background]: their real_iou "
        "and real_recall are then left empty, and a car predicted on one of their real cars "
        "counts against the inserted car (read inserted_recall)")


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
        file = Path(spec["file"]).expanduser()
        if not file.is_absolute():
            file = base_dir / file
        out[name] = UserCar(name, file, float(scale), spec.get("forward", "+x"),
                            spec.get("up", "+z"), semantic, f"{where}{key}")
    return out
