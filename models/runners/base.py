"""What every segmentation runner shares: the Segmenter protocol, the Prediction it returns,
the bundled model's paths, input checks, and the mapping from model outputs to our classes.

Predictions are in our class ids: 0 unknown, 1 car, 2 pedestrian, 3 cyclist, with
SemanticKITTI's train ids beside them; invalid pixels (range == 0) are always 0.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Protocol

import numpy as np

from falsify.classes import CLASSES
from falsify.errors import FalsifyError
from falsify.models.spec import (
    POINT_CHANNELS,
    SCAN_INDEX,
    ModelSpec,
    load_paired_spec,
    model_hash,
    normalise,
)

WEIGHTS_DIR = Path(__file__).resolve().parent.parent / "weights"
CARDS_DIR = Path(__file__).resolve().parent.parent / "cards"   # one model card per network, shipped
BUNDLED_ONNX = WEIGHTS_DIR / "squeezeseg.onnx"
BUNDLED_PT = WEIGHTS_DIR / "squeezeseg.pt"
# Frames per forward pass. Both backends run SqueezeSeg fastest one frame at a time on the 2-core
# EPYC: the activations stay in cache (fp32 with CRF, ONNX Runtime 1 thread: 46 ms/frame at
# batch 1 against 54 at 8; 2 threads: 25 against 35; torch 2 threads: 52 against 105).
BATCH = 1
BACKENDS = ("onnx", "torch", "python")


@dataclass(frozen=True)
class Prediction:
    """Per-pixel classes (B,H,W) uint8 in our ids; on demand ``probabilities`` (B,H,W,4)
    float32 and ``train_ids`` (B,H,W) uint8, SemanticKITTI's train id of the top output index (0
    where that index maps to no train class, and on invalid pixels).

    The pipeline needs only the classes; the probabilities cost 1.5 ms/frame, so they are
    computed the first time they are read.
    """

    classes: np.ndarray
    raw: np.ndarray = field(repr=False)
    spec: ModelSpec = field(repr=False)
    valid: np.ndarray = field(repr=False)

    @cached_property
    def probabilities(self) -> np.ndarray:
        return _our_probabilities(self.raw, self.spec, self.valid)

    @cached_property
    def train_ids(self) -> np.ndarray:
        ids = self.spec.train_id_table()[np.asarray(self.raw).argmax(axis=1)]
        ids[~self.valid] = 0
        return ids


class Segmenter(Protocol):
    """What the rest of falsify calls: a spec, a content hash and ``predict``."""

    spec: ModelSpec
    model_hash: str

    def predict(self, scans: np.ndarray) -> Prediction: ...


def check_scans(scans: np.ndarray, spec: ModelSpec, source: Path) -> np.ndarray:
    """(H,W,C) or (B,H,W,C) with C >= 5 -> float32 (B,H,W,C); FalsifyError on shape or NaN/inf."""
    a = np.asarray(scans)
    if a.ndim == 3:
        a = a[None]
    any_size = spec.input_kind == "points"
    if a.ndim != 4 or not any_size and a.shape[1:3] != (spec.height, spec.width) or (
            a.shape[3] < 5):
        if any_size:
            raise FalsifyError(f"model {source} expects scans of shape (B, H, W, 6) (x, y, z, "
                               f"intensity, range, label), got {tuple(np.shape(scans))}")
        raise FalsifyError(
            f"model {source} expects scans of shape (B, {spec.height}, {spec.width}, 6) "
            f"(x, y, z, intensity, range, label), got {tuple(np.shape(scans))}")
    if not np.issubdtype(a.dtype, np.number):
        raise FalsifyError(f"model {source}: scans must be numeric, got dtype {a.dtype}")
    a = a.astype(np.float32, copy=False)
    if not np.isfinite(a[..., :5]).all():
        bad = np.argwhere(~np.isfinite(a[..., :5]))[0]
        raise FalsifyError(f"model {source}: scan input holds NaN or inf (first at batch, row, "
                           f"col, channel = {tuple(int(i) for i in bad)}); refusing to score it")
    return a


def _our_probabilities(out: np.ndarray, spec: ModelSpec, valid: np.ndarray) -> np.ndarray:
    """Model output (B,K,H,W) -> (B,H,W,4) probabilities of our classes; unmapped outputs count
    as unknown, invalid pixels are certain unknown."""
    out = out.astype(np.float32, copy=False)
    if spec.output_kind == "logits":
        e = np.exp(out - out.max(axis=1, keepdims=True))
        p = e / e.sum(axis=1, keepdims=True)
    else:
        p = out
    ours = np.zeros((p.shape[0], len(CLASSES), *p.shape[2:]), np.float32)
    used = set()
    for j, ids in enumerate(spec.four_class_outputs()):
        for i in ids:
            ours[:, j] += p[:, i]
            used.add(i)
    for i in range(p.shape[1]):
        if i not in used:
            ours[:, 0] += p[:, i]
    probs = np.ascontiguousarray(np.moveaxis(ours, 1, -1))
    probs[~valid] = np.eye(len(CLASSES), dtype=np.float32)[0]
    return probs


def _one_to_one(spec: ModelSpec) -> list[int] | None:
    """The model output index of each of our classes when every output is exactly one of ours."""
    order = spec.four_class_outputs()
    flat = [i for o in order for i in o]
    if all(len(o) == 1 for o in order) and sorted(flat) == list(range(spec.num_classes)):
        return flat
    return None


def check_finite(out: np.ndarray, valid: np.ndarray, source: Path | str) -> np.ndarray:
    """`out` (B, K, H, W) unchanged, or a FalsifyError naming `source` when a valid pixel has a
    NaN or infinite score: argmax would read it as some class and score it as an answer."""
    out = np.asarray(out)
    if not np.issubdtype(out.dtype, np.floating) or np.isfinite(out).all():
        return out
    bad = ~np.isfinite(out).all(axis=1) & valid
    if bad.any():
        raise FalsifyError(f"model {source}: its output has NaN or inf scores on "
                           f"{int(bad.sum()):,} valid pixels of {int(valid.sum()):,}; "
                           "refusing to score them")
    return out


def to_prediction(out: np.ndarray, spec: ModelSpec, valid: np.ndarray) -> Prediction:
    """Model output (B,K,H,W) -> Prediction in our 4 classes; invalid pixels are unknown.
    Spec names fold into ours as `falsify.models.spec.four_class_of` says (person is
    pedestrian, bicyclist cyclist; SemanticKITTI's other classes unknown).

    With one model output per class of ours, the classes are the argmax of the raw output
    (softmax keeps the order). A spec in SemanticKITTI's names: the top output's class folded
    into ours, as its labels are folded, so `classes` agrees with `train_ids`. Otherwise the
    argmax of the summed probabilities."""
    order = _one_to_one(spec)
    if order is not None:   # in our order already (the bundled networks): no copy to reorder
        out = np.asarray(out)
        ours = out if order == list(range(len(order))) else out[:, order]
        classes = ours.argmax(axis=1).astype(np.uint8)
    elif spec.semantic:
        classes = spec.four_class_table()[np.asarray(out).argmax(axis=1)]
    else:
        classes = _our_probabilities(out, spec, valid).argmax(axis=-1).astype(np.uint8)
    classes[~valid] = 0
    return Prediction(classes=classes, raw=out, spec=spec, valid=valid)


def feeds(spec: ModelSpec, scans: np.ndarray) -> dict[str, np.ndarray]:
    """A range model's inputs for scans: the normalised channels, and the xyz and mask inputs
    where its spec names them."""
    x, xyz, mask = normalise(scans, spec.channels, spec.mean, spec.std)
    out = {spec.input_name: x}
    if spec.xyz_input:
        out[spec.xyz_input] = xyz
    if spec.mask_input:
        out[spec.mask_input] = mask
    return out


def open_model(path: str | Path, spec_path: str | Path | None, role: str
               ) -> tuple[Path, Path, ModelSpec, str]:
    """The model file, its spec (beside it unless given) and their content hash; the file is
    checked to be the `role` file ("onnx", "pt") the spec was exported with, where it says."""
    path = Path(path)
    if not path.is_file():
        raise FalsifyError(f"model file {path} not found")
    spec_path, spec = load_paired_spec(path, role, spec_path)
    return path, spec_path, spec, model_hash(path, spec_path)


def points_of(scan: np.ndarray, valid: np.ndarray, spec: ModelSpec) -> np.ndarray:
    """A scan's valid pixels as (N, 4) float32 points (x, y, z, intensity), row-major pixel
    order, each column as (value - mean) / std of the spec (raw values for mean 0, std 1)."""
    pts = scan[valid][:, [SCAN_INDEX[c] for c in POINT_CHANNELS]]
    if any(spec.mean) or any(s != 1 for s in spec.std):
        pts = (pts - np.float32(spec.mean)) / np.float32(spec.std)
    return np.ascontiguousarray(pts, dtype=np.float32)


def scatter(per_scan: list[np.ndarray | None], valid: np.ndarray, classes: int) -> np.ndarray:
    """Per-scan point scores (N, K) back onto their pixels: (B, K, H, W) float32, 0 on invalid
    pixels and for scans given as None (no point)."""
    out = np.zeros((valid.shape[0], classes, *valid.shape[1:]), np.float32)
    for b, scores in enumerate(per_scan):
        if scores is not None:
            rows, cols = np.nonzero(valid[b])
            out[b][:, rows, cols] = scores.T
    return out
