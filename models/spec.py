"""Model spec: the JSON file beside a model (``<model>.onnx`` -> ``<model>.json``).

It says how to turn a scan (H, W, 6: x, y, z, intensity, range, label) into the model's input
tensors (a range image, or the scan's valid points for `input_kind` "points") and how to read its
output, so a runner can check a model before any sample runs. Class names are our four or
SemanticKITTI's train classes. Importing this module needs numpy only (no torch).
"""

from __future__ import annotations

import hashlib
import json
import math
import re
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from falsify.classes import CLASSES
from falsify.errors import FalsifyError
from falsify.fileio import file_sha256, write_text
from falsify.semantic import KITTI4_OF_RAW, LEARNING_MAP, TRAIN_CLASSES, TRAIN_ID

ALL_CHANNELS = ("x", "y", "z", "intensity", "range")
DEFAULT_CHANNELS = ("x", "y", "z", "range")  # the paper leaves intensity out for synthetic data
SCAN_INDEX = {"x": 0, "y": 1, "z": 2, "intensity": 3, "range": 4}
INPUT_MEAN = (10.88, 0.23, -1.04, 0.21, 12.12)
INPUT_STD = (11.47, 6.91, 0.86, 0.16, 12.32)
OUTPUT_KINDS = ("logits", "probabilities")
# "range": (B, C, H, W) range-image tensors in; "points": each scan's valid points, (N, 4) x, y, z,
# intensity (the remission), in; per-point classes out.
INPUT_KINDS = ("range", "points")
POINT_CHANNELS = ("x", "y", "z", "intensity")
SPEC_VERSION = 1
# The files an export writes beside a spec whose sha256 it records: the ONNX graph, the weights.
HASHED_ROLES = ("onnx", "pt")
_HEX64 = re.compile(r"[0-9a-f]{64}")
# Names a spec may map output indices to: our four, then SemanticKITTI's train classes.
SPEC_CLASSES: tuple[str, ...] = (*CLASSES, *(n for n in TRAIN_CLASSES[1:] if n not in CLASSES))
# Our names that are SemanticKITTI classes under another name.
ALIASES = {"pedestrian": "person", "cyclist": "bicyclist"}
# train id -> our four classes, as `falsify.semantic.kitti4` reads labels (motorcyclists count
# as cyclists), so a prediction and a label of the same thing fold alike.
_FOUR_OF_TRAIN = np.zeros(len(TRAIN_CLASSES), np.uint8)
_FOUR_OF_TRAIN[LEARNING_MAP[KITTI4_OF_RAW > 0]] = KITTI4_OF_RAW[KITTI4_OF_RAW > 0]


def train_id_of(name: str) -> int:
    """The SemanticKITTI train id of a spec class name (0, unlabeled, for 'unknown')."""
    return 0 if name == "unknown" else TRAIN_ID[ALIASES.get(name, name)]


def four_class_of(name: str) -> int:
    """Our class id (0 unknown, 1 car, 2 pedestrian, 3 cyclist) of a spec class name."""
    return int(_FOUR_OF_TRAIN[train_id_of(name)])

NORMALISATION_NOTE = (
    "each channel c except 'mask': (scan[..., c] - mean[c]) / std[c], then multiplied by the "
    "valid mask (range > 0); 'mask' is the valid mask itself (mean 0, std 1). Tensor 'xyz' "
    "(if named) is the raw x, y, z of the scan (zero where invalid), 'mask' (if named) is "
    "(B, 1, H, W) float32."
)


@dataclass(frozen=True)
class ModelSpec:
    """What a runner needs to feed a segmentation model and read its answer."""

    name: str
    channels: tuple[str, ...]
    mean: tuple[float, ...]
    std: tuple[float, ...]
    height: int
    width: int
    input_name: str
    output_name: str
    output_kind: str
    num_classes: int
    classes: Mapping[str, tuple[int, ...]]
    layout: str = "NCHW"
    xyz_input: str | None = None
    mask_input: str | None = None
    architecture: str = "squeezeseg"
    crf_iterations: int = 0
    notes: str = NORMALISATION_NOTE
    extra: Mapping[str, Any] = field(default_factory=dict)
    input_kind: str = "range"
    # the files exported with this spec, by role (HASHED_ROLES): their sha256, which a runner
    # checks, so that an export stopped between its files is refused, not run half old
    sha256: Mapping[str, str] = field(default_factory=dict)

    def check_fits(self, sensor: Any, model: str) -> None:
        """FalsifyError unless the sensor's range images have this model's H x W (a points
        model takes any sensor's points)."""
        if self.input_kind == "points":
            return
        if (self.height, self.width) != tuple(sensor.shape):
            raise FalsifyError(f"model {model} takes {self.height}×{self.width} range images but "
                               f"sensor {sensor.name} makes {sensor.shape[0]}×{sensor.shape[1]}")

    def four_class_outputs(self) -> list[list[int]]:
        """The output indices folded into each of our four classes, by our class id."""
        out: list[list[int]] = [[] for _ in CLASSES]
        for name, ids in self.classes.items():
            out[four_class_of(name)] += ids
        return out

    def four_class_table(self) -> np.ndarray:
        """Output index -> our class id, (num_classes,) uint8; 0 (unknown) for unmapped ones."""
        table = np.zeros(self.num_classes, np.uint8)
        for name, ids in self.classes.items():
            table[list(ids)] = four_class_of(name)
        return table

    @property
    def semantic(self) -> bool:
        """Whether the spec names any SemanticKITTI class besides our four."""
        return any(name not in CLASSES for name in self.classes)

    def train_id_table(self) -> np.ndarray:
        """Output index -> SemanticKITTI train id, (num_classes,) uint8; 0 for indices mapped
        to no train class."""
        table = np.zeros(self.num_classes, np.uint8)
        for name, ids in self.classes.items():
            table[list(ids)] = train_id_of(name)
        return table

    def to_json(self) -> str:
        """Deterministic JSON text (sorted keys) for the spec file; `input_kind` only when it
        is not the default "range" (range-model spec files keep their bytes)."""
        d = asdict(self)
        if self.input_kind == "range":
            del d["input_kind"]
        if not self.sha256:   # a spec written without its files' hashes keeps its bytes
            del d["sha256"]
        d["version"] = SPEC_VERSION
        d["classes"] = {k: list(v) if len(v) > 1 else v[0] for k, v in self.classes.items()}
        d["channels"], d["mean"], d["std"] = list(self.channels), list(self.mean), list(self.std)
        d["extra"] = dict(self.extra)
        return json.dumps(d, indent=2, sort_keys=True) + "\n"


def default_spec(name: str = "squeezeseg", channels: Sequence[str] = DEFAULT_CHANNELS,
                 height: int = 64, width: int = 512, crf_iterations: int = 3,
                 **extra: Any) -> ModelSpec:
    """The spec of our own SqueezeSeg export: channels + mask, raw xyz and mask for the CRF."""
    mean = [INPUT_MEAN[SCAN_INDEX[c]] for c in channels] + [0.0]
    std = [INPUT_STD[SCAN_INDEX[c]] for c in channels] + [1.0]
    return ModelSpec(
        name=name, channels=(*channels, "mask"), mean=tuple(mean), std=tuple(std),
        height=height, width=width, input_name="input", output_name="logits",
        output_kind="logits", num_classes=len(CLASSES),
        classes={c: (i,) for i, c in enumerate(CLASSES)},
        xyz_input="xyz" if crf_iterations else None,
        mask_input="mask" if crf_iterations else None,
        crf_iterations=crf_iterations, extra=extra,
    )


def spec_path_for(model_path: str | Path) -> Path:
    """``model.onnx`` (or ``.pt``) -> ``model.json``."""
    return Path(model_path).with_suffix(".json")


def save_spec(spec: ModelSpec, path: str | Path) -> Path:
    """Write the spec JSON atomically (a stop mid-write leaves the old spec or none, never half
    of one beside its model); returns the path."""
    path = Path(path)
    write_text(path, spec.to_json())
    return path


# What each required key holds, named when it is missing (docs/network.md has an example spec).
KEY_HINTS = {
    "name": "a name for the model, e.g. \"rangenet\"",
    "channels": f"the input channels in the network's order, names from {[*ALL_CHANNELS, 'mask']}",
    "mean": "one number per channel, subtracted before dividing by std",
    "std": "one number per channel, > 0",
    "height": "the range image's rows, e.g. 64",
    "width": "the range image's columns, e.g. 2048",
    "input_name": "the ONNX graph's input name, e.g. \"input\"",
    "output_name": "the ONNX graph's output name",
    "output_kind": f"one of {list(OUTPUT_KINDS)}",
    "num_classes": "the number of output channels, e.g. 20",
    "classes": f"class name -> output index, names from {list(SPEC_CLASSES)}",
}


def _get(d: Mapping[str, Any], key: str, path: str | Path, kind: type | tuple[type, ...],
         default: Any = ..., nullable: bool = False) -> Any:
    if key not in d:
        if default is ...:
            hint = f": {KEY_HINTS[key]}" if key in KEY_HINTS else ""
            raise FalsifyError(f"model spec {path}: missing key '{key}'{hint}")
        return default
    v = d[key]
    if v is None and nullable:
        return None
    if not isinstance(v, kind) or isinstance(v, bool) and kind is not bool:
        raise FalsifyError(f"model spec {path}: key '{key}' has invalid value {v!r}")
    return v


def load_spec(path: str | Path) -> ModelSpec:
    """Read and validate a spec JSON; FalsifyError names the file and the key on any problem."""
    path = Path(path)
    try:
        d = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise FalsifyError(
            f"model spec {path} not found (a model needs <model>.json beside it)") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise FalsifyError(f"model spec {path}: not valid JSON ({e})") from e
    return spec_from_dict(d, path)


def _class_map(raw_classes: dict, path: str | Path, num_classes: int
               ) -> dict[str, tuple[int, ...]]:
    """A spec's "classes" (name -> output index or list of indices) as name -> indices;
    FalsifyError on an unknown name, an index out of range or one index in two classes."""

    def bad(why: str) -> FalsifyError:
        return FalsifyError(f"model spec {path}: key 'classes' {why}")

    classes: dict[str, tuple[int, ...]] = {}
    for name, idx in raw_classes.items():
        if name not in SPEC_CLASSES:
            raise bad(f"has unknown class {name!r}; allowed {list(SPEC_CLASSES)}")
        ids = idx if isinstance(idx, list) else [idx]
        if not ids or not all(isinstance(i, int) and not isinstance(i, bool)
                              and 0 <= i < num_classes for i in ids):
            raise bad(f"'{name}' must map to output indices in [0, {num_classes})")
        classes[name] = tuple(ids)
    if all(name == "unknown" for name in classes):
        raise bad("must map at least one class besides 'unknown' (e.g. 'car')")
    used = [i for ids in classes.values() for i in ids]
    if len(used) != len(set(used)):
        raise bad("maps one output index to two classes")
    return classes


# Every key a spec may hold: a misspelt one ("num_class") is an error, not a default.
SPEC_KEYS = frozenset({
    "name", "version", "input_kind", "channels", "mean", "std", "height", "width", "layout",
    "input_name", "output_name", "output_kind", "num_classes", "classes", "xyz_input",
    "mask_input", "architecture", "crf_iterations", "notes", "extra", "sha256"})


def spec_from_dict(d: Any, path: str | Path) -> ModelSpec:
    """Validate spec data (as a spec file holds it); FalsifyError names `path` (the file, or
    what the data came from) and the key on any problem.

    A "points" spec may leave out what only range images need: channels (x, y, z, intensity),
    mean 0 and std 1 (the raw values), height and width (0: any sensor), input_name "points",
    output_name "logits" and output_kind "logits"."""
    if not isinstance(d, dict):
        raise FalsifyError(f"model spec {path}: top level must be a JSON object")

    def bad(key: str, why: str) -> FalsifyError:
        return FalsifyError(f"model spec {path}: key '{key}' {why}")

    unknown = sorted(set(d) - SPEC_KEYS)
    if unknown:
        raise FalsifyError(f"model spec {path}: unknown key {unknown[0]!r}; allowed: "
                           f"{', '.join(sorted(SPEC_KEYS))} (anything of your own goes in "
                           "'extra')")
    input_kind = _get(d, "input_kind", path, str, "range")
    if input_kind not in INPUT_KINDS:
        raise bad("input_kind", f"must be one of {list(INPUT_KINDS)}, got {input_kind!r}")
    points = input_kind == "points"
    if points:
        d = {"channels": list(POINT_CHANNELS), "mean": [0.0] * 4, "std": [1.0] * 4,
             "height": 0, "width": 0, "input_name": "points", "output_name": "logits",
             "output_kind": "logits", **d}
    channels = _get(d, "channels", path, list)
    if points and tuple(channels) != POINT_CHANNELS:
        raise bad("channels", f"must be {list(POINT_CHANNELS)} for a points model (its (N, 4) "
                  f"input), got {channels}")
    allowed = (*ALL_CHANNELS, "mask")
    if not channels or any(c not in allowed for c in channels) or len(set(channels)) != len(
            channels):
        raise bad("channels", f"must be distinct names from {list(allowed)}, got {channels}")
    stats = {}
    for key in ("mean", "std"):
        v = _get(d, key, path, list)
        if len(v) != len(channels) or not all(
                isinstance(x, int | float) and not isinstance(x, bool) and math.isfinite(x)
                for x in v):
            raise bad(key, f"must be {len(channels)} finite numbers (one per channel), got {v}")
        stats[key] = tuple(float(x) for x in v)
    if any(s <= 0 for s in stats["std"]):
        raise bad("std", "must be > 0")
    height = _get(d, "height", path, int)
    width = _get(d, "width", path, int)
    for key, v in (("height", height), ("width", width)):
        if v < 0 or v == 0 and not points:
            raise bad(key, f"must be > 0, got {v}")
    layout = _get(d, "layout", path, str, "NCHW")
    if layout != "NCHW":
        raise bad("layout", f"must be 'NCHW', got {layout!r}")
    kind = _get(d, "output_kind", path, str)
    if kind not in OUTPUT_KINDS:
        raise bad("output_kind", f"must be one of {list(OUTPUT_KINDS)}, got {kind!r}")
    num_classes = _get(d, "num_classes", path, int)
    if num_classes < 1:
        raise bad("num_classes", f"must be >= 1, got {num_classes}")
    classes = _class_map(_get(d, "classes", path, dict), path, num_classes)
    crf = _get(d, "crf_iterations", path, int, 0)
    if not 0 <= crf <= 3:
        raise bad("crf_iterations", f"must be 0..3, got {crf}")
    hashes = _get(d, "sha256", path, dict, {})
    for role, digest in hashes.items():
        if role not in HASHED_ROLES:
            raise bad("sha256", f"has unknown file {role!r}; allowed: {', '.join(HASHED_ROLES)}")
        if not isinstance(digest, str) or not _HEX64.fullmatch(digest):
            raise bad("sha256", f"'{role}' must be 64 lowercase hex digits, got {digest!r}")
    return ModelSpec(
        name=_get(d, "name", path, str),
        channels=tuple(channels), mean=stats["mean"], std=stats["std"],
        height=height, width=width,
        input_name=_get(d, "input_name", path, str),
        output_name=_get(d, "output_name", path, str),
        output_kind=kind, num_classes=num_classes, classes=classes, layout=layout,
        xyz_input=_get(d, "xyz_input", path, str, None, nullable=True),
        mask_input=_get(d, "mask_input", path, str, None, nullable=True),
        architecture=_get(d, "architecture", path, str, "squeezeseg"),
        crf_iterations=crf,
        notes=_get(d, "notes", path, str, NORMALISATION_NOTE),
        extra=_get(d, "extra", path, dict, {}),
        input_kind=input_kind,
        sha256=dict(hashes),
    )


def check_exported_file(spec: ModelSpec, spec_path: str | Path, path: str | Path,
                        role: str) -> None:
    """FalsifyError unless `path` is the `role` file ("onnx", "pt") its spec was written with
    (specs without the hash, older or hand-written ones, are not checked): an export killed
    between its files leaves a new spec beside an old file, which would load silently."""
    want = spec.sha256.get(role)
    if want is None:
        return
    try:
        got = file_sha256(path)
    except OSError as e:
        raise FalsifyError(f"cannot read model file {path}: {e.strerror or e}") from e
    if got != want:
        raise FalsifyError(f"{path} is not the file its spec {spec_path} was exported with "
                           f"(sha256 {got[:12]}, the spec says {want[:12]}): an export was "
                           f"stopped or one file replaced; export again (`falsify export "
                           f"WEIGHTS --out {Path(path).with_suffix('.onnx')}`)")


def load_paired_spec(path: str | Path, role: str, spec_path: str | Path | None = None
                     ) -> tuple[Path, ModelSpec]:
    """The spec of model file `path` (beside it unless given) and the spec, checked to be the
    one `path` was exported with (`check_exported_file`)."""
    spec_path = spec_path_for(path) if spec_path is None else Path(spec_path)
    spec = load_spec(spec_path)
    check_exported_file(spec, spec_path, path, role)
    return spec_path, spec


def model_hash(path: str | Path, spec_path: str | Path | None = None) -> str:
    """sha256 (hex) of the model bytes followed by the spec bytes; show the first 12 chars."""
    path = Path(path)
    spec_path = spec_path_for(path) if spec_path is None else Path(spec_path)
    h = hashlib.sha256()
    for p in (path, spec_path):
        try:
            h.update(p.read_bytes())
        except OSError as e:
            raise FalsifyError(f"cannot read model file {p}: {e.strerror or e}") from e
    return h.hexdigest()


def normalise(scans: np.ndarray, channels: Sequence[str], mean: Sequence[float],
              std: Sequence[float]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Scans (B,H,W,>=5), cast to float32 -> input (B,C,H,W), raw xyz (B,3,H,W), mask
    (B,1,H,W), all float32. Each plane is (v - mean) / std * mask computed in place in its
    output: one shared inference process does this for every worker's frames."""
    scans = np.asarray(scans, np.float32)
    b, h, w = scans.shape[:3]
    mask = np.empty((b, 1, h, w), np.float32)
    np.greater(scans[..., 4], 0, out=mask[:, 0], casting="unsafe")
    x = np.empty((b, len(channels), h, w), np.float32)
    for i, (c, m, s) in enumerate(zip(channels, mean, std, strict=True)):
        plane = x[:, i]
        if c == "mask":
            plane[...] = mask[:, 0]
            continue
        np.subtract(scans[..., SCAN_INDEX[c]], np.float32(m), out=plane)
        np.divide(plane, np.float32(s), out=plane)
        np.multiply(plane, mask[:, 0], out=plane)
    xyz = np.empty((b, 3, h, w), np.float32)
    for j in range(3):
        np.multiply(scans[..., j], mask[:, 0], out=xyz[:, j])
    return x, xyz, mask
