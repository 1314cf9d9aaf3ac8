"""Per-class IoU, precision and recall, with the official SqueezeSeg evaluation's definitions.

IoU = TP / (TP + FP + FN), precision = TP / (TP + FP), recall = TP / (TP + FN). The official
evaluation pools TP, FP and FN over the whole set (`pooled`), then divides; invalid pixels are
label 0 and prediction 0 (set by the caller), so they count as "unknown". A ratio whose denominator
is 0 is undefined: None with a note, never 0 or 1.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from enum import StrEnum

import numpy as np

from falsify.classes import CAR, CLASSES
from falsify.errors import ConfigError
from falsify.semantic import TRAIN_CLASSES, kitti4, train_ids


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
    # Rows: label, columns: prediction; both int64 (int64 + uint64 would be float64, which
    # bincount refuses).
    joint = (label.astype(np.int64, copy=False).ravel() * n_classes
             + pred.astype(np.int64, copy=False).ravel())
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


def class_scores(counts: np.ndarray, names: tuple[str, ...] = CLASSES) -> list[ClassScore]:
    """IoU, precision and recall per class from (n_classes, 3) TP, FP, FN counts; `names` are
    the classes by id."""
    counts = np.asarray(counts)
    if counts.ndim != 2 or counts.shape[1] != 3:
        raise ValueError(f"counts must have shape (n_classes, 3), got {counts.shape}")
    out = []
    for i, (tp, fp, fn) in enumerate(counts.tolist()):
        name = names[i] if i < len(names) else f"class {i}"
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


PARTS = ("inserted_iou", "inserted_recall", "real_iou", "real_recall")

# Our four classes' names for SemanticKITTI's, and back: one objective name works either way.
TO_KITTI4 = {"person": "pedestrian", "bicyclist": "cyclist"}
_TO_TRAIN = {v: k for k, v in TO_KITTI4.items()}


def column(name: str) -> str:
    """A class name as a column prefix (SQL-safe: 'traffic-sign' -> 'traffic_sign')."""
    return name.replace("-", "_")


@dataclass(frozen=True)
class Scoring:
    """What a run scores: the classes by id (id 0 is unknown / unlabeled), which of them get
    columns, and the objective its samplers minimise (a class or "miou", the mean IoU over the
    scored classes the model maps (`judged`), other than id 0, that a sample's label or
    prediction holds).

    Four-class scoring (our SqueezeSeg networks) counts every pixel, empty ones as unknown, as
    SqueezeSeg's own evaluation does. SemanticKITTI scoring ignores pixels labelled unlabeled
    (id 0, empty pixels too), as SemanticKITTI's evaluation does.
    """

    classes: tuple[str, ...] = CLASSES
    scored: tuple[str, ...] = CLASSES
    objective: str = "car"
    # Real backgrounds: the objective class scored apart on the inserted objects (the real
    # ones left out) and on the real ones (the inserted left out), as PARTS columns.
    parts: bool = False
    # Real backgrounds whose placed actors are of several classes: each of these scored apart
    # on the inserted objects too, as inserted_<class>_iou and _recall columns.
    placed: tuple[str, ...] = ()
    # The classes the model's spec maps, which "miou" averages (empty: all of `scored`): a
    # four-class model scores all four, but a class it cannot predict is not its failure.
    judged: tuple[str, ...] = ()

    @classmethod
    def of(cls, mapped: Sequence[str], objective: str = "car") -> Scoring:
        """The scoring for a model whose spec maps `mapped` class names; ConfigError names an
        objective the model cannot be scored on, with the allowed ones."""
        if all(n in CLASSES for n in mapped):
            # a four-class model scores all four, but is judged only on those its spec maps
            classes, scored, judged = CLASSES, CLASSES, tuple(mapped)
            objective = TO_KITTI4.get(objective, objective)
        else:
            names = {_TO_TRAIN.get(n, n) for n in mapped}
            classes = TRAIN_CLASSES
            scored = judged = tuple(n for n in TRAIN_CLASSES[1:] if n in names)
            objective = _TO_TRAIN.get(objective, objective)
        allowed = [n for n in scored
                   if n in judged and n not in ("unknown", "unlabeled")] + ["miou"]
        if objective not in allowed:
            raise ConfigError(f"--objective: {objective!r} is not a class this model "
                              f"predicts; allowed: {', '.join(allowed)}")
        # only miou reads `judged`; left empty where it changes nothing, so that a car run's
        # Scoring stays equal to CAR_SCORING (its metadata as before)
        narrower = objective == "miou" and not set(scored) <= set(judged)
        return cls(classes, scored, objective,
                   judged=tuple(n for n in scored if n in judged) if narrower else ())

    @staticmethod
    def placed_classes(mapped: Sequence[str], semantics: Iterable[int]) -> list[str]:
        """The classes of the placed objects (raw SemanticKITTI ids) in the model's classes
        (four-class or SemanticKITTI's), sorted, unknown and unlabeled included."""
        ids = np.array(sorted(set(semantics)), np.int64)
        four = all(n in CLASSES for n in mapped)
        return sorted({CLASSES[c] for c in kitti4(ids)} if four
                      else {TRAIN_CLASSES[c] for c in train_ids(ids)})

    @staticmethod
    def placed_class(mapped: Sequence[str], semantics: Iterable[int]) -> str:
        """The class a run scores by default: that of the placed objects; ConfigError when they
        are of several classes or of one the model counts as unknown."""
        names = Scoring.placed_classes(mapped, semantics)
        if len(names) == 1 and names[0] not in ("unknown", "unlabeled"):
            return names[0]
        raise ConfigError("--objective: the placed actors are " + ", ".join(names) + " in this "
                          "model's classes; name the class to minimise (allowed: " + ", ".join(
                              n for n in mapped if n not in ("unknown", "unlabeled")) + ", miou)")

    @property
    def semantic(self) -> bool:
        return self.classes is TRAIN_CLASSES or self.classes == TRAIN_CLASSES

    @property
    def columns(self) -> list[str]:
        """The per-sample metric columns: tp, fp, fn, iou, precision, recall per scored class,
        then miou where the objective is miou or the classes are SemanticKITTI's."""
        cols = [f"{column(c)}_{m}" for c in self.scored
                for m in ("tp", "fp", "fn", "iou", "precision", "recall")]
        cols += ["miou"] if self.semantic or self.objective == "miou" else []
        if self.parts:
            cols += list(PARTS) if self.objective != "miou" else []
            cols += [f"inserted_{column(c)}_{m}" for c in self.placed for m in ("iou", "recall")]
        return cols

    @property
    def score_column(self) -> str:
        """The column the samplers minimise."""
        return "miou" if self.objective == "miou" else f"{column(self.objective)}_iou"

    def score(self, pred: np.ndarray, truth: np.ndarray, inserted: np.ndarray | None = None,
              real_labelled: bool = True) -> tuple[dict[str, float | int | None], str]:
        """Per-sample metrics of class-id images `pred` and `truth` (ids into `classes`) and, when
        the objective is undefined, why; `inserted` marks the pixels of inserted objects (the
        PARTS columns need it); `real_labelled` False: the background's own objects carry no
        labels (a real scan without them), so the real_ columns are left empty."""
        pred = np.asarray(pred)
        truth = np.asarray(truth)
        parts = {}
        if self.parts:
            parts = self.part_scores(pred, truth, inserted, real_labelled)
        if self.semantic:
            keep = truth != 0
            pred, truth = pred[keep], truth[keep]
        counts = confusion(pred, truth, len(self.classes))
        metrics: dict[str, float | int | None] = {}
        notes: dict[str, str] = {}
        ious: list[float] = []
        for cs in class_scores(counts, self.classes):
            if cs.name not in self.scored:
                continue
            for m in ("tp", "fp", "fn", "iou", "precision", "recall"):
                metrics[f"{column(cs.name)}_{m}"] = getattr(cs, m)
            notes[cs.name] = cs.note
            if (cs.iou is not None and cs.name not in ("unknown", "unlabeled")
                    and cs.name in (self.judged or self.scored)):
                ious.append(cs.iou)
        if "miou" in self.columns:
            metrics["miou"] = float(np.mean(ious)) if ious else None
        metrics.update(parts)
        if self.objective == "miou":
            return metrics, ("" if ious else
                             "no class the model predicts in label or prediction")
        return metrics, notes[self.objective]

    def part_scores(self, pred: np.ndarray, truth: np.ndarray, inserted: np.ndarray | None,
                    real_labelled: bool = True) -> dict[str, float | None]:
        """IoU and recall of the objective class on the inserted objects (the real pixels of
        that class left out; None where no inserted point is of that class) and on the real
        ones (the inserted pixels left out; None where the background is not `real_labelled`:
        its objects are unknown, not absent); unlabeled pixels are left out where the classes
        are SemanticKITTI's."""
        ins = np.zeros(truth.shape, bool) if inserted is None else np.asarray(inserted, bool)
        labelled = truth != 0 if self.semantic else np.ones(truth.shape, bool)
        out: dict[str, float | None] = {}

        def part(prefix: str, c: int, keep: np.ndarray) -> None:
            keep = keep & labelled
            p, t = pred[keep] == c, truth[keep] == c
            tp, fp, fn = int((p & t).sum()), int((p & ~t).sum()), int((~p & t).sum())
            # A placed object's IoU is undefined where no placed point is of class c (a cyclist
            # sample's inserted_pedestrian_iou): the scan's false positives alone made it 0.
            placed_none = prefix.startswith("inserted") and tp + fn == 0
            out[f"{prefix}_iou"] = None if placed_none else _ratio(tp, tp + fp + fn)
            out[f"{prefix}_recall"] = _ratio(tp, tp + fn)

        if self.objective != "miou":
            c = self.classes.index(self.objective)
            part("inserted", c, ~((truth == c) & ~ins))
            if real_labelled:
                part("real", c, ~ins)
            else:
                out["real_iou"] = out["real_recall"] = None
        for name in self.placed:
            c = self.classes.index(name)
            part(f"inserted_{column(name)}", c, ~((truth == c) & ~ins))
        return out
