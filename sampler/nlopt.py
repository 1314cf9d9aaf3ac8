"""NLopt: minimise the car IoU over the continuous dims, one NLopt run per discrete combination.

- Discrete dims (car models, count, background, image-only and value-list dims) form an outer
  loop over their combinations, in `Space.grid()` order (count first, then dims in config order);
  dims of cars beyond a combination's count are not enumerated.
- Budget: combinations without a free continuous dim cost one evaluation each (done first, in
  one batch); the rest of the budget is split equally over the other combinations, the remainder
  going one each to the first ones. A budget below the number of combinations is a ConfigError.
- NLopt works in the unit cube over the free continuous dims (lo < hi); fixed dims (lo == hi)
  stay out of the vector. Proposals are clipped into [lo, hi] before a sample is built.
- A None (or nan) score becomes `penalty` (default 1.0, the best possible IoU) so the optimiser
  moves away from invalid samples.
- Local methods start at the centre of the box with an initial step of `initial_step` (1/4) of
  each range and stop when a step is below `xtol` of the range or the score is exactly flat. A
  run that stops before its share is restarted from a seeded uniform point (except DIRECT, which
  is deterministic and ignores the start: it runs once); global methods run to their share.
- `nlopt.srand` is reseeded before every run from (seed, combination, restart), so the sequence
  of samples is a function of (space, budget, seed, the scores told).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass

import nlopt
import numpy as np
from falsify.sampler.base import NLOPT_ALGORITHMS, Evaluate, Recorder, SearchResult, check_budget

from falsify.errors import ConfigError
from falsify.space import Categorical, Continuous, Sample, Space, Value

LOCAL_SUBOPTIMISERS = ("LN_BOBYQA", "LN_COBYLA")
FTOL = 1e-9  # local runs also stop on an exactly flat score (e.g. the penalty plateau)
_START_FREE = ("GN_DIRECT_L",)  # deterministic and ignore x0: a restart would repeat itself


@dataclass(frozen=True)
class ComboResult:
    """What the optimiser did on one discrete combination."""

    combo: tuple[tuple[str, Value], ...]
    evaluations: int
    runs: int
    best_score: float | None
    best_sample: Sample | None


@dataclass(frozen=True)
class NloptSampler:
    """An NLopt algorithm by name; `local` is G_MLSL_LDS's sub-optimiser."""

    name: str = "LN_BOBYQA"
    local: str = "LN_BOBYQA"
    penalty: float = 1.0
    initial_step: float = 0.25
    xtol: float = 1e-3

    def run(self, space: Space, evaluate: Evaluate, budget: int | None,
            seed: int) -> SearchResult:
        rec = Recorder(evaluate)
        self.optimise(space, rec, budget, seed)
        return rec.result()

    def optimise(self, space: Space, evaluate: Evaluate, budget: int | None,
                 seed: int) -> list[ComboResult]:
        """Run the outer loop; returns one result per discrete combination, in order."""
        self._check()
        n = check_budget(self.name, budget, required=True)
        assert n is not None
        combos = discrete_combos(space)
        if n == 0:
            return []
        if n < len(combos):
            raise ConfigError(f"sampler {self.name}: budget {n} is smaller than the "
                              f"{len(combos)} combinations of discrete dims; give a budget of "
                              f"at least {len(combos)} or fix some discrete dims")
        fixed = [c for c in combos if not _free(space, c)]
        results: dict[int, ComboResult] = {}
        if fixed:
            samples = [space.make(c) for c in fixed]
            scores = evaluate(samples)
            for c, s, sc in zip(fixed, samples, scores, strict=True):
                ok = sc is not None and not math.isnan(sc)
                results[combos.index(c)] = ComboResult(
                    tuple(c.items()), 1, 0, float(sc) if ok else None, s if ok else None)
        free = [i for i, c in enumerate(combos) if _free(space, c)]
        left = n - len(fixed)
        for k, i in enumerate(free):
            quota = left // len(free) + (1 if k < left % len(free) else 0)
            results[i] = self._minimise(space, evaluate, combos[i], quota, [seed % 2**63, i])
        return [results[i] for i in range(len(combos))]

    def _minimise(self, space: Space, evaluate: Evaluate, combo: dict[str, Value], quota: int,
                  seed_words: list[int]) -> ComboResult:
        """Minimise over one combination's free continuous dims with at most `quota` evaluations."""
        dims = _free(space, combo)
        lo = np.array([d.lo for d in dims])
        hi = np.array([d.hi for d in dims])
        width = hi - lo
        rng = np.random.default_rng(seed_words)
        used, runs = 0, 0
        best: tuple[float, Sample] | None = None

        def objective(u: np.ndarray, grad: np.ndarray) -> float:
            nonlocal used, best
            if used >= quota:
                raise nlopt.ForcedStop()
            x = np.clip(lo + np.clip(u, 0.0, 1.0) * width, lo, hi)
            point = {d.name: float(v) for d, v in zip(dims, x, strict=True)}
            sample = space.make({**combo, **point})
            score = evaluate([sample])[0]
            used += 1
            if score is None or math.isnan(score):
                return self.penalty
            if best is None or score < best[0]:
                best = (float(score), sample)
            return float(score)

        while used < quota:
            before = used
            opt = self._opt(len(dims), quota - used)
            opt.set_min_objective(objective)
            x0 = np.full(len(dims), 0.5) if runs == 0 else rng.uniform(0.0, 1.0, len(dims))
            nlopt.srand(int(rng.integers(2**31)))
            runs += 1
            try:
                opt.optimize(x0)
            except (nlopt.ForcedStop, nlopt.RoundoffLimited):
                pass
            if used == before or self.name in _START_FREE:
                break
        return ComboResult(tuple(combo.items()), used, runs,
                           None if best is None else best[0], None if best is None else best[1])

    def _opt(self, n: int, maxeval: int) -> nlopt.opt:
        opt = nlopt.opt(getattr(nlopt, self.name), n)
        opt.set_lower_bounds(np.zeros(n))
        opt.set_upper_bounds(np.ones(n))
        opt.set_maxeval(maxeval)
        if self.name == "G_MLSL_LDS":
            sub = nlopt.opt(getattr(nlopt, self.local), n)
            sub.set_xtol_abs(np.full(n, self.xtol))
            sub.set_ftol_abs(FTOL)
            sub.set_initial_step(np.full(n, self.initial_step))
            opt.set_local_optimizer(sub)
        if self.name.startswith("LN_"):
            opt.set_xtol_abs(np.full(n, self.xtol))
            opt.set_ftol_abs(FTOL)
            opt.set_initial_step(np.full(n, self.initial_step))
        return opt

    def _check(self) -> None:
        if self.name not in NLOPT_ALGORITHMS:
            raise ConfigError(f"unknown NLopt algorithm {self.name!r}; allowed: "
                              f"{', '.join(NLOPT_ALGORITHMS)}")
        if self.local not in LOCAL_SUBOPTIMISERS:
            raise ConfigError(f"sampler {self.name}: local {self.local!r}; allowed: "
                              f"{', '.join(LOCAL_SUBOPTIMISERS)}")
        for key in ("initial_step", "xtol"):
            v = getattr(self, key)
            if not (isinstance(v, int | float) and 0.0 < v <= 1.0):
                raise ConfigError(f"sampler {self.name}: {key} {v!r} must be in (0, 1] "
                                  "(a fraction of each dim's range)")
        if not (isinstance(self.penalty, int | float) and math.isfinite(self.penalty)):
            raise ConfigError(f"sampler {self.name}: penalty {self.penalty!r} must be a number")


def discrete_combos(space: Space) -> list[dict[str, Value]]:
    """Every combination of the categorical dims active for its count, in grid order."""
    out: list[dict[str, Value]] = []
    counts = space.dims["count"].grid() if "count" in space.dims else (1,)
    for count in counts:
        cats: Sequence[Categorical] = [
            d for d in space.discrete() if d.name != "count" and space.active(d.name, int(count))]
        for values in itertools.product(*(d.values for d in cats)):
            combo: dict[str, Value] = {"count": count} if "count" in space.dims else {}
            combo.update(zip((d.name for d in cats), values, strict=True))
            out.append(combo)
    return out


def _free(space: Space, combo: dict[str, Value]) -> tuple[Continuous, ...]:
    """The continuous dims with lo < hi that are active for the combination's count."""
    return tuple(d for d in space.continuous(int(combo.get("count", 1))) if d.hi > d.lo)
