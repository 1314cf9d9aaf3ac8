"""Network evaluation on labelled scan sets: IoU, precision and recall per class, pooled per set
(as the official SqueezeSeg evaluation pools them) and per range band, so a gap can be located.

Ignored pixels (e.g. inside a KITTI `Van` box) count as no class's TP, FP or FN. A band holds the
valid, not ignored pixels whose measured range falls in it; invalid pixels only ever count as
unknown, so the car counts of the bands add up to the pooled car counts. Scans whose labels were
not found are predicted but never scored: read as all unknown, every car predicted on them would
count as a false positive. Labels whose scan is missing are listed beside them, never dropped
unsaid.

A network with SemanticKITTI classes on sets whose scans carry SemanticKITTI labels (`.bin` with
`.label`) is scored per train class as SemanticKITTI's evaluation scores points: pixels labelled
unlabeled are left out, and mIoU is the mean over the classes present in the labels.

Two protocols (`score`): "pixels" scores the range image's pixels, each holding its nearest point
and that point's label; "points" scores every point of a .bin scan that has a pixel with that
pixel's prediction against its own label, at its own range (RangeNet++'s and SalsaNext's
evaluation without kNN, the leaderboard's protocol); a points network is fed every such point
and each is scored with its own answer. Points without a pixel are counted apart.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np

from falsify.data.scansets import (
    ScanPoints,
    ScanSet,
    SetPlan,
    pixel_classes,
    plan_orphans,
    plan_semantic,
    point_rows,
    read_part,
)
from falsify.errors import FalsifyError
from falsify.models.runners import Segmenter
from falsify.results.metrics import CLASSES, ClassScore, Scoring, class_scores, confusion, pooled
from falsify.semantic import TRAIN_CLASSES, train_ids
from falsify.sensor.lidar import Sensor

# Range bands in metres: [lo, hi).
BANDS: tuple[tuple[float, float], ...] = ((0.0, 15.0), (15.0, 30.0), (30.0, math.inf))
CHUNK = 8   # scans per predict call
SCORES = ("pixels", "points")   # what is scored: the range image's pixels, or the scans' points


def band_name(lo: float, hi: float) -> str:
    return f"{lo:g}+ m" if math.isinf(hi) else f"{lo:g}-{hi:g} m"


@dataclass(frozen=True)
class Scores:
    """Pooled TP/FP/FN counts (n_classes, 3) and the per-class scores they give."""

    counts: np.ndarray
    classes: tuple[ClassScore, ...]

    @classmethod
    def of(cls, counts: np.ndarray) -> Scores:
        counts = np.asarray(counts, np.int64)
        names = TRAIN_CLASSES if len(counts) == len(TRAIN_CLASSES) else CLASSES
        return cls(counts, tuple(class_scores(counts, names)))

    @property
    def miou(self) -> float | None:
        """Mean IoU over the classes present in the labels (SemanticKITTI scoring only)."""
        if len(self.classes) != len(TRAIN_CLASSES):
            return None
        ious = [c.iou for c in self.classes[1:] if c.tp + c.fn > 0 and c.iou is not None]
        return float(np.mean(ious)) if ious else None

    def to_json(self) -> dict:
        out = {s.name: {"iou": s.iou, "precision": s.precision, "recall": s.recall,
                        "tp": s.tp, "fp": s.fp, "fn": s.fn, "note": s.note}
               for s in self.classes}
        if self.miou is not None:
            out["miou"] = self.miou
        return out

    def car(self) -> ClassScore:
        return self.classes[1]


@dataclass(frozen=True)
class SetEvaluation:
    """One set: scores pooled over its labelled scans, per range band, and car IoU per scan
    (None for a scan without labels)."""

    name: str
    sources: tuple[str, ...]
    pooled: Scores
    bands: tuple[tuple[str, Scores], ...]
    scan_car_iou: tuple[float | None, ...]
    ignored_pixels: int
    predictions: np.ndarray = field(repr=False)    # (B, H, W) uint8
    unlabelled: tuple[str, ...] = ()               # sources predicted but left out of the scores
    orphan_labels: tuple[str, ...] = ()            # labels of the set whose scan is missing
    score: str = "pixels"                          # the protocol: SCORES
    ignored_points: int = 0                        # "points": points counted for no class
    points_outside_image: int = 0                  # "points": points with no pixel, not scored

    @property
    def scored(self) -> int:
        """How many scans the scores count."""
        return len(self.sources) - len(self.unlabelled)

    def to_json(self) -> dict:
        missing = set(self.unlabelled)
        return {"name": self.name, "scans": len(self.sources), "scored_scans": self.scored,
                "unlabelled": list(self.unlabelled),
                "labels_without_scans": list(self.orphan_labels), "pooled": self.pooled.to_json(),
                "bands": {b: s.to_json() for b, s in self.bands},
                "ignored_pixels": self.ignored_pixels,
                **({"ignored_points": self.ignored_points,
                    "points_outside_image": self.points_outside_image}
                   if self.score == "points" else {}),
                "per_scan": [{"scan": s, "car_iou": v, "labelled": s not in missing}
                             for s, v in zip(self.sources, self.scan_car_iou, strict=True)]}


@dataclass(frozen=True)
class Evaluation:
    """A model on several sets; `pooled` and `bands` sum every set's counts."""

    model: str
    model_hash: str
    sets: tuple[SetEvaluation, ...]
    pooled: Scores
    bands: tuple[tuple[str, Scores], ...] = ()
    score: str = "pixels"   # the protocol: SCORES

    @property
    def points_outside_image(self) -> int:
        """Every set's points without a pixel ("points" protocol), never scored."""
        return sum(s.points_outside_image for s in self.sets)

    @property
    def unlabelled(self) -> tuple[str, ...]:
        """Every set's scans without labels, in order."""
        return tuple(u for s in self.sets for u in s.unlabelled)

    @property
    def orphan_labels(self) -> tuple[str, ...]:
        """Every set's labels whose scan is missing, in order."""
        return tuple(u for s in self.sets for u in s.orphan_labels)

    @property
    def labelled_sets(self) -> int:
        """How many sets have at least one scored scan."""
        return sum(1 for s in self.sets if s.scored)

    def to_json(self) -> dict:
        return {"model": self.model, "model_hash": self.model_hash, "score": self.score,
                **({"points_outside_image": self.points_outside_image}
                   if self.score == "points" else {}),
                "scans": sum(len(s.sources) for s in self.sets),
                "scored_scans": sum(s.scored for s in self.sets),
                "unlabelled": list(self.unlabelled),
                "labels_without_scans": list(self.orphan_labels),
                "pooled": self.pooled.to_json(),
                "bands": {b: s.to_json() for b, s in self.bands},
                "sets": [s.to_json() for s in self.sets]}


def band_counts(pred: np.ndarray, label: np.ndarray, rng: np.ndarray, ignore: np.ndarray,
                bands: tuple[tuple[float, float], ...] = BANDS,
                n_classes: int = len(CLASSES)) -> np.ndarray:
    """(n_bands, n_classes, 3) TP/FP/FN of the valid, not ignored pixels in each range band."""
    out = np.zeros((len(bands), n_classes, 3), np.int64)
    keep = (rng > 0) & ~ignore
    for i, (lo, hi) in enumerate(bands):
        m = keep & (rng >= lo) & (rng < hi)
        out[i] = confusion(pred[m], label[m], n_classes)
    return out


def semantic_scoring(model: Segmenter, sets: list[ScanSet]) -> bool:
    """Score per SemanticKITTI class: the model predicts SemanticKITTI's classes and every set's
    scans carry SemanticKITTI labels (else the four-class view is scored)."""
    return bool(sets) and all(s.semantic is not None for s in sets) and predicts_semantic(model)


def predicts_semantic(model: Segmenter) -> bool:
    """Whether the model's classes are SemanticKITTI's (scored per train class)."""
    classes = getattr(model.spec, "classes", None)
    return bool(classes) and Scoring.of(list(classes), "miou").semantic


def scored_labels(label: np.ndarray, raw: np.ndarray | None, ignore: np.ndarray,
                  semantic: bool) -> tuple[np.ndarray, np.ndarray]:
    """The class each pixel or point is scored against and whether it is left out, one rule for
    both protocols: the SemanticKITTI train id of its raw id with `semantic` (unlabeled left
    out), else its four-class id; `ignore` (an ignored box's) is always left out."""
    if semantic:
        train = train_ids(raw).astype(np.uint8)
        return train, ignore | (train == 0)
    return np.asarray(label).astype(np.uint8), ignore


def _scan_counts(pred: np.ndarray, label: np.ndarray, rng: np.ndarray, ignore: np.ndarray,
                 bands: tuple[tuple[float, float], ...], n: int) -> tuple[np.ndarray, np.ndarray]:
    """One scan's pooled (n, 3) and per-band (n_bands, n, 3) counts, pixels or points alike."""
    keep = ~ignore
    return (confusion(pred[keep], label[keep], n),
            band_counts(pred, label, rng, ignore, bands, n))


def _point_arrays(pred: np.ndarray, points: ScanPoints, semantic: bool
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(prediction, label, range, ignore) per point: each takes its pixel's prediction."""
    label, ignore = scored_labels(points.label, points.semantic, points.ignore, semantic)
    return pred.reshape(-1)[points.pixel], label, points.range, ignore


def evaluate_set(model: Segmenter, scans: ScanSet,
                 bands: tuple[tuple[float, float], ...] = BANDS,
                 semantic: bool = False, score: str = "pixels") -> SetEvaluation:
    """Run `model` on every scan of one set and pool the labelled scans' counts overall and per
    band (per SemanticKITTI train class with `semantic`, unlabeled left out), over the range
    image's pixels or, with score="points", over every point that has a pixel."""
    if score not in SCORES:
        raise ValueError(f"score {score!r}: expected one of {', '.join(SCORES)}")
    if score == "points" and scans.points is None:
        raise ValueError(f"set {scans.name}: read without its points (load_sets(points=True))")
    preds = []
    for i in range(0, len(scans), CHUNK):
        p = model.predict(scans.images[i:i + CHUNK])
        preds.append(p.train_ids if semantic else p.classes)
    pred = np.concatenate(preds).astype(np.uint8)
    rng = scans.images[..., 4]
    label, ignore = scored_labels(np.where(rng > 0, scans.images[..., 5], 0),
                                  None if scans.semantic is None
                                  else np.where(rng > 0, scans.semantic, 0),
                                  scans.ignore, semantic)
    n = len(TRAIN_CLASSES) if semantic else len(CLASSES)
    labelled = scans.labelled()
    totals, per_scan = [], []
    band_sum = np.zeros((len(bands), n, 3), np.int64)
    ignored_points = outside = 0
    for k in range(len(scans)):
        if not labelled[k]:
            per_scan.append(None)
            continue
        if score == "points":
            pts = scans.points[k]
            p_k, l_k, r_k, i_k = _point_arrays(pred[k], pts, semantic)
            ignored_points += int(pts.ignore.sum())
            outside += pts.outside
        else:
            p_k, l_k, r_k, i_k = pred[k], label[k], rng[k], ignore[k]
        c, b = _scan_counts(p_k, l_k, r_k, i_k, bands, n)
        totals.append(c)
        per_scan.append(Scores.of(c).car().iou)
        band_sum += b
    return SetEvaluation(
        scans.name, scans.sources, Scores.of(pooled(totals)), _band_scores(band_sum, bands),
        tuple(per_scan), int(scans.ignore[labelled].sum()), pred, scans.unlabelled,
        scans.orphan_labels, score, ignored_points, outside)


def evaluate(model: Segmenter, sets: list[ScanSet],
             bands: tuple[tuple[float, float], ...] = BANDS,
             score: str = "pixels") -> Evaluation:
    """Evaluate `model` on each set (scores pooled per set, per band) and on all together, over
    pixels or points (`score`, SCORES)."""
    semantic = semantic_scoring(model, sets)
    results = tuple(_scored_set(model, s, bands, semantic, score) for s in sets)
    return _evaluation(model, results, bands, semantic, score)


def _scored_set(model: Segmenter, scans: ScanSet, bands: tuple[tuple[float, float], ...],
                semantic: bool, score: str) -> SetEvaluation:
    """One set's evaluation: a points network fed its points when scored per point."""
    if score == "points" and model.spec.input_kind == "points":
        return _points_network_set(model, scans, bands, semantic)
    return evaluate_set(model, scans, bands, semantic, score)


def _evaluation(model: Segmenter, results: tuple[SetEvaluation, ...],
                bands: tuple[tuple[float, float], ...], semantic: bool,
                score: str) -> Evaluation:
    """The sets' evaluations with every set's counts pooled, overall and per band."""
    return Evaluation(model.spec.name, model.model_hash, results,
                      Scores.of(pooled([r.pooled.counts for r in results])),
                      _band_scores(_band_sum(results, bands, semantic), bands), score)


def _band_sum(results, bands: tuple[tuple[float, float], ...], semantic: bool) -> np.ndarray:
    """The per-band counts of `results` (set or part evaluations) summed."""
    n = len(TRAIN_CLASSES) if semantic else len(CLASSES)
    total = np.zeros((len(bands), n, 3), np.int64)
    for r in results:
        total += np.stack([sc.counts for _, sc in r.bands])
    return total


# Scans read, predicted and handed on at a time by `evaluate_plans`: a SemanticKITTI sequence of
# 4,071 scans held whole took about 7 GB (14 GB scored per point), 1.7 and 3.3 MB a scan.
PART = 64


def evaluate_plans(model: Segmenter, plans: list[SetPlan], sensor: Sensor,
                   bands: tuple[tuple[float, float], ...] = BANDS, score: str = "pixels",
                   part: int | None = None,
                   on_part: Callable[[int, ScanSet, SetEvaluation], None] | None = None
                   ) -> Evaluation:
    """`evaluate` on the planned sets, `part` (default PART) scans read at a time: each part is
    read, predicted and handed to `on_part` (its set's index, its scans, their evaluation with
    predictions), then dropped. A set's scores are its parts' counts summed: the numbers
    `evaluate` gives on the whole sets, whose protocol (per SemanticKITTI class or not) is
    decided from the plans."""
    part = part or PART
    semantic = (bool(plans) and all(plan_semantic(p) for p in plans)
                and predicts_semantic(model))
    shape = None
    results = []
    for k, plan in enumerate(plans):
        parts = []
        for i in range(0, len(plan.files), part):
            scans = read_part(plan, list(plan.files[i:i + part]), sensor, score == "points")
            if shape is None:
                shape = scans.images.shape[1:]
            elif scans.images.shape[1:] != shape:
                raise FalsifyError(f"scans have different shapes: "
                                   f"{sorted({shape, scans.images.shape[1:]})}")
            if semantic and scans.semantic is None:   # a part of unlabelled scans only
                scans = replace(scans, semantic=np.zeros(scans.images.shape[:3], np.uint16))
            r = _scored_set(model, scans, bands, semantic, score)
            if on_part is not None:
                on_part(k, scans, r)
            parts.append(replace(r, predictions=np.zeros((0,), np.uint8)))
        results.append(_merged(parts, plan_orphans(plan), bands, semantic))
    return _evaluation(model, tuple(results), bands, semantic, score)


def _merged(parts: list[SetEvaluation], orphans: tuple[str, ...],
            bands: tuple[tuple[float, float], ...], semantic: bool) -> SetEvaluation:
    """One set's evaluation from its parts': counts summed, per-scan lists joined in order."""
    return SetEvaluation(
        parts[0].name, tuple(s for p in parts for s in p.sources),
        Scores.of(pooled([p.pooled.counts for p in parts if p.scored])),
        _band_scores(_band_sum(parts, bands, semantic), bands),
        tuple(v for p in parts for v in p.scan_car_iou),
        sum(p.ignored_pixels for p in parts), np.zeros((0,), np.uint8),
        tuple(u for p in parts for u in p.unlabelled), orphans, parts[0].score,
        sum(p.ignored_points for p in parts), sum(p.points_outside_image for p in parts))


def _points_network_set(model: Segmenter, scans: ScanSet,
                        bands: tuple[tuple[float, float], ...], semantic: bool) -> SetEvaluation:
    """A points network scored per point: fed every point of each scan that has a pixel, each
    scored with its own answer (`point_rows`), not with the answer of the nearer point that
    won its pixel; its predictions come back per pixel (the class of the point each pixel
    holds) for the pictures and .pred.npy files."""
    r = evaluate_set(model, point_rows(scans), bands, semantic, "points")
    pixels = np.stack([pixel_classes(p, r.predictions[k, 0, :len(p.pixel)],
                                     scans.images.shape[1:3])
                       for k, p in enumerate(scans.points)])
    return replace(r, predictions=pixels,
                   ignored_pixels=int(scans.ignore[scans.labelled()].sum()))


def _band_scores(counts: np.ndarray, bands: tuple[tuple[float, float], ...]
                 ) -> tuple[tuple[str, Scores], ...]:
    return tuple((band_name(lo, hi), Scores.of(counts[i])) for i, (lo, hi) in enumerate(bands))
