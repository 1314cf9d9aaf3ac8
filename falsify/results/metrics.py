"""Per-class IoU, precision and recall, with the official SqueezeSeg evaluation's definitions.

IoU = TP / (TP + FP + FN), precision = TP / (TP + FP), recall = TP / (TP + FN). The official
evaluation pools TP, FP and FN over the whole set (`pooled`), then divides; invalid pixels are
label 0 and prediction 0 (set by the caller), so they count as "unknown". A ratio whose denominator
is 0 is undefined: None with a note, never 0 or 1.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from enum import StrEnum

import numpy as np

from falsify.classes import CAR, CLASSES


class Status(StrEnum):
    """What became of a sample; stored as its value in the `status` column."""

    OK = "ok"                   # scored: car IoU defined
    UNDEFINED = "undefined"     # cast and predicted, but car IoU has an empty union
    INVALID = "invalid"         # the scene cannot exist (cars intersect)


def confusion(pred: np.ndarray, label: np.ndarray, n_classes: int = 4) -> np.ndarray:
    """TP, FP, FN per class as an (n_classes, 3) int64 array; pred and label: class ids, any
    shape (the same for both)."""
    pred = np.asarray(pred)
    label = np.asarray(label)
    if pred.shape != label.shape:
        raise ValueError(f"pred shape {pred.shape} != label shape {label.shape}")
    if pred.size == 0:
        return np.zeros((n_classes, 3), np.int64)
    for what, a in (("pred", pred), ("label", label)):
        if not np.issubdtype(a.dtype, np.integer):
            raise ValueError(f"{what} must hold integer class ids, got dtype {a.dtype}")
        lo, hi = int(a.min()), int(a.max())
        if lo < 0 or hi >= n_classes:
            bad = lo if lo < 0 else hi
            raise ValueError(f"{what} holds class id {bad}; allowed 0..{n_classes - 1}")
    # Rows: label, columns: prediction.
    joint = label.astype(np.int64, copy=False).ravel() * n_classes + pred.ravel()
    matrix = np.bincount(joint, minlength=n_classes * n_classes).reshape(n_classes, n_classes)
    tp = np.diagonal(matrix)
    out = np.empty((n_classes, 3), np.int64)
    out[:, 0] = tp
    out[:, 1] = matrix.sum(axis=0) - tp
    out[:, 2] = matrix.sum(axis=1) - tp
    return out


@dataclass(frozen=True)
class ClassScore:
    """One class's counts and ratios; a ratio is None when undefined, and `note` says why."""

    name: str
    tp: int
    fp: int
    fn: int
    iou: float | None
    precision: float | None
    recall: float | None
    note: str


def class_scores(counts: np.ndarray) -> list[ClassScore]:
    """IoU, precision and recall per class from (n_classes, 3) TP, FP, FN counts."""
    counts = np.asarray(counts)
    if counts.ndim != 2 or counts.shape[1] != 3:
        raise ValueError(f"counts must have shape (n_classes, 3), got {counts.shape}")
    out = []
    for i, (tp, fp, fn) in enumerate(counts.tolist()):
        name = CLASSES[i] if i < len(CLASSES) else f"class {i}"
        notes = []
        if tp + fp + fn == 0:
            notes.append(f"no {name} in label or prediction")
        else:
            if tp + fp == 0:
                notes.append(f"no {name} predicted")
            if tp + fn == 0:
                notes.append(f"no {name} in label")
        out.append(ClassScore(name, tp, fp, fn, _ratio(tp, tp + fp + fn), _ratio(tp, tp + fp),
                              _ratio(tp, tp + fn), "; ".join(notes)))
    return out


def class_iou(counts: np.ndarray, class_id: int = CAR) -> float | None:
    """One class's IoU from (n_classes, 3) counts (default: car); None when undefined."""
    tp, fp, fn = (int(v) for v in np.asarray(counts)[class_id])
    return _ratio(tp, tp + fp + fn)


def pooled(counts_list: Iterable[np.ndarray]) -> np.ndarray:
    """Sum of (n_classes, 3) counts over a set, as the official evaluation pools them."""
    arrays = [np.asarray(c, np.int64) for c in counts_list]
    if not arrays:
        return np.zeros((len(CLASSES), 3), np.int64)
    shapes = {a.shape for a in arrays}
    if len(shapes) != 1:
        raise ValueError(f"counts of different shapes: {sorted(shapes)}")
    return np.sum(arrays, axis=0, dtype=np.int64)


def _ratio(num: int, den: int) -> float | None:
    return num / den if den else None
