"""How far a world is from real streets, measured by how the network fails in each.

Two finished runs over the same positions, one on our streets (the world) and one with the car
placed in real scans, compared four ways: the per-background spread of the placed car's IoU,
precision and recall (with the 1-Wasserstein distance between the runs' spreads), each street
against the real place it stands for where both runs hold it (and the floor a world of fewer
places than the real run can reach), the x × y maps of its IoU cell by
cell (which blind spots the world finds and misses), and, optionally, what the false-positive
car points of a few replayed samples lie on. Limits on the distances turn the comparison into a
check (`Limits`, `check_targets`): each target met or missed, and whether the floor leaves it
within reach.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from falsify.errors import FalsifyError
from falsify.results.metrics import Status
from falsify.results.miou_maps import CellMap, fmt_value, jaccard, miou_map
from falsify.results.store import RunData, check_complete, open_run
from falsify.world.space import EFFECT_DIMS

METRICS = ("iou", "precision", "recall")
QUANTILES = (0.1, 0.5, 0.9)
PRECISION_NOTE = ("precision is car_precision on both runs: it counts the background's own cars "
                  "(real ones, or the streets' parked ones) as true positives too")
MAX_FP_SAMPLES = 10_000


# -- statistics ------------------------------------------------------------------------------
def wasserstein1(u: Sequence[float], v: Sequence[float]) -> float | None:
    """The 1-Wasserstein distance between two empirical 1-D distributions (equal weights per
    value): W1 = ∫ |F_u(t) − F_v(t)| dt, the area between their empirical CDFs (Villani,
    "Optimal Transport: Old and New", 2009, Remark 2.19); NaNs are left out, as
    Distribution.of leaves them out beside it (one NaN would make the whole distance NaN);
    None if either is empty."""
    a = np.asarray(u, np.float64)
    b = np.asarray(v, np.float64)
    a, b = np.sort(a[np.isfinite(a)]), np.sort(b[np.isfinite(b)])
    if not len(a) or not len(b):
        return None
    both = np.sort(np.concatenate([a, b]))
    widths = np.diff(both)
    # Both CDFs are constant on each [both[k], both[k+1]): their values just right of both[k].
    fa = np.searchsorted(a, both[:-1], side="right") / len(a)
    fb = np.searchsorted(b, both[:-1], side="right") / len(b)
    return float(np.sum(np.abs(fa - fb) * widths))


@dataclass(frozen=True)
class Distribution:
    """Count, mean, extremes and 10th/50th/90th percentiles (linear interpolation, numpy's
    default) of a set of values; all None when it is empty."""

    count: int
    mean: float | None
    min: float | None
    p10: float | None
    p50: float | None
    p90: float | None
    max: float | None

    @classmethod
    def of(cls, values: Sequence[float]) -> Distribution:
        v = np.asarray(values, np.float64)
        v = v[np.isfinite(v)]
        if not len(v):
            return cls(0, None, None, None, None, None, None)
        p10, p50, p90 = (float(q) for q in np.quantile(v, QUANTILES))
        return cls(len(v), float(v.mean()), float(v.min()), p10, p50, p90, float(v.max()))

    def to_json(self) -> dict:
        return {k: _r(getattr(self, k)) for k in
                ("count", "mean", "min", "p10", "p50", "p90", "max")}


@dataclass(frozen=True)
class MetricComparison:
    """One metric of the placed car, its per-background means in each run and their W1."""

    metric: str
    world_column: str
    real_column: str
    world: Distribution
    real: Distribution
    w1: float | None
    world_values: dict[str, float]   # background name -> mean over its ok rows
    real_values: dict[str, float]

    def to_json(self) -> dict:
        return {"metric": self.metric, "world_column": self.world_column,
                "real_column": self.real_column, "world": self.world.to_json(),
                "real": self.real.to_json(), "w1": _r(self.w1),
                "world_per_background": {k: _r(v) for k, v in self.world_values.items()},
                "real_per_background": {k: _r(v) for k, v in self.real_values.items()}}


@dataclass(frozen=True)
class PlacePair:
    """One real place in both runs: the placed car's means (IoU, precision, recall) over the
    streets standing for it and over its real scan's rows."""

    place: str
    streets: int
    world: dict[str, float]
    real: dict[str, float]

    def to_json(self) -> dict:
        def num(v: float) -> float | None:
            return _r(v) if np.isfinite(v) else None

        return {"place": self.place, "streets": self.streets,
                "world": {k: num(v) for k, v in self.world.items()},
                "real": {k: num(v) for k, v in self.real.items()}}


@dataclass(frozen=True)
class PlacePairing:
    """Each street against the real place it stands for, where both runs hold the place: the
    spreads can agree while each street is as hard as another place, not its own."""

    pairs: tuple[PlacePair, ...]
    mae: dict[str, float | None]   # metric -> mean |world - real| over the pairs
    world_only: tuple[str, ...]    # places a street stands for that the real run lacks
    real_only: tuple[str, ...]

    def to_json(self) -> dict:
        return {"pairs": [p.to_json() for p in self.pairs],
                "mae": {k: _r(v) for k, v in self.mae.items()},
                "world_only": list(self.world_only), "real_only": list(self.real_only)}


@dataclass(frozen=True)
class PlaceFloor:
    """How near a world can come when its streets stand for only some of the real run's places:
    the real values of those places against all of them, as a world whose every street scored
    exactly its own place's real value would stand. Gaps at or below these are the choice of
    places, not the world."""

    places: int                    # real places the world's streets stand for
    real_places: int               # real places in the real run
    w1: dict[str, float | None]    # metric -> W1 of those places' real values against all
    p10: dict[str, float | None]   # metric -> 10th percentile of those places' real values
    map_mae: float | None          # the real map over those places' rows against the whole

    def to_json(self) -> dict:
        return {"places": self.places, "real_places": self.real_places,
                "w1": {k: _r(v) for k, v in self.w1.items()},
                "p10": {k: _r(v) for k, v in self.p10.items()}, "map_mae": _r(self.map_mae)}


@dataclass(frozen=True)
class MapAgreement:
    """The two x × y maps of the placed car's IoU over the cells both define; a cell is blind
    below `threshold`. World misses: blind in the real run only; false alarms: world only."""

    threshold: float
    cells_world: int
    cells_real: int
    cells_both: int
    mae: float | None
    pearson: float | None      # None with under 2 cells or a constant map
    blind_world: int
    blind_real: int
    agreement: float | None    # share of the common cells both call blind or both not
    world_misses: tuple[tuple[float, float], ...]
    false_alarms: tuple[tuple[float, float], ...]
    jaccard: float

    def to_json(self) -> dict:
        return {"threshold": self.threshold, "cells_world": self.cells_world,
                "cells_real": self.cells_real, "cells_both": self.cells_both,
                "mae": _r(self.mae), "pearson": _r(self.pearson),
                "blind_world": self.blind_world, "blind_real": self.blind_real,
                "agreement": _r(self.agreement),
                "world_misses": [list(c) for c in self.world_misses],
                "false_alarms": [list(c) for c in self.false_alarms],
                "jaccard": _r(self.jaccard)}


@dataclass(frozen=True)
class Limits:
    """The most each distance may be for the world to pass: W1 of the per-background IoU and
    precision, |world - real| of the per-background IoU's 10th percentile, the maps' MAE, and
    the mean |street - place| of IoU over the places both runs hold; None: not checked."""

    w1: float | None = None
    p10_gap: float | None = None
    map_mae: float | None = None
    place_mae: float | None = None


LIMIT_OPTIONS = {"w1": "--max-w1", "p10_gap": "--max-p10-gap", "map_mae": "--max-map-mae",
                 "place_mae": "--max-place-mae"}


def check_limits(limits: Limits) -> None:
    """FalsifyError naming the option whose limit is not a number in [0, 1]."""
    for key, option in LIMIT_OPTIONS.items():
        v = getattr(limits, key)
        if v is not None and not (np.isfinite(v) and 0.0 <= v <= 1.0):
            raise FalsifyError(f"{option}: {v} must be a number in [0, 1]")


@dataclass(frozen=True)
class Target:
    """One limit against its distance: met when the distance is defined and at most the limit.
    `floor` is the same distance for a world whose every street scored its own place's real
    value (None without a floor); a target whose floor exceeds its limit is out of reach for
    any world on these streets' places."""

    name: str                  # "w1 iou", "w1 precision", "p10 gap iou", "map mae", "place mae iou"
    value: float | None
    limit: float
    floor: float | None

    @property
    def met(self) -> bool:
        return self.value is not None and self.value <= self.limit

    @property
    def reachable(self) -> bool | None:
        return None if self.floor is None else self.floor <= self.limit

    def to_json(self) -> dict:
        return {"name": self.name, "value": _r(self.value), "limit": self.limit,
                "met": self.met, "floor": _r(self.floor), "reachable": self.reachable}


def check_targets(metrics: Sequence[MetricComparison], amap: MapAgreement,
                  places: PlacePairing | None, floor: PlaceFloor | None,
                  limits: Limits) -> tuple[Target, ...]:
    """The targets `limits` sets, in a fixed order (W1 of IoU and precision, the 10th
    percentile gap of IoU, the map's MAE, the per-place MAE of IoU), each with the floor's
    value beside it (0 for the per-place MAE: each street its own place's value). The per-place
    target is missed, undefined, when no place is in both runs."""
    by = {m.metric: m for m in metrics}
    out: list[Target] = []
    if limits.w1 is not None:
        for metric in ("iou", "precision"):
            out.append(Target(f"w1 {metric}", by[metric].w1, limits.w1,
                              None if floor is None else floor.w1[metric]))
    if limits.p10_gap is not None:
        iou = by["iou"]
        gap = (None if iou.world.p10 is None or iou.real.p10 is None
               else abs(iou.world.p10 - iou.real.p10))
        fl = (None if floor is None or floor.p10["iou"] is None or iou.real.p10 is None
              else abs(floor.p10["iou"] - iou.real.p10))
        out.append(Target("p10 gap iou", gap, limits.p10_gap, fl))
    if limits.map_mae is not None:
        out.append(Target("map mae", amap.mae, limits.map_mae,
                          None if floor is None else floor.map_mae))
    if limits.place_mae is not None:
        out.append(Target("place mae iou", None if places is None else places.mae["iou"],
                          limits.place_mae, None if places is None else 0.0))
    return tuple(out)


@dataclass(frozen=True)
class FalsePositives:
    """Predicted-car points whose label is not car, in `samples` replayed rows of one run, by
    the SemanticKITTI class of what they lie on."""

    run: str
    samples: int
    points: int
    by_class: dict[str, int]   # most points first
    stored_fp: int             # the rows' stored car_fp, to compare with `points`
    note: str = ""

    def to_json(self) -> dict:
        return {"run": self.run, "samples": self.samples, "points": self.points,
                "by_class": dict(self.by_class), "stored_car_fp": self.stored_fp,
                "note": self.note}


@dataclass(frozen=True)
class RunSide:
    """One of the two runs as compared: where it is, what it ran on, which columns say how the
    placed car did."""

    path: str
    real: bool
    ok_rows: int
    backgrounds: int
    iou_column: str
    recall_column: str

    def to_json(self) -> dict:
        return {"path": self.path, "backgrounds_are": "real scans" if self.real else "streets",
                "ok_rows": self.ok_rows, "backgrounds": self.backgrounds,
                "iou_column": self.iou_column, "recall_column": self.recall_column,
                "precision_column": "car_precision"}


@dataclass(frozen=True)
class AgreementResult:
    """The whole comparison of a world run with a real run."""

    world: RunSide
    real: RunSide
    metrics: tuple[MetricComparison, ...]
    map: MapAgreement
    false_positives: tuple[FalsePositives, ...]   # empty when skipped
    fp_note: str
    places: PlacePairing | None = None   # None: no place in both runs
    floor: PlaceFloor | None = None      # None: no place in both runs
    targets: tuple[Target, ...] = ()     # empty: no limit given
    precision_note: str = PRECISION_NOTE

    @property
    def passed(self) -> bool:
        """Every target met (true when there is none)."""
        return all(t.met for t in self.targets)

    def to_json(self) -> dict:
        targets = None if not self.targets else {
            "met": sum(t.met for t in self.targets), "total": len(self.targets),
            "passed": self.passed, "each": [t.to_json() for t in self.targets]}
        return {"world": self.world.to_json(), "real": self.real.to_json(), "targets": targets,
                "metrics": [m.to_json() for m in self.metrics], "map": self.map.to_json(),
                "places": None if self.places is None else self.places.to_json(),
                "floor": None if self.floor is None else self.floor.to_json(),
                "false_positives": [f.to_json() for f in self.false_positives],
                "false_positives_note": self.fp_note, "precision_note": self.precision_note}


def _r(v):
    return None if v is None else round(float(v), 6) if isinstance(v, float) else v


# -- the comparison --------------------------------------------------------------------------
def placed_columns(data: RunData) -> dict[str, str]:
    """The columns of the placed car's IoU, precision and recall: the placed car's own
    (inserted_*, the background's cars left out), else, in runs scored before streets had
    them, the car class's; FalsifyError if one is missing."""
    placed = "inserted_iou" in data.frame.columns
    cols = {"iou": "inserted_iou" if placed else "car_iou", "precision": "car_precision",
            "recall": "inserted_recall" if placed else "car_recall"}
    for c in cols.values():
        if c not in data.frame.columns:
            raise FalsifyError(f"{data.path}: samples table lacks column {c!r} (the car's "
                               "scores); was it run with the car objective?")
    return cols


def ok_rows(data: RunData) -> pd.DataFrame:
    return data.frame[data.frame["status"] == Status.OK]


def background_means(data: RunData, columns: list[str]) -> pd.DataFrame:
    """Each background's mean of `columns` over its ok rows, one row per background id (none
    for a run without a background dim or ok rows)."""
    ok = ok_rows(data)
    if "background" not in ok.columns or not len(ok):
        return pd.DataFrame(columns=columns, dtype=float)
    return ok[columns].astype(float).groupby(ok["background"], sort=True).mean()


def per_background(data: RunData, column: str) -> dict[str, float]:
    """Each background's mean of `column` over its ok rows (backgrounds where it is undefined
    in every row left out), keyed by the background's name."""
    means = background_means(data, [column])[column].dropna()
    return {_bg_name(data, bg): float(v) for bg, v in means.items()}


def _bg_name(data: RunData, bg) -> str:
    try:
        return data.space.background_name(int(bg))
    except (IndexError, TypeError, ValueError):
        return str(bg)


def _bg_place(data: RunData, bg) -> str | None:
    try:
        return data.space.background_place(int(bg))
    except (IndexError, TypeError, ValueError):
        return None


def compare_metric(world: RunData, real: RunData, metric: str) -> MetricComparison:
    wc, rc = placed_columns(world)[metric], placed_columns(real)[metric]
    wv, rv = per_background(world, wc), per_background(real, rc)
    return MetricComparison(metric, wc, rc, Distribution.of(list(wv.values())),
                            Distribution.of(list(rv.values())),
                            wasserstein1(list(wv.values()), list(rv.values())), wv, rv)


def by_place(data: RunData) -> dict[str, tuple[int, dict[str, float]]]:
    """Per real place the run's backgrounds are or stand for: how many backgrounds, and the
    mean over them of each metric's per-background mean (backgrounds of no place left out)."""
    cols = placed_columns(data)
    groups: dict[str, list[dict[str, float]]] = {}
    for bg, row in background_means(data, list(cols.values())).iterrows():
        place = _bg_place(data, bg)
        if place is not None:
            groups.setdefault(place, []).append({m: float(row[c]) for m, c in cols.items()})
    return {place: (len(rows), {m: float(np.nanmean([r[m] for r in rows]))
                                if any(np.isfinite(r[m]) for r in rows) else float("nan")
                                for m in METRICS})
            for place, rows in sorted(groups.items())}


def pair_places(world: dict[str, tuple[int, dict[str, float]]],
                real: dict[str, tuple[int, dict[str, float]]]) -> PlacePairing | None:
    """The places both sides hold, paired (see PlacePairing); None when they share none."""
    common = sorted(set(world) & set(real))
    if not common:
        return None
    pairs = tuple(PlacePair(p, world[p][0], world[p][1], real[p][1]) for p in common)
    mae = {}
    for m in METRICS:
        d = [abs(x.world[m] - x.real[m]) for x in pairs
             if np.isfinite(x.world[m]) and np.isfinite(x.real[m])]
        mae[m] = float(np.mean(d)) if d else None
    return PlacePairing(pairs, mae, tuple(sorted(set(world) - set(real))),
                        tuple(sorted(set(real) - set(world))))


def place_floor(real: RunData, places: Sequence[str], real_places: int, rmap: CellMap,
                threshold: float) -> PlaceFloor:
    """The real run's per-background values and map over the backgrounds of `places` against
    all of its own (see PlaceFloor)."""
    cols = placed_columns(real)
    means = background_means(real, list(cols.values()))
    wanted = set(places)
    mine = [bg for bg in means.index if _bg_place(real, bg) in wanted]
    w1, p10 = {}, {}
    for m, c in cols.items():
        every, part = (v[np.isfinite(v)] for v in (means[c].to_numpy(float),
                                                   means.loc[mine, c].to_numpy(float)))
        w1[m] = wasserstein1(list(part), list(every))
        p10[m] = Distribution.of(list(part)).p10
    ok = ok_rows(real)
    part_map = miou_map(ok[ok["background"].isin(mine)], real.space, "x", "y", cols["iou"])
    return PlaceFloor(len(places), real_places, w1, p10,
                      map_agreement(part_map, rmap, threshold).mae)


def check_same_grid(world: RunData, real: RunData, wmap: CellMap, rmap: CellMap) -> None:
    """FalsifyError naming both runs and the dims whose grids differ."""
    differ = []
    for dim, a, b in (("x", wmap.a_values, rmap.a_values), ("y", wmap.b_values, rmap.b_values)):
        same = len(a) == len(b) and all(abs(float(p) - float(q)) < 1e-6
                                        for p, q in zip(a, b, strict=True))
        if not same:
            differ.append(f"{dim}: [{', '.join(fmt_value(v) for v in a)}] against "
                          f"[{', '.join(fmt_value(v) for v in b)}]")
    if differ:
        raise FalsifyError(f"{world.path} and {real.path}: their x/y grids differ ("
                           f"{'; '.join(differ)}); compare runs of the same positions")


def check_sides(world: RunData, real: RunData) -> None:
    """FalsifyError for runs given the wrong way round (real scans as the world, streets as
    the real side) or with other effect dims (fog, rain, ...), whose rows would pool unsaid."""
    if world.space.real_backgrounds and not real.space.real_backgrounds:
        raise FalsifyError(f"{world.path} holds real scans and {real.path} streets: give the "
                           f"world's run first (falsify agreement {real.path} {world.path})")
    effects = {}
    for d in (world, real):
        effects[d.path] = {n: tuple(d.space.dims[n].grid()) for n in EFFECT_DIMS
                           if n in d.space.dims}
    if len({tuple(sorted(e.items())) for e in effects.values()}) > 1:
        shown = "; ".join(f"{p}: {e or 'none'}" for p, e in effects.items())
        raise FalsifyError(f"the runs' weather and fault dims differ ({shown}): their rows "
                           "would pool other conditions into one side; compare runs of the "
                           "same effects")


def map_agreement(wmap: CellMap, rmap: CellMap, threshold: float) -> MapAgreement:
    """Agreement of two maps on one grid over the cells both define (see MapAgreement)."""
    w, r = wmap.miou, rmap.miou
    has_w, has_r = np.isfinite(w), np.isfinite(r)
    both = has_w & has_r
    wv, rv = w[both], r[both]
    mae = float(np.abs(wv - rv).mean()) if len(wv) else None
    pearson = None
    if len(wv) >= 2 and np.ptp(wv) > 0 and np.ptp(rv) > 0:
        pearson = float(np.corrcoef(wv, rv)[0, 1])
    blind_w = both & (np.where(has_w, w, 1.0) < threshold)
    blind_r = both & (np.where(has_r, r, 1.0) < threshold)

    def cells(mask: np.ndarray) -> tuple[tuple[float, float], ...]:
        jj, ii = np.nonzero(mask)
        return tuple((float(wmap.a_values[i]), float(wmap.b_values[j]))
                     for j, i in zip(jj, ii, strict=True))

    agree = float((blind_w == blind_r)[both].mean()) if both.any() else None
    return MapAgreement(threshold, int(has_w.sum()), int(has_r.sum()), int(both.sum()), mae,
                        pearson, int(blind_w.sum()), int(blind_r.sum()), agree,
                        cells(blind_r & ~blind_w), cells(blind_w & ~blind_r),
                        jaccard(set(cells(blind_w)), set(cells(blind_r))))


def side(data: RunData) -> RunSide:
    cols = placed_columns(data)
    ok = ok_rows(data)
    n_bg = int(ok["background"].nunique()) if "background" in ok.columns else 0
    return RunSide(str(data.path), bool(data.space.real_backgrounds), len(ok), n_bg,
                   cols["iou"], cols["recall"])


def run_agreement(world_run: str | Path, real_run: str | Path, threshold: float | None = None,
                  fp_samples: int = 0, device: str = "cpu",
                  limits: Limits = Limits(), allow_incomplete: bool = False) -> AgreementResult:
    """Compare a run on our streets with a run of the same positions on real scans; the
    threshold defaults to the real run's, `fp_samples` rows of each run are replayed, and
    `limits` set the targets to check; either run incomplete is an error unless allowed."""
    from falsify.checks import check_range
    from falsify.jobs.gate import check_threshold

    check_threshold(threshold)
    check_range(fp_samples, "--fp-samples", 0, MAX_FP_SAMPLES)
    check_limits(limits)
    world, real = open_run(world_run), open_run(real_run)
    check_complete(world, allow_incomplete, "world run ")
    check_complete(real, allow_incomplete, "real run ")
    check_sides(world, real)
    for which, d in (("world", world), ("real", real)):
        if not len(ok_rows(d)):   # dashes everywhere, or MISSED under a --max-* limit
            statuses = ", ".join(sorted(set(d.frame["status"].astype(str)))) or "absent"
            raise FalsifyError(f"{which} run {d.path}: no valid sample to compare (every row is "
                               f"{statuses})")
    wcol, rcol = placed_columns(world)["iou"], placed_columns(real)["iou"]
    wmap = miou_map(ok_rows(world), world.space, "x", "y", wcol)
    rmap = miou_map(ok_rows(real), real.space, "x", "y", rcol)
    check_same_grid(world, real, wmap, rmap)
    t = real.threshold if threshold is None else float(threshold)
    metrics = tuple(compare_metric(world, real, m) for m in METRICS)
    if fp_samples:
        fps = tuple(false_positives(d, fp_samples, device) for d in (world, real))
        note = (f"{fp_samples} ok rows of each run replayed (evenly spaced in evaluation "
                "order) and predicted again")
    else:
        fps, note = (), "skipped (--fp-samples 0); --fp-samples N replays N rows of each run"
    real_places = by_place(real)
    places = pair_places(by_place(world), real_places)
    floor = (None if places is None else
             place_floor(real, [p.place for p in places.pairs], len(real_places), rmap, t))
    amap = map_agreement(wmap, rmap, t)
    return AgreementResult(side(world), side(real), metrics, amap, fps, note, places, floor,
                           check_targets(metrics, amap, places, floor, limits))


# -- false positives by what they lie on -----------------------------------------------------
def spread_rows(frame: pd.DataFrame, n: int) -> pd.DataFrame:
    """n rows evenly spaced over the frame in evaluation order (all when it has at most n)."""
    frame = frame.sort_values("eval_index", kind="stable")
    if len(frame) <= n:
        return frame
    return frame.iloc[np.unique(np.linspace(0, len(frame) - 1, n).round().astype(int))]


def fp_classes(pred: np.ndarray, label: np.ndarray, valid: np.ndarray,
               semantic: np.ndarray | None) -> dict[str, int]:
    """Points predicted car (our class ids) whose label is not car, counted by the SemanticKITTI
    train class of their raw id (by our four classes' name where the scan has no raw ids)."""
    from falsify.classes import CAR, CLASSES
    from falsify.semantic import TRAIN_CLASSES, train_ids

    fp = valid & (pred == CAR) & (label != CAR)
    if semantic is None:
        ids, names = label[fp].astype(np.int64), CLASSES
    else:
        ids, names = train_ids(semantic[fp]).astype(np.int64), TRAIN_CLASSES
    counts = np.bincount(ids, minlength=len(names))
    return {names[k]: int(c) for k, c in enumerate(counts) if c}


def false_positives(data: RunData, n: int, device: str = "cpu") -> FalsePositives:
    """Replay n ok rows of a run (their scans as the run cast them), predict them with the
    run's model, and count their false-positive car points by the class they lie on."""
    from falsify.jobs.report import open_model, run_lod
    from falsify.results.replay import Replay

    rows = spread_rows(ok_rows(data), n)
    seg, note = open_model(data.meta, True, device=device)
    if seg is None:
        return FalsePositives(str(data.path), 0, 0, {}, 0, note)
    try:
        replay = Replay(data.space, lod=run_lod(data.meta))
    except Exception as exc:   # the rest of the comparison stands without it
        return FalsePositives(str(data.path), 0, 0, {}, 0, f"scans not regenerated ({exc})")
    total: dict[str, int] = {}
    done, stored, errors = 0, 0, []
    for _, row in rows.iterrows():
        try:
            _, scan = replay.scan(row)
            pred = seg.predict(scan.image[None]).classes[0]
        except Exception as exc:
            errors.append(f"row {int(row['eval_index'])}: {exc}")
            continue
        for name, c in fp_classes(pred, scan.label, scan.valid, scan.semantic).items():
            total[name] = total.get(name, 0) + c
        done += 1
        stored += int(row["car_fp"]) if pd.notna(row.get("car_fp")) else 0
    notes = [note] + ([f"{len(errors)} not replayed ({errors[0]})"] if errors else [])
    by_class = dict(sorted(total.items(), key=lambda kv: (-kv[1], kv[0])))
    return FalsePositives(str(data.path), done, sum(total.values()), by_class, stored,
                          "; ".join(n for n in notes if n))


# -- text ------------------------------------------------------------------------------------
def format_text(res: AgreementResult) -> str:
    """A few aligned lines: the runs, the per-background spreads, the maps, false positives."""
    def f(v) -> str:
        return "-" if v is None else f"{v:.3f}"

    def kind(s: RunSide) -> str:
        return (f"{s.path} ({'real scans' if s.real else 'streets'}, {s.ok_rows} ok rows, "
                f"{s.backgrounds} backgrounds)")

    lines = [f"world: {kind(res.world)}", f"real:  {kind(res.real)}",
             "placed car, per-background means:",
             f"  {'metric':10s} {'run':5s} {'column':16s} {'n':>3s} {'mean':>6s} {'p10':>6s} "
             f"{'p50':>6s} {'p90':>6s} {'min':>6s} {'max':>6s} {'W1':>6s}"]
    for m in res.metrics:
        for who, col, d, w1 in (("world", m.world_column, m.world, ""),
                                ("real", m.real_column, m.real, f(m.w1))):
            lines.append(f"  {m.metric if who == 'world' else '':10s} {who:5s} {col:16s} "
                         f"{d.count:3d} {f(d.mean):>6s} {f(d.p10):>6s} {f(d.p50):>6s} "
                         f"{f(d.p90):>6s} {f(d.min):>6s} {f(d.max):>6s} {w1:>6s}")
    lines.append(f"  ({res.precision_note})")
    a = res.map
    lines.append(f"x × y map of the placed car's IoU over {a.cells_both} common cells: MAE "
                 f"{f(a.mae)}, Pearson {f(a.pearson)}")
    lines.append(f"blind below {a.threshold:g}: world {a.blind_world}, real {a.blind_real}; "
                 f"alike {f(a.agreement)}, world misses {len(a.world_misses)}, world only "
                 f"{len(a.false_alarms)}, Jaccard {f(a.jaccard)}")
    lines.extend(_places_text(res.places, f))
    if res.floor is not None:
        fl = res.floor
        real_p10 = next(m.real.p10 for m in res.metrics if m.metric == "iou")
        lines.append(f"floor, were each street exactly its own place ({fl.places} of "
                     f"{fl.real_places} real places): W1 IoU {f(fl.w1['iou'])}, precision "
                     f"{f(fl.w1['precision'])}, recall {f(fl.w1['recall'])}; p10 IoU "
                     f"{f(fl.p10['iou'])} (real {f(real_p10)}); map MAE {f(fl.map_mae)}")
    lines.extend(_targets_text(res.targets, f))
    if not res.false_positives:
        lines.append(f"false-positive car points: {res.fp_note}")
    for fp in res.false_positives:
        top = ", ".join(f"{k} {v}" for k, v in list(fp.by_class.items())[:6]) or "none"
        lines.append(f"false-positive car points, {fp.run}: {fp.points} in {fp.samples} "
                     f"replayed rows (stored car_fp {fp.stored_fp}): {top}"
                     + (f" [{fp.note}]" if fp.note else ""))
    return "\n".join(lines)


def _targets_text(targets: tuple[Target, ...], f) -> list[str]:
    """One line a target: its distance against its limit, met or missed, and the floor's."""
    if not targets:
        return []
    out = [f"targets: {sum(t.met for t in targets)} of {len(targets)} met"]
    for t in targets:
        reach = ("" if t.floor is None else f"  floor {f(t.floor)}"
                 + ("" if t.reachable else ": out of reach on these places"))
        if t.value is None and t.name.startswith("place"):
            reach = "  no place in both runs"
        out.append(f"  {t.name:13s} {f(t.value):>6s} <= {t.limit:<6g} "
                   f"{'met' if t.met else 'MISSED':6s}{reach}")
    return out


def _places_text(pl: PlacePairing | None, f) -> list[str]:
    """The per-place lines: each place's IoU and precision, world against real, hardest real
    place first."""
    if pl is None:
        return ["per place: no real place in both runs"]
    out = [f"per place, {len(pl.pairs)} in both runs: mean |world - real| IoU "
           f"{f(pl.mae['iou'])}, precision {f(pl.mae['precision'])}, recall "
           f"{f(pl.mae['recall'])}"
           + (f"; streets' places not in the real run: {len(pl.world_only)}"
              if pl.world_only else "")
           + (f"; real places no street stands for: {len(pl.real_only)}"
              if pl.real_only else ""),
           f"  {'place':24s} {'streets':>7s} {'IoU world':>9s} {'real':>6s} "
           f"{'prec world':>10s} {'real':>6s}"]
    for p in sorted(pl.pairs, key=lambda p: (p.real["iou"], p.place)):
        out.append(f"  {p.place:24s} {p.streets:7d} {f(p.world['iou']):>9s} "
                   f"{f(p.real['iou']):>6s} {f(p.world['precision']):>10s} "
                   f"{f(p.real['precision']):>6s}")
    return out
