"""NLopt: minimise the car IoU over the continuous dims, one NLopt run per discrete combination.

- Discrete dims (car models, count, background, image-only and value-list dims) form an outer
  loop over their combinations, in `Space.grid()` order (count first, then dims in config order);
  dims of cars beyond a combination's count are not enumerated.
- Budget: combinations without a free continuous dim cost one evaluation each (done first, in
  one batch); the rest of the budget is split equally over the other combinations, the remainder
  going one each to the first ones. A budget below the number of combinations is a ConfigError.
  A point asked again (a simplex re-evaluating a vertex, a restart landing on an old point)
  costs one evaluation like any ask and is in the curve; the driver answers it from the run's
  store, so it is neither scored nor stored twice (the run holds fewer rows than its budget).
- NLopt works in the unit cube over the free continuous dims (lo < hi); fixed dims (lo == hi)
  stay out of the vector. Proposals are clipped into [lo, hi] before a sample is built.
- A None (or nan, or inf) score becomes `penalty` (default 1.0, the best possible IoU) so the
  optimiser moves away from invalid samples (an infinite score stopped DIRECT with an error).
- Local methods start at the centre of the box with an initial step of `initial_step` (1/4) of
  each range and stop when a step is below `xtol` of the range or the score is exactly flat. A
  run that stops before its share is restarted from a seeded uniform point (except DIRECT, which
  is deterministic and ignores the start: it runs once); global methods run to their share.
- `nlopt.srand` is reseeded before every run from (seed, combination, restart), so the sequence
  of samples is a function of (space, budget, seed, the scores told).
- With `concurrent` W > 1 (the driver's workers), up to W combinations run at once, each in its
  own thread with its own NLopt run(s), each asking `evaluate` for one point at a time; the
  threads never wait on each other (`evaluate` must be safe to call from several threads).
  Nothing of a combination depends on another (its quota, its seeds, its numpy Generator and
  NLopt's generator, which is per thread, are its own), so the samples, scores and results are
  those of the sequential loop whatever W and the timing. A Recorder passed as `evaluate` keeps
  the order that defines the curve: the fixed combinations' batch, then each free combination's
  evaluations in combination order, each in its own evaluation order (not completion order).
- An exception in one combination (a worker dying, an error in `evaluate`) or in the calling
  thread (KeyboardInterrupt) stops the others at their next evaluation and is raised once all
  have stopped; combinations not started are not started. Nothing is raised through NLopt
  itself: the objective keeps the exception, asks NLopt to stop, and it is raised after.
"""

from __future__ import annotations

import itertools
import math
import threading
from collections.abc import Sequence
from concurrent.futures import FIRST_EXCEPTION, Future, ThreadPoolExecutor, wait
from dataclasses import dataclass

import nlopt
import numpy as np

from falsify.errors import ConfigError
from falsify.sampler.base import (
    NLOPT_ALGORITHMS,
    Evaluate,
    Recorder,
    SearchResult,
    check_budget,
    defined,
    part_of,
)
from falsify.world.space import Categorical, Continuous, Sample, Space, Value

LOCAL_SUBOPTIMISERS = ("LN_BOBYQA", "LN_COBYLA")
FTOL = 1e-9  # local runs also stop on an exactly flat score (e.g. the penalty plateau)
_START_FREE = ("GN_DIRECT_L",)  # deterministic and ignore x0: a restart would repeat itself
_POLL_S = 0.5   # how often the calling thread looks up from waiting (so signals get through)


class _Stopped(Exception):
    """Raised by a combination's run stopped because another combination failed."""


_Job = tuple[int, Evaluate, dict[str, Value], int, list[int]]
"""A free combination's run: (index, evaluate, combination, quota, seed words)."""


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
    """An NLopt algorithm by name; `local` is G_MLSL_LDS's sub-optimiser; `concurrent` is how
    many combinations run at once (it changes the speed, never the result)."""

    name: str = "LN_BOBYQA"
    local: str = "LN_BOBYQA"
    penalty: float = 1.0
    initial_step: float = 0.25
    xtol: float = 1e-3
    concurrent: int = 1

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
        if n == 0:
            return []
        needed = combo_count(space)   # counted, not made: there may be millions
        if n < needed:
            raise ConfigError(f"sampler {self.name}: budget {n:,} is smaller than the "
                              f"{needed:,} combinations of discrete dims; give a budget of "
                              f"at least {needed:,} or fix some discrete dims")
        combos = discrete_combos(space)
        fixed = [c for c in combos if not _free(space, c)]
        results: dict[int, ComboResult] = {}
        if fixed:
            samples = [space.make(c) for c in fixed]
            scores = evaluate(samples)
            for c, s, sc in zip(fixed, samples, scores, strict=True):
                v = defined(sc)
                results[combos.index(c)] = ComboResult(
                    tuple(c.items()), 1, 0, v, None if v is None else s)
        free = [i for i, c in enumerate(combos) if _free(space, c)]
        left = n - len(fixed)
        quotas = {i: left // len(free) + (1 if k < left % len(free) else 0)
                  for k, i in enumerate(free)}
        # Part i + 1 of a Recorder holds combination i's evaluations (part 0: the fixed batch).
        jobs: list[_Job] = [(i, part_of(evaluate, i + 1), combos[i], quotas[i],
                             [seed % 2**63, i]) for i in free]
        if self.concurrent <= 1 or len(jobs) <= 1:
            for i, part, combo, quota, words in jobs:
                results[i] = self._minimise(space, part, combo, quota, words)
        else:
            results.update(self._concurrently(space, jobs))
        return [results[i] for i in range(len(combos))]

    def _concurrently(self, space: Space, jobs: list[_Job]) -> dict[int, ComboResult]:
        """Run the jobs' `_minimise` on up to `concurrent` threads; results by combination.

        The first exception (of a job, or here: KeyboardInterrupt) sets `stop`, so every running
        job raises _Stopped at its next evaluation, and cancels the jobs not started; it is
        raised once no job runs. Of jobs failing together, the first combination's error wins."""
        stop = threading.Event()
        pool = ThreadPoolExecutor(max_workers=min(self.concurrent, len(jobs)),
                                  thread_name_prefix=f"nlopt-{self.name}")
        futures: dict[Future, int] = {}
        try:
            for i, part, combo, quota, words in jobs:
                futures[pool.submit(self._minimise, space, part, combo, quota, words,
                                    stop)] = i
            pending = set(futures)
            while pending:
                done, pending = wait(pending, timeout=_POLL_S, return_when=FIRST_EXCEPTION)
                errors = {futures[f]: e for f in done if (e := f.exception()) is not None}
                if errors:
                    raise errors[min(errors)]
            return {i: f.result() for f, i in futures.items()}
        except BaseException:
            stop.set()
            raise
        finally:
            pool.shutdown(wait=True, cancel_futures=True)

    def _minimise(self, space: Space, evaluate: Evaluate, combo: dict[str, Value], quota: int,
                  seed_words: list[int], stop: threading.Event | None = None) -> ComboResult:
        """Minimise over one combination's free continuous dims with at most `quota` evaluations;
        raises _Stopped at the next evaluation once `stop` is set."""
        dims = _free(space, combo)
        lo = np.array([d.lo for d in dims])
        hi = np.array([d.hi for d in dims])
        width = hi - lo
        rng = np.random.default_rng(seed_words)
        used, runs = 0, 0
        best: tuple[float, Sample] | None = None

        error: BaseException | None = None   # raised out of `evaluate`: re-raised below

        def step(u: np.ndarray) -> float:
            nonlocal used, best
            x = np.clip(lo + np.clip(u, 0.0, 1.0) * width, lo, hi)
            point = {d.name: float(v) for d, v in zip(dims, x, strict=True)}
            sample = space.make({**combo, **point})
            score = defined(evaluate([sample])[0])
            used += 1
            if score is None:   # invalid, undefined, nan or inf: NLopt is told the penalty
                return self.penalty
            if best is None or score < best[0]:
                best = (score, sample)
            return score

        def objective(u: np.ndarray, grad: np.ndarray) -> float:
            # Nothing is raised through NLopt: an exception raised there stays pending while
            # some algorithms (CRS) call the objective once more, and any call made then fails
            # with SystemError. Out of budget, told to stop, or on an error (kept, raised once
            # NLopt has returned), the objective asks NLopt to stop and returns the penalty.
            nonlocal error
            if error is None and used < quota:
                if stop is not None and stop.is_set():
                    error = _Stopped()
                else:
                    try:
                        return step(u)
                    except BaseException as exc:
                        error = exc
            opt.force_stop()
            return self.penalty

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
            if error is not None:
                raise error
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
        c = self.concurrent
        if isinstance(c, bool) or not isinstance(c, int) or c < 1:
            raise ConfigError(f"sampler {self.name}: concurrent {c!r} must be an integer >= 1")


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


def combo_count(space: Space) -> int:
    """How many combinations `discrete_combos` makes, computed without making them."""
    counts = space.dims["count"].grid() if "count" in space.dims else (1,)
    return sum(math.prod(len(d.values) for d in space.discrete()
                         if d.name != "count" and space.active(d.name, int(count)))
               for count in counts)


def _free(space: Space, combo: dict[str, Value]) -> tuple[Continuous, ...]:
    """The continuous dims with lo < hi that are active for the combination's count."""
    return tuple(d for d in space.continuous(int(combo.get("count", 1))) if d.hi > d.lo)
