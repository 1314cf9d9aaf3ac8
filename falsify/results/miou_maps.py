"""mIoU maps over pairs of dims, blind-spot cells, and the paper's per-cell comparison.

mIoU(i, j) is the mean car IoU (or the run's objective, or any class's IoU) of the valid samples
in cell (i, j): over backgrounds in the paper's grid, and over every other dim where those vary
too. Samples of a search land in the
cell of the nearest grid value. Samples whose IoU is undefined (no car in label or prediction)
or that are invalid are counted per cell but never averaged in.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import pandas as pd

from falsify.results.metrics import Status
from falsify.world.space import Continuous, Space


def fmt_value(v: float | int | str) -> str:
    """A coordinate as users write it: -5.0 → "-5", 2.5 → "2.5"."""
    if isinstance(v, str):
        return v
    return f"{float(v):g}"


def axis_texts(values) -> dict:
    """Each distinct value of an axis as its shortest text at 6 significant digits, or with as
    many more as tell it from the axis's other values (100.0001 and 100.0002 are both "100" at
    6): two cells never share a label, a key or a gate's name. Categories stay as they are."""
    vals = list(dict.fromkeys(values))
    if any(isinstance(v, str) for v in vals):
        return {v: fmt_value(v) for v in vals}
    floats = sorted({float(v) for v in vals})
    for digits in range(6, 18):   # 17 significant digits tell any two doubles apart
        texts = [f"{v:.{digits}g}" for v in floats]
        if len(set(texts)) == len(floats):
            break
    return dict(zip(floats, texts, strict=True))


@dataclass(frozen=True)
class Cell:
    """One map cell: its coordinates, mIoU, and how many samples stand behind it."""

    a: float | int | str
    b: float | int | str
    miou: float | None
    samples: int      # valid samples averaged
    undefined: int
    invalid: int
    lower: float | None = None   # an estimated map's interval (level-set runs)
    upper: float | None = None


@dataclass(frozen=True)
class CellMap:
    """A grid of cells over dims `a` (columns) × `b` (rows); miou NaN where no valid sample."""

    a: str
    b: str
    a_values: tuple
    b_values: tuple
    miou: np.ndarray      # (len(b_values), len(a_values)) float64
    samples: np.ndarray   # int64, same shape
    undefined: np.ndarray
    invalid: np.ndarray
    lower: np.ndarray | None = None   # an estimated map's interval per cell (level-set runs)
    upper: np.ndarray | None = None

    @property
    def filled(self) -> np.ndarray:
        """The cells a sample landed in (valid, undefined or invalid) or with an estimate."""
        return ((self.samples + self.undefined + self.invalid) > 0) | np.isfinite(self.miou)

    @property
    def estimated(self) -> bool:
        """Whether miou is an estimate of the full grid's map, with an interval per cell."""
        return self.lower is not None

    def cells(self) -> list[Cell]:
        out = []
        for j, bv in enumerate(self.b_values):
            for i, av in enumerate(self.a_values):
                m = self.miou[j, i]
                lo = hi = None
                if self.lower is not None and self.upper is not None and np.isfinite(m):
                    lo, hi = float(self.lower[j, i]), float(self.upper[j, i])
                out.append(Cell(av, bv, None if np.isnan(m) else float(m),
                                int(self.samples[j, i]), int(self.undefined[j, i]),
                                int(self.invalid[j, i]), lo, hi))
        return out

    def blind_spots(self, threshold: float) -> list[Cell]:
        """Cells whose mIoU is below the threshold, worst first."""
        cells = [c for c in self.cells() if c.miou is not None and c.miou < threshold]
        return sorted(cells, key=lambda c: (c.miou, str(c.a), str(c.b)))

    def to_frame(self) -> pd.DataFrame:
        frame = pd.DataFrame([c.__dict__ for c in self.cells()]).rename(
            columns={"a": self.a, "b": self.b})
        return frame if self.estimated else frame.drop(columns=["lower", "upper"])


def with_estimates(cmap: CellMap, estimates: Sequence[Sequence]) -> CellMap:
    """`cmap` (an x × y map of a run's rows) with each cell's mIoU replaced by the estimate
    of the full grid's [x, y, estimate, lower, upper, ...] and its interval kept."""
    miou = np.full(cmap.miou.shape, np.nan)
    lower, upper = miou.copy(), miou.copy()
    for x, y, est, lo, hi, *_ in estimates:
        i, j = _match(x, cmap.a_values), _match(y, cmap.b_values)
        if i is None or j is None or est is None:
            continue
        i, j = cmap.a_values.index(i), cmap.b_values.index(j)
        miou[j, i], lower[j, i], upper[j, i] = est, lo, hi
    return CellMap(cmap.a, cmap.b, cmap.a_values, cmap.b_values, miou, cmap.samples,
                   cmap.undefined, cmap.invalid, lower, upper)


def axis_values(space: Space, dim: str) -> tuple:
    return tuple(space.dims[dim].grid())


def snap(values: pd.Series, space: Space, dim: str) -> pd.Series:
    """Map sampled values of a dim onto its grid (nearest value); categorical values stay."""
    d = space.dims[dim]
    if not isinstance(d, Continuous):
        return values
    grid = np.asarray(d.grid(), dtype=np.float64)
    v = values.to_numpy(dtype=np.float64)
    idx = np.abs(v[:, None] - grid[None, :]).argmin(axis=1)
    return pd.Series(grid[idx], index=values.index)


def miou_map(frame: pd.DataFrame, space: Space, a: str = "x", b: str = "y",
             column: str = "car_iou") -> CellMap:
    """The mIoU map of dims a × b over a run's rows (all other dims averaged) of one metric
    column (the objective's, or any class's IoU); samples where it is undefined count as such."""
    a_vals, b_vals = axis_values(space, a), axis_values(space, b)
    shape = (len(b_vals), len(a_vals))
    miou = np.full(shape, np.nan)
    samples = np.zeros(shape, np.int64)
    undefined = np.zeros(shape, np.int64)
    invalid = np.zeros(shape, np.int64)
    if len(frame):
        ia = _axis_index(snap(frame[a], space, a), a_vals)
        ib = _axis_index(snap(frame[b], space, b), b_vals)
        placed = (ia >= 0) & (ib >= 0)
        cell = (ib * len(a_vals) + ia)[placed]
        bad = (frame["status"] == Status.INVALID).to_numpy()[placed]
        values = frame[column].astype(float).to_numpy()[placed]
        defined = ~bad & ~np.isnan(values)
        size = shape[0] * shape[1]
        invalid.flat[:] = np.bincount(cell[bad], minlength=size)
        samples.flat[:] = np.bincount(cell[defined], minlength=size)
        undefined.flat[:] = np.bincount(cell[~bad], minlength=size) - samples.flat
        # each cell's mean over its values in row order, as a per-cell np.mean: the same bytes
        order = np.argsort(cell[defined], kind="stable")
        cells, values = cell[defined][order], values[defined][order]
        starts = np.flatnonzero(np.r_[True, cells[1:] != cells[:-1]]) if len(cells) else []
        for k, start in enumerate(starts):
            end = starts[k + 1] if k + 1 < len(starts) else len(cells)
            miou.flat[cells[start]] = cell_mean(values[start:end])
    return CellMap(a, b, a_vals, b_vals, miou, samples, undefined, invalid)


def cell_mean(values: np.ndarray) -> float:
    """The mean of a cell's IoUs rounded to 1e-12: float round-off must not put a cell whose
    exact mean is the threshold (IoUs 0.6 and 0.7 at 0.65) below it, a blind spot 0.000 below."""
    return round(float(np.mean(values)), 12)


def _axis_index(keys: pd.Series, values: tuple) -> np.ndarray:
    """Each row's index into the axis `values` (as `_match` finds it), -1 where none matches
    or the key is missing; matched once per distinct key, not once per row."""
    codes, uniques = pd.factorize(keys, use_na_sentinel=True)
    numeric = not any(isinstance(v, str) for v in values)
    axis = np.asarray(values, dtype=np.float64) if numeric else None
    table = np.full(len(uniques) + 1, -1, np.int64)   # the last entry: a missing key's code
    for k, u in enumerate(uniques):
        if numeric and not isinstance(u, str):
            hits = np.flatnonzero(np.abs(axis - float(u)) < 1e-6)
            table[k] = hits[0] if len(hits) else -1
        else:
            v = _match(u, values)
            table[k] = -1 if v is None else values.index(v)
    return table[codes]


def _match(value, values: tuple):
    """Find `value` among the axis values, tolerating float round-off and str/int storage."""
    for v in values:
        if isinstance(v, str) or isinstance(value, str):
            if str(v) == str(value):
                return v
        elif abs(float(v) - float(value)) < 1e-6:
            return v
    return None


def compare(before: CellMap, after: CellMap) -> pd.DataFrame:
    """Per-cell mIoU change (after − before) over cells both runs score, sorted descending:
    the paper's sorted per-cell improvement plot."""
    fb, fa = before.to_frame(), after.to_frame()
    keys = [before.a, before.b]
    merged = fb.merge(fa, on=keys, suffixes=("_before", "_after"))
    merged = merged.dropna(subset=["miou_before", "miou_after"])
    merged["change"] = merged["miou_after"] - merged["miou_before"]
    return merged.sort_values("change", ascending=False, kind="stable").reset_index(drop=True)


# -- a map against a reference map (the trade-off's measure) -----------------------------
def jaccard(a: set, b: set) -> float:
    """|A ∩ B| / |A ∪ B|; 1.0 when both sets are empty (full agreement)."""
    union = a | b
    return 1.0 if not union else len(a & b) / len(union)


def fill_nearest(cells: CellMap, xs: Sequence[float], ys: Sequence[float]) -> np.ndarray:
    """Values on the (ys, xs) grid, each from the nearest cell of `cells` that has one (metric
    distance in x, y; ties go to the lower y, then the lower x). NaN if no cell has a value."""
    jj, ii = np.nonzero(np.isfinite(cells.miou))
    if not len(jj):
        return np.full((len(ys), len(xs)), np.nan)
    px = np.asarray(cells.a_values, float)[ii]
    py = np.asarray(cells.b_values, float)[jj]
    gx, gy = np.meshgrid(np.asarray(xs, float), np.asarray(ys, float))
    d2 = (gx[..., None] - px) ** 2 + (gy[..., None] - py) ** 2
    return cells.miou[jj, ii][d2.argmin(axis=-1)]


@dataclass(frozen=True)
class MapError:
    """How a map differs from the reference map on the reference's cells."""

    mean_abs: float | None
    max_abs: float | None
    jaccard: float
    blind_spots: int
    lost_cells: int   # cells with an mIoU in the reference but none here


def map_error(ref: CellMap, values: np.ndarray, threshold: float) -> MapError:
    """Errors over cells both maps define; blind spots (mIoU < threshold) over the reference's
    defined cells."""
    has_ref, has = np.isfinite(ref.miou), np.isfinite(values)
    both = has_ref & has
    diff = np.abs(ref.miou[both] - values[both])
    ref_bs = set(zip(*np.nonzero(has_ref & (np.where(has_ref, ref.miou, 1.0) < threshold)),
                     strict=True))
    bs = set(zip(*np.nonzero(both & (np.where(has, values, 1.0) < threshold)), strict=True))
    return MapError(float(diff.mean()) if len(diff) else None,
                    float(diff.max()) if len(diff) else None,
                    jaccard(ref_bs, bs), len(bs), int((has_ref & ~has).sum()))
