"""What the failing samples of a run have in common: rules over the space's own dims, the share
of IoU variance each dim explains, and clusters of failing samples.

Rules are conjunctions of at most `depth` conditions (`y >= 16`, `|x| >= 3`, `background == 5`)
found by a beam search over the dims' own values that maximises weighted relative accuracy,
WRAcc = coverage x (precision - base rate) (Lavrac et al., "Subgroup Discovery with CN2-SD",
JMLR 2004): a rule must cover many samples and fail far more often than the run does. Rules are
taken one after another, each scored on the failures the earlier ones left uncovered (sequential
covering), so a second rule names a different region. Sensitivity is the first-order index
S_i = Var(E[IoU | dim_i]) / Var(IoU) (Sobol', 1993), exact on a full grid (a main effect of the
ANOVA decomposition); on scattered samples continuous dims are binned at their quantiles.

A sample whose `count` is below k does not place car k; its car-k dims hold pinned defaults that
mean nothing (`Space.make`). So car k's dims are judged only on the samples that hold car k
(`Space.active`, as the samplers do): a condition on them covers only such samples, their
candidate cuts, sensitivity and cluster means come from those samples alone, and a cluster's
centre shows them only when more than half of its samples hold car k.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import pandas as pd

from falsify.results.metrics import Status
from falsify.world.space import Categorical, Continuous, Space

MAX_CUTS = 24         # thresholds tried per continuous dim (its values, thinned to this many)
BEAM = 12             # partial rules kept between depths
MIN_SUPPORT = 3       # samples a rule must cover
MIN_PRECISION = 0.6   # share of a rule's samples that must fail for it to be reported
SENSITIVITY_BINS = 10  # quantile bins of a continuous dim on scattered samples
OPS = ("<=", ">=", "|x|<=", "|x|>=", "==")


@dataclass(frozen=True)
class Condition:
    """One test on one dim, in the dim's own units."""

    dim: str
    op: str          # one of OPS
    value: float | int | str

    def mask(self, column: pd.Series) -> np.ndarray:
        if self.op == "==":
            return (column == self.value).to_numpy()
        v = column.astype(float).to_numpy()
        if self.op == "<=":
            return v <= float(self.value) + 1e-9
        if self.op == ">=":
            return v >= float(self.value) - 1e-9
        if self.op == "|x|<=":
            return np.abs(v) <= float(self.value) + 1e-9
        return np.abs(v) >= float(self.value) - 1e-9

    def text(self) -> str:
        value = _fmt(self.value)
        if self.op.startswith("|x|"):
            return f"|{self.dim}| {self.op[3:]} {value}"
        return f"{self.dim} {self.op} {value}"


@dataclass(frozen=True)
class Rule:
    """A conjunction of conditions and how the run's samples fall under it."""

    conditions: tuple[Condition, ...]
    support: int          # samples the rule covers
    failing: int          # of them below the threshold
    precision: float      # failing / support
    recall: float         # failing / all failing samples of the run
    mean_iou: float
    wracc: float

    def text(self) -> str:
        return " and ".join(c.text() for c in self.conditions)

    def to_json(self) -> dict:
        return {"rule": self.text(), "support": self.support, "failing": self.failing,
                "precision": round(self.precision, 4), "recall": round(self.recall, 4),
                "mean_iou": round(self.mean_iou, 4), "wracc": round(self.wracc, 5),
                "conditions": [{"dim": c.dim, "op": c.op, "value": c.value}
                               for c in self.conditions]}


@dataclass(frozen=True)
class Cluster:
    """A group of failing samples: its centre in the dims' units, its size and mean IoU."""

    centre: dict[str, float | int | str]
    size: int
    mean_iou: float

    def to_json(self) -> dict:
        return {"centre": self.centre, "size": self.size, "mean_iou": round(self.mean_iou, 4)}


@dataclass(frozen=True)
class Explanation:
    """Rules, per-dim sensitivity and clusters of one table of samples."""

    threshold: float
    samples: int
    failing: int
    rules: tuple[Rule, ...]
    sensitivity: dict[str, float]
    clusters: tuple[Cluster, ...]
    score: str = "car_iou"   # the column explained: the run's objective

    def to_json(self) -> dict:
        return {"score": self.score, "threshold": self.threshold, "samples": self.samples,
                "failing": self.failing,
                "rules": [r.to_json() for r in self.rules],
                "sensitivity": {k: round(v, 4) for k, v in self.sensitivity.items()},
                "clusters": [c.to_json() for c in self.clusters]}


def score_name(column: str) -> str:
    """A score column in words: car_iou -> car IoU, traffic_sign_iou -> traffic sign IoU, miou
    -> mIoU."""
    if column == "miou":
        return "mIoU"
    return column.removesuffix("_iou").replace("_", " ") + " IoU"


def _fmt(value: float | int | str) -> str:
    if isinstance(value, str):
        return value
    return f"{float(value):g}"


def holds(space: Space, frame: pd.DataFrame, name: str) -> np.ndarray:
    """Bool per row: whether dim `name` means anything for the row's sample, i.e. the sample
    holds the car the dim belongs to (`Space.active` on its count; every row without a count
    column). A car beyond a sample's count was not placed: its dims are pinned defaults."""
    if "count" not in frame.columns or name not in space.dims:
        return np.ones(len(frame), bool)
    counts = frame["count"]
    held = {c: space.active(name, int(c)) for c in counts.dropna().unique()}
    return counts.map(held).fillna(False).to_numpy(bool)


def explained_dims(space: Space, frame: pd.DataFrame) -> list[str]:
    """The dims that vary over the samples they mean something for (a dim with one value
    explains nothing; nor does a car's dim that varies only through its pinned default)."""
    return [d for d in space.dims if d in frame.columns
            and frame[d][holds(space, frame, d)].nunique(dropna=True) > 1]


def candidates(space: Space, frame: pd.DataFrame, dims: Sequence[str]) -> list[Condition]:
    """Every condition worth trying on the values each dim takes where it means something."""
    out: list[Condition] = []
    for name in dims:
        dim = space.dims[name]
        column = frame[name][holds(space, frame, name)].dropna()
        if isinstance(dim, Categorical):
            out += [Condition(name, "==", _plain(v)) for v in sorted(column.unique(), key=str)]
            continue
        values = np.unique(column.astype(float).to_numpy())
        cuts = _thin(values)
        out += [Condition(name, op, float(c)) for c in cuts for op in ("<=", ">=")]
        if isinstance(dim, Continuous) and dim.lo < 0 < dim.hi:
            mags = _thin(np.unique(np.abs(values)))
            out += [Condition(name, op, float(c)) for c in mags for op in ("|x|<=", "|x|>=")]
    return out


def _plain(v):
    return v.item() if hasattr(v, "item") else v


def _thin(values: np.ndarray) -> np.ndarray:
    if len(values) <= MAX_CUTS:
        return values
    return values[np.unique(np.linspace(0, len(values) - 1, MAX_CUTS).round().astype(int))]


def find_rules(frame: pd.DataFrame, space: Space, threshold: float, depth: int = 2,
               max_rules: int = 5, score: str = "car_iou") -> tuple[Rule, ...]:
    """Up to `max_rules` rules, each best by WRAcc on the failures left by the ones before;
    a failure is a `score` below the threshold. A condition on car k's dim covers only the
    samples holding car k."""
    fail = frame[score].astype(float).to_numpy() < threshold
    if not fail.any() or fail.all():
        return ()
    iou = frame[score].astype(float).to_numpy()
    conds = candidates(space, frame, explained_dims(space, frame))
    held = {d: holds(space, frame, d) for d in {c.dim for c in conds}}
    masks = {c: c.mask(frame[c.dim]) & held[c.dim] for c in conds}
    left = fail.copy()
    rules: list[Rule] = []
    for _ in range(max_rules):
        if not left.any():
            break
        best = _beam(conds, masks, left, fail, depth)
        if best is None:
            break
        chosen, cover = best
        n, k = int(cover.sum()), int((fail & cover).sum())
        if n < MIN_SUPPORT or k / n < MIN_PRECISION:
            break
        base = fail.mean()
        rules.append(Rule(chosen, n, k, k / n, k / int(fail.sum()), float(iou[cover].mean()),
                          float(n / len(fail) * (k / n - base))))
        left &= ~cover
    return tuple(rules)


def _beam(conds: Sequence[Condition], masks: dict, left: np.ndarray, fail: np.ndarray,
          depth: int) -> tuple[tuple[Condition, ...], np.ndarray] | None:
    """The conjunction of highest WRAcc on the still-uncovered failures (`left`) among those
    whose precision reaches MIN_PRECISION; the beam keeps the highest-WRAcc partial rules, so
    a broad first condition can be narrowed into a precise one. Failures an earlier rule
    explained are left out of the counts, so a region is not rewarded twice."""
    n_all = len(left)
    base = left.mean()
    eligible = left | ~fail

    def counts(cover: np.ndarray) -> tuple[int, int]:
        c = cover & eligible
        return int(c.sum()), int((left & c).sum())

    def wracc(n: int, k: int) -> float:
        return -math.inf if n < MIN_SUPPORT else n / n_all * (k / n - base)

    beam: list[tuple[float, tuple[Condition, ...], np.ndarray]] = [(0.0, (), np.ones(n_all, bool))]
    best: tuple[float, tuple[Condition, ...], np.ndarray] | None = None
    for _ in range(depth):
        grown = []
        for _, rule, cover in beam:
            used = {c.dim for c in rule}
            for c in conds:
                if c.dim in used:
                    continue
                new = cover & masks[c]
                if new.sum() == cover.sum():
                    continue
                n, k = counts(new)
                grown.append((wracc(n, k), (*rule, c), new, n, k))
        if not grown:
            break
        grown.sort(key=lambda t: (-t[0], len(t[1]), [x.text() for x in t[1]]))
        beam = [g[:3] for g in grown[:BEAM]]
        precise = [g for g in grown if g[3] >= MIN_SUPPORT and g[4] / g[3] >= MIN_PRECISION]
        if precise:
            top = precise[0]
            # A longer rule must beat a shorter one clearly to be preferred (readability).
            if best is None or top[0] > best[0] * 1.05 + 1e-12:
                best = top[:3]
    if best is None or not math.isfinite(best[0]) or best[0] <= 0:
        return None
    return best[1], best[2] & eligible


def sensitivity(frame: pd.DataFrame, space: Space, dims: Sequence[str],
                score: str = "car_iou") -> dict[str, float]:
    """First-order index of each dim: the share of the score's variance its value alone
    explains. Car k's dims are grouped over the samples holding car k only (elsewhere their
    value is a pinned default, which would pass off `count`'s effect as theirs): their index is
    the between-group sum of squares among those samples over the run's total, so it stays a
    share of the run's variance, comparable with the other dims'."""
    y_all = frame[score].astype(float)
    var = float(y_all.var(ddof=0))
    out = {}
    for name in dims:
        held = holds(space, frame, name)
        y, col = y_all[held], frame[name][held]
        dim = space.dims[name]
        if isinstance(dim, Continuous) and col.nunique() > SENSITIVITY_BINS * 2:
            col = pd.qcut(col.astype(float), SENSITIVITY_BINS, duplicates="drop")
        means = y.groupby(col, observed=True).transform("mean")
        share = len(y) / len(y_all)   # 1 for a dim every sample holds
        out[name] = 0.0 if var == 0 or not len(y) else float(means.var(ddof=0) * share / var)
    return dict(sorted(out.items(), key=lambda kv: -kv[1]))


def clusters(frame: pd.DataFrame, space: Space, dims: Sequence[str], threshold: float,
             k: int = 4, seed: int = 0, score: str = "car_iou") -> tuple[Cluster, ...]:
    """k-means (k-means++ start, seeded) over the failing samples' continuous dims scaled to
    their ranges; categorical dims are reported as each cluster's most common value.

    A car's dims count only on the samples holding that car: a sample without car k is placed
    by its other dims (partial distances), and a centre shows car k's dims, averaged over the
    cluster's samples that hold car k, only when more than half of its samples do."""
    fail = frame[frame[score].astype(float) < threshold].reset_index(drop=True)
    cont = [d for d in dims if isinstance(space.dims[d], Continuous)]
    if len(fail) == 0 or not cont:
        return ()
    k = min(k, len(fail))
    held = {d: holds(space, fail, d) for d in dims}
    lo = np.array([space.dims[d].lo for d in cont])
    span = np.array([max(space.dims[d].hi - space.dims[d].lo, 1e-9) for d in cont])
    pts = (fail[cont].astype(float).to_numpy() - lo) / span
    pts[~np.column_stack([held[d] for d in cont])] = np.nan
    labels = _kmeans(pts, k, np.random.default_rng(seed))
    out = []
    for j in range(k):
        part = labels == j
        if not part.any():
            continue
        centre: dict[str, float | int | str] = {}
        for d in dims:
            here = part & held[d]
            if 2 * here.sum() <= part.sum():   # most of the cluster lacks this dim's car
                continue
            values = fail[d][here]
            centre[d] = (round(float(values.astype(float).mean()), 3) if d in cont
                         else _plain(values.mode().iloc[0]))
        centre = {d: centre[d] for d in [*cont, *(d for d in dims if d not in cont)]
                  if d in centre}
        out.append(Cluster(centre, int(part.sum()),
                           float(fail[score][part].astype(float).mean())))
    return tuple(sorted(out, key=lambda c: (-c.size, c.mean_iou)))


def _sq_dist(pts: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Squared distance of each point to centre `c` over the dims both have (NaN: absent),
    scaled up by the share of dims compared (partial distance); inf where none is shared."""
    diff = (pts - c) ** 2
    seen = ~np.isnan(diff)
    if seen.all():
        return diff.sum(-1)
    n = seen.sum(-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        d = np.where(seen, diff, 0.0).sum(-1) * (pts.shape[-1] / n)
    return np.where(n > 0, d, np.inf)


def _kmeans(pts: np.ndarray, k: int, rng: np.random.Generator, iters: int = 50) -> np.ndarray:
    """Labels of k-means over `pts`; NaN entries (dims of a car the sample lacks) are left out
    of distances and means."""
    centres = [pts[rng.integers(len(pts))]]
    for _ in range(1, k):
        d2 = np.min([_sq_dist(pts, c) for c in centres], axis=0)
        d2 = np.where(np.isfinite(d2), d2, 0.0)
        total = d2.sum()
        centres.append(pts[rng.choice(len(pts), p=d2 / total)] if total > 0 else
                       pts[rng.integers(len(pts))])
    c = np.array(centres)
    labels = np.zeros(len(pts), int)
    for _ in range(iters):
        labels = np.stack([_sq_dist(pts, cj) for cj in c], -1).argmin(1)
        new = np.array([_nanmean(pts[labels == j], c[j]) for j in range(k)])
        if np.allclose(new, c, equal_nan=True):
            break
        c = new
    return labels


def _nanmean(members: np.ndarray, old: np.ndarray) -> np.ndarray:
    """Per-dim mean of a cluster's members over those that have the dim; the old centre where
    the cluster is empty, NaN where no member has the dim."""
    if not len(members):
        return old
    seen = ~np.isnan(members)
    n = seen.sum(0)
    total = np.where(seen, members, 0.0).sum(0)
    return np.where(n > 0, total / np.maximum(n, 1), np.nan)


def explain(frame: pd.DataFrame, space: Space, threshold: float, depth: int = 2,
            max_rules: int = 5, k: int = 4, seed: int = 0,
            score: str = "car_iou") -> Explanation:
    """Rules, sensitivity and clusters of a run's valid rows (status ok), failing where `score`
    (the run's objective column) is below the threshold."""
    ok = frame[frame["status"] == Status.OK].reset_index(drop=True)
    dims = explained_dims(space, ok)
    fail = int((ok[score].astype(float) < threshold).sum()) if len(ok) else 0
    return Explanation(
        threshold, len(ok), fail,
        find_rules(ok, space, threshold, depth, max_rules, score) if len(ok) else (),
        sensitivity(ok, space, dims, score) if len(ok) > 1 else {},
        clusters(ok, space, dims, threshold, k, seed, score) if len(ok) else (), score)
