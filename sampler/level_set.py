"""Level set: which cells of the x × y map are blind (mean score below the threshold), decided
with as few evaluations as the scores allow, instead of scoring every sample of every cell.

A cell's value is what the grid would report: the mean score over all its samples (the grid's
other dims: backgrounds, weather, ... — here the *replicates*, a random factor shared by all
cells). The sampler estimates it from a few of them and stops a cell once its interval excludes
the threshold:

- **Replicates as a random factor, neighbours sharing strength.** Scores follow
  y[c, r] = mu[c] + b[r] + e: a replicate effect b ~ N(0, tau^2) (a hard background lowers
  every cell it is scored in, so one cell's low score on it says less about that cell), a
  residual e ~ N(0, sigma_c^2) whose per-cell variance is pooled with the global one (a
  scaled-inverse-chi-square prior with `prior_dof` degrees), and cell means mu under a Gaussian
  process over the cells' grid indices (constant mean, squared-exponential kernel whose length
  scale and variance are the candidates' best by log marginal likelihood; Rasmussen & Williams
  2006, eq. 2.30). The posterior of (mu, b) is the solution of Henderson's mixed model
  equations (1975) with the GP's precision added to the cells' block; their inverse is the
  joint covariance, whose cross terms matter: a cell's mean and the replicate effects are
  estimated from the same scores. Variances come from alternating ridge least squares first.
- **Finite population.** A cell has R samples; its value is their mean. With n scored the
  estimate is (sum of the scored + sum over the unscored r of (mu[c] + b[r])) / R, its variance
  that of the unscored part's posterior plus (R-n) sigma_c^2, over R^2: zero once every sample
  is scored (sampling without replacement, Cochran 1977).
- **Sequential stopping.** The interval is estimate +- q sd, q Student's t quantile for
  `confidence` with the cell's pooled degrees of freedom. A cell is blind once the interval
  lies below the threshold, and safe only once the stricter one-sided bound at
  1 - (1 - confidence) / 4 lies above it: missing a blind spot costs more than a sample.
  Each round gives the next sample of the `round` cells whose interval lies closest to the
  threshold in sd units, each cell's samples taken in a balanced order (one seeded permutation
  of the replicates, rotated per cell, so every replicate is scored about equally often and its
  effect stays estimable). The run stops when every cell is decided, or the budget is spent.
- **How honest the intervals are** is measured, not assumed: `falsify bench map` reports the
  share of cells whose interval holds the grid's value (docs/benchmarks.md; below the nominal
  level on real backgrounds, whose residuals are heavier-tailed than the model's).

Samples a run scores are ordinary grid samples, so its store, resume and report are a grid's;
the run adds each cell's estimate and interval (`SearchResult.cells`), which its map and gate
read. Deterministic: every choice is a function of (space, seed, options, the scores told).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from statistics import NormalDist

import numpy as np

from falsify.errors import ConfigError
from falsify.sampler.base import (
    CellEstimate,
    Evaluate,
    Recorder,
    SearchResult,
    check_budget,
    defined,
)
from falsify.world.space import Sample, Space

LENGTH_SCALES = (0.5, 1.0, 2.0, 3.0, 5.0)   # in cells; 0.5 leaves cells almost independent
SIGNAL_SCALES = (0.5, 1.0, 2.0)               # times the spread of the fitted cell means
FIT_ITERATIONS = 30
VAR_FLOOR = 1e-6
SAFE_FACTOR = 4    # a cell is called safe at one-sided 1 - (1 - confidence) / 4, blind at / 2
NUGGET = 1e-4      # independent share of each cell's prior variance (keeps the GP invertible)
UNKNOWN_VAR = 0.25  # a residual variance no score measures: the most a score in [0, 1] can have
# Every round solves the model over all cells and replicates at once (dense matrices of that
# side: 4.2 s at 1,000 on one core, 23 s at 2,000, terabytes at a fine step's 800,000 cells).
MAX_UNKNOWNS = 2_000


@dataclass(frozen=True)
class Cells:
    """The map's cells and the grid samples behind each: `samples[c][k]` is cell c's k-th sample
    in its scoring order, `replicates[c][k]` that sample's replicate index."""

    keys: tuple[tuple, ...]              # (x, y) per cell
    index: np.ndarray                    # (cells, 2) grid indices of x and y
    samples: tuple[tuple[Sample, ...], ...]
    replicates: tuple[tuple[int, ...], ...]
    n_replicates: int


def cells_of(space: Space, seed: int) -> Cells:
    """Group the space's grid by (x, y); order each cell's samples by one seeded permutation of
    the replicates (the other dims' combinations), rotated by the cell's position."""
    for dim in ("x", "y"):
        if dim not in space.dims:
            raise ConfigError(f"sampler level-set maps x × y; the space has no dim {dim!r}")
    check_model_size(space)
    xs, ys = list(space.dims["x"].grid()), list(space.dims["y"].grid())
    by_cell: dict[tuple, list[Sample]] = {}
    rep_of: dict[tuple, int] = {}
    for s in space.grid():
        by_cell.setdefault((s["x"], s["y"]), []).append(s)
        rep_of.setdefault(_replicate_key(s), len(rep_of))
    n_rep = len(rep_of)
    perm = np.random.default_rng(seed).permutation(n_rep)
    rank = np.empty(n_rep, np.int64)
    rank[perm] = np.arange(n_rep)
    keys = sorted(by_cell, key=lambda k: (ys.index(k[1]), xs.index(k[0])))
    samples, replicates = [], []
    for c, key in enumerate(keys):
        reps = [rep_of[_replicate_key(s)] for s in by_cell[key]]
        order = sorted(range(len(reps)), key=lambda k: ((rank[reps[k]] - c) % n_rep, k))
        samples.append(tuple(by_cell[key][k] for k in order))
        replicates.append(tuple(reps[k] for k in order))
    index = np.array([[xs.index(k[0]), ys.index(k[1])] for k in keys], dtype=np.float64)
    return Cells(tuple(keys), index.reshape(-1, 2), tuple(samples), tuple(replicates), n_rep)


def check_model_size(space: Space) -> None:
    """ConfigError, before any sample, when the map's cells and replicates are more than the
    model can be fitted over each round (it would run for hours, or exhaust memory)."""
    n_x, n_y = space.dims["x"].size, space.dims["y"].size
    cells = n_x * n_y
    replicates = space.size() // cells   # every cell holds the same combinations of the rest
    if cells + replicates > MAX_UNKNOWNS:
        raise ConfigError(
            f"sampler level-set: the map has {cells:,} cell{'s' * (cells != 1)} (x: {n_x:,} "
            f"values, y: {n_y:,}) and {replicates:,} samples per cell; it fits its model over "
            f"at most {MAX_UNKNOWNS:,} cells and samples per cell together: take larger dims.x "
            "or dims.y steps (or fewer values of the other dims), or search with random or sobol")


def _replicate_key(s: Sample) -> tuple:
    return tuple((n, v) for n, v in s.values if n not in ("x", "y"))


@dataclass
class _Fit:
    """The model's posterior: cell means and replicate effects, their joint covariance, and
    each cell's and replicate's residual variance."""

    mu: np.ndarray        # (cells,) every cell, scored or not
    b: np.ndarray         # (replicates,)
    cov: np.ndarray       # posterior covariance of (mu, b), cells first
    var_cell: np.ndarray  # (cells,) residual variance per cell (pooled)


def residual_variances(cell: np.ndarray, rep: np.ndarray, y: np.ndarray, n_cells: int,
                       n_rep: int, prior_dof: float
                       ) -> tuple[np.ndarray, np.ndarray, float, np.ndarray]:
    """Alternating ridge least squares for y = mu[cell] + b[rep] + e: the cell means (nan where
    none is scored), the scores per cell, tau^2 (the replicate effects' variance) and each
    cell's residual variance, pooled with the global one over `prior_dof` degrees of freedom."""
    n = np.bincount(cell, minlength=n_cells).astype(np.float64)
    n_r = np.bincount(rep, minlength=n_rep).astype(np.float64)
    b = np.zeros(n_rep)
    mu = np.full(n_cells, np.nan)
    has = n > 0
    sigma2, lam, tau2 = max(float(np.var(y)), VAR_FLOOR), 1.0, VAR_FLOOR
    for _ in range(FIT_ITERATIONS):
        mu[has] = np.bincount(cell, y - b[rep], minlength=n_cells)[has] / n[has]
        b = np.bincount(rep, y - mu[cell], minlength=n_rep) / (n_r + lam)
        resid = y - mu[cell] - b[rep]
        dof = max(len(y) - int(has.sum()) - int((n_r > 0).sum()), 1)
        sigma2 = max(float(resid @ resid) / dof, VAR_FLOOR)
        tau2 = max(float(np.mean(b[n_r > 0] ** 2)) if (n_r > 0).any() else 0.0, VAR_FLOOR)
        lam = sigma2 / tau2
    resid = y - mu[cell] - b[rep]
    ss = np.bincount(cell, resid ** 2, minlength=n_cells)
    var_cell = (prior_dof * sigma2 + ss) / (prior_dof + np.maximum(n - 1, 0))
    return mu, n, tau2, var_cell


def gp_prior(index: np.ndarray, mu: np.ndarray, noise: np.ndarray
             ) -> tuple[float, np.ndarray]:
    """The prior of every cell's mean: a constant plus a GP over grid indices (squared-
    exponential kernel), its length scale and variance the candidates' best by the log
    marginal likelihood of the scored cells' means `mu` with variances `noise`."""
    obs = np.isfinite(mu)
    n_all = len(mu)
    if obs.sum() < 2:
        return (float(mu[obs][0]) if obs.any() else 0.5), np.eye(n_all) * 0.25
    X, yo, vo = index[obs], mu[obs], noise[obs]
    d2_oo = ((X[:, None, :] - X[None, :, :]) ** 2).sum(-1)
    w = 1.0 / vo
    m = float((w * yo).sum() / w.sum())
    spread = max(float(np.var(yo)) - float(np.mean(vo)), float(np.var(yo)) * 0.1, VAR_FLOOR)
    best: tuple[float, float, float] | None = None
    for ell in LENGTH_SCALES:
        for scale in SIGNAL_SCALES:
            s2 = spread * scale
            K = s2 * (np.exp(-0.5 * d2_oo / ell ** 2) + NUGGET * np.eye(len(yo))) + np.diag(vo)
            L = np.linalg.cholesky(K)
            alpha = np.linalg.solve(L.T, np.linalg.solve(L, yo - m))
            lml = -0.5 * float((yo - m) @ alpha) - float(np.log(np.diag(L)).sum())
            if best is None or lml > best[0] + 1e-12:
                best = (lml, ell, s2)
    assert best is not None
    _, ell, s2 = best
    d2 = ((index[:, None, :] - index[None, :, :]) ** 2).sum(-1)
    return m, s2 * (np.exp(-0.5 * d2 / ell ** 2) + NUGGET * np.eye(n_all))


def fit(cell: np.ndarray, rep: np.ndarray, y: np.ndarray, index: np.ndarray, n_rep: int,
        prior_dof: float) -> _Fit:
    """The posterior of y = mu[cell] + b[rep] + e with mu ~ GP and b ~ N(0, tau^2): the mixed
    model equations (Henderson 1975) with the GP's precision added to the cells' block, solved
    at once; their inverse is the joint covariance that an estimate of a cell's unscored part
    needs (its mean's error and the replicate effects' are correlated)."""
    n_cells = len(index)
    mu0, n, tau2, var_cell = residual_variances(cell, rep, y, n_cells, n_rep, prior_dof)
    w = 1.0 / var_cell[cell]
    # the scored cells' own means and their variances, for choosing the GP
    noise = np.where(n > 0, var_cell / np.maximum(n, 1), np.inf)
    m, K = gp_prior(index, mu0, noise)
    k = n_cells
    C = np.zeros((k + n_rep, k + n_rep))
    ri = k + rep
    np.add.at(C, (cell, cell), w)
    np.add.at(C, (cell, ri), w)
    np.add.at(C, (ri, cell), w)
    np.add.at(C, (ri, ri), w)
    K_inv = np.linalg.inv(K)
    C[:k, :k] += K_inv
    C[k:, k:] += np.eye(n_rep) / tau2
    rhs = np.zeros(k + n_rep)
    np.add.at(rhs, cell, w * y)
    np.add.at(rhs, ri, w * y)
    rhs[:k] += K_inv @ np.full(k, m)
    cov = np.linalg.inv(C)
    sol = cov @ rhs
    return _Fit(sol[:k], sol[k:], cov, var_cell)


@dataclass(frozen=True)
class LevelSetSampler:
    """Rounds of `round` samples, each for the cell least sure to be on one side of the
    threshold, until every cell is decided at `confidence` (two-sided) or `budget` runs out;
    `initial` samples of every cell first. `threshold` None takes the space's."""

    round: int = 16
    initial: int = 2
    confidence: float = 0.95
    threshold: float | None = None
    prior_dof: float = 2.0
    name: str = field(default="level-set", init=False)

    def __post_init__(self) -> None:
        for key, low in (("round", 1), ("initial", 1)):
            v = getattr(self, key)
            if isinstance(v, bool) or not isinstance(v, int) or v < low:
                raise ConfigError(f"sampler {self.name}: {key} must be an integer >= {low}, "
                                  f"got {v!r}")
        if not isinstance(self.confidence, int | float) or not 0.5 <= self.confidence < 1:
            raise ConfigError(f"sampler {self.name}: confidence must be in [0.5, 1), got "
                              f"{self.confidence!r}")
        if self.threshold is not None and not 0 < self.threshold <= 1:
            raise ConfigError(f"sampler {self.name}: threshold must be in (0, 1], got "
                              f"{self.threshold!r}")
        if not isinstance(self.prior_dof, int | float) or self.prior_dof <= 0:
            raise ConfigError(f"sampler {self.name}: prior_dof must be > 0")

    def run(self, space: Space, evaluate: Evaluate, budget: int | None,
            seed: int) -> SearchResult:
        left = check_budget(self.name, budget, required=False)
        t = space.threshold if self.threshold is None else self.threshold
        z = NormalDist().inv_cdf(0.5 + self.confidence / 2)
        cells = cells_of(space, seed)
        n_cells = len(cells.keys)
        taken = np.zeros(n_cells, np.int64)             # samples scored per cell
        scores: list[list[float | None]] = [[] for _ in range(n_cells)]
        rec = Recorder(evaluate)

        def score(picks: list[int]) -> None:
            nonlocal left
            if left is not None:
                picks = picks[:left]
                left -= len(picks)
            batch = []
            for c in picks:
                batch.append(cells.samples[c][taken[c]])
                taken[c] += 1
            got = rec(batch)
            if len(got) != len(batch):
                raise RuntimeError(f"evaluate returned {len(got)} scores for {len(batch)} samples")
            for c, s in zip(picks, got, strict=True):
                scores[c].append(defined(s))

        first = [c for k in range(self.initial) for c in range(n_cells)
                 if k < len(cells.samples[c])]
        for start in range(0, len(first), self.round):
            if left == 0:
                break
            score(first[start:start + self.round])
        est = self._estimate(cells, taken, scores, t, z)
        while left is None or left > 0:
            open_ = [(0.0 if e.estimate is None else abs(e.estimate - t) / max(e.sd, 1e-12), c)
                     for c, e in enumerate(est)
                     if not e.decided and taken[c] < len(cells.samples[c])]
            if not open_:
                break
            open_.sort()
            picks: list[int] = []
            spare = {c: len(cells.samples[c]) - int(taken[c]) for _, c in open_}
            while len(picks) < self.round and any(spare.values()):
                for _, c in open_:
                    if spare[c] and len(picks) < self.round:
                        picks.append(c)
                        spare[c] -= 1
            score(picks)
            est = self._estimate(cells, taken, scores, t, z)
        result = rec.result()
        return SearchResult(result.curve, result.best, result.best_sample, result.samples,
                            cells=tuple(est))

    def _estimate(self, cells: Cells, taken: np.ndarray, scores: list[list[float | None]],
                  t: float, z: float) -> list[CellEstimate]:
        """Every cell's estimate of its grid mean, interval and whether it is decided."""
        n_cells = len(cells.keys)
        z_safe = NormalDist().inv_cdf(1 - (1 - self.confidence) / SAFE_FACTOR)
        cidx, ridx, ys = [], [], []
        for c in range(n_cells):
            for k, s in enumerate(scores[c]):
                if s is not None:
                    cidx.append(c)
                    ridx.append(cells.replicates[c][k])
                    ys.append(s)
        out: list[CellEstimate] = []
        if not ys:
            for c, key in enumerate(cells.keys):
                full = taken[c] == len(cells.samples[c])
                out.append(CellEstimate(key[0], key[1], None, None, None, int(taken[c]),
                                        len(cells.samples[c]), bool(full)))
            return out
        post = fit(np.asarray(cidx), np.asarray(ridx), np.asarray(ys), cells.index,
                   cells.n_replicates, self.prior_dof)
        # Until some cell holds two scores nothing measures the residual variance (each cell's
        # mean fits its one score exactly, and the fit's variance is the floor): a budget cut in
        # the first round must not call cells decided, on intervals a hundredth wide, from one
        # score each. The unscored samples' spread is then the most a score can have.
        replicated = bool((np.bincount(cidx, minlength=n_cells) >= 2).any())
        k = n_cells
        for c, key in enumerate(cells.keys):
            defined = [s for s in scores[c] if s is not None]
            rest = np.asarray(cells.replicates[c][taken[c]:], dtype=np.int64)
            total = len(defined) + len(rest)
            if total == 0:
                out.append(CellEstimate(key[0], key[1], None, None, None, int(taken[c]),
                                        len(cells.samples[c]), True))
                continue
            m = len(rest)
            value = (sum(defined) + m * post.mu[c] + float(post.b[rest].sum())) / total
            # error of the unscored part: the posterior of the cell's mean and of each unscored
            # replicate's effect, jointly, and each unscored sample's own residual (sampling
            # without replacement: nothing once all are scored)
            rb = k + rest
            v_est = (m * m * post.cov[c, c] + 2 * m * float(post.cov[c, rb].sum())
                     + float(post.cov[np.ix_(rb, rb)].sum()))
            v_resid = (float(post.var_cell[c]) if replicated else UNKNOWN_VAR) * m
            sd = math.sqrt(max(v_est, 0.0) + v_resid) / total
            dof = self.prior_dof + max(len(defined) - 1, 0)
            q, q_safe = t_quantile(z, dof), t_quantile(z_safe, dof)
            lo, hi = value - q * sd, value + q * sd
            # a cell none of whose scored samples has a score is not decided by its neighbours
            # alone: the grid may well have no value for it (every sample invalid)
            # safe needs the stricter bound: a blind spot missed costs more than a safe cell
            # scored once more
            decided = m == 0 or (replicated and bool(defined)
                                 and (hi < t or value - q_safe * sd >= t))
            out.append(CellEstimate(key[0], key[1], float(value), float(lo), float(hi),
                                    int(taken[c]), len(cells.samples[c]), bool(decided),
                                    sd=float(sd)))
        return out


def t_quantile(z: float, dof: float) -> float:
    """Student's t quantile from the normal one `z` (Cornish-Fisher expansion; Abramowitz and
    Stegun 1964, 26.7.5): a cell's residual variance is itself estimated from few samples."""
    z2 = z * z
    return z * (1 + (z2 + 1) / (4 * dof) + (5 * z2 ** 2 + 16 * z2 + 3) / (96 * dof ** 2)
                + (3 * z2 ** 3 + 19 * z2 ** 2 + 17 * z2 - 15) / (384 * dof ** 3)
                + (79 * z2 ** 4 + 776 * z2 ** 3 + 1482 * z2 ** 2 - 1920 * z2 - 945)
                / (92160 * dof ** 4))


def blind_cells(cells: Sequence[CellEstimate], threshold: float) -> list[CellEstimate]:
    """The cells whose estimate is below the threshold."""
    return [c for c in cells if c.estimate is not None and c.estimate < threshold]
