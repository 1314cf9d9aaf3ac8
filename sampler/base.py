"""The sampler contract, the registry of sampler names and small helpers shared by samplers."""

from __future__ import annotations

import functools
import math
import threading
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from typing import Protocol

import nlopt
import numpy as np

from falsify.errors import ConfigError
from falsify.world.space import Categorical, Sample, Space

Score = float | None
"""A sample's car IoU (lower = worse for the network); None = invalid sample or undefined IoU."""

Evaluate = Callable[[Sequence[Sample]], list[Score]]
"""The driver's evaluator: scores a batch (in parallel, from the store on resume), in order."""

BATCH = 64


def defined(score: Score) -> float | None:
    """The score as a float, or None where it is none (invalid, undefined) or not finite (nan,
    inf): no sampler steers by, or reports, a score that is not a number in range."""
    if score is None:
        return None
    value = float(score)
    return value if math.isfinite(value) else None


_NLOPT_CANDIDATES = (
    "GN_DIRECT_L", "GN_CRS2_LM", "GN_ISRES", "GN_ESCH", "G_MLSL_LDS",
    "LN_BOBYQA", "LN_COBYLA", "LN_NELDERMEAD", "LN_SBPLX",
)
NLOPT_ALGORITHMS: tuple[str, ...] = tuple(n for n in _NLOPT_CANDIDATES if hasattr(nlopt, n))
"""NLopt algorithms offered by name (those this NLopt build provides)."""

ALGORITHMS: tuple[str, ...] = ("grid", "random", "sobol", "cross-entropy", "level-set",
                               *NLOPT_ALGORITHMS, "bo")
"""Every name `make_sampler` accepts. `bo` is listed even without its optional Optuna, so that
asking for it says how to install Optuna rather than that the name is unknown."""


@dataclass(frozen=True)
class CellEstimate:
    """A map cell's estimated mean score (what the full grid would give), its interval, and how
    many of its samples were scored; `decided` once the interval excludes the threshold."""

    x: float | int | str
    y: float | int | str
    estimate: float | None        # None: no sample of the cell has a score
    lower: float | None
    upper: float | None
    scored: int                   # samples evaluated
    samples: int                  # samples the cell has in the grid
    decided: bool
    sd: float = 0.0

    def as_list(self) -> list:
        """[x, y, estimate, lower, upper, scored, samples, decided], rounded, for the run's
        metadata."""
        return [self.x, self.y, _rounded(self.estimate), _rounded(self.lower),
                _rounded(self.upper), self.scored, self.samples, self.decided]


def _rounded(v: float | None) -> float | None:
    return None if v is None else round(v, 6)


@dataclass(frozen=True)
class SearchResult:
    """What a sampler did: the score of every evaluation in order, and the lowest it found;
    samplers that estimate the map (level-set) add each cell's estimate."""

    curve: tuple[Score, ...]          # car IoU per evaluation, in the sampler's order
    best: Score                       # the lowest defined score; None if none was defined
    best_sample: Sample | None
    samples: tuple[Sample, ...] = field(default=(), repr=False)   # each evaluation's sample
    cells: tuple[CellEstimate, ...] = field(default=(), repr=False)

    @property
    def evaluations(self) -> int:
        return len(self.curve)

    @property
    def lowest(self) -> list[Score]:
        """The lowest score so far after each evaluation."""
        return lowest_so_far(self.curve)


class Recorder:
    """Wraps an evaluate callback and keeps every sample and score it passes, in order.

    Calls may come from several threads at once: `part(key)` hands out an evaluate that
    records under `key` (direct calls record under key 0), and the order kept is by key, then
    by call order within the key, so it does not depend on how the threads' calls interleave
    as long as each key is called from one thread at a time."""

    def __init__(self, evaluate: Evaluate):
        self._evaluate = evaluate
        self._lock = threading.Lock()
        self._parts: dict[int, tuple[list[Sample], list[Score]]] = {}

    def __call__(self, samples: Sequence[Sample]) -> list[Score]:
        return self._record(0, samples)

    def part(self, key: int) -> Evaluate:
        """An evaluate that records under `key` (an int; parts are kept in ascending order)."""
        return functools.partial(self._record, key)

    def _record(self, key: int, samples: Sequence[Sample]) -> list[Score]:
        scores = self._evaluate(samples)
        with self._lock:
            kept_samples, kept_scores = self._parts.setdefault(key, ([], []))
            kept_samples.extend(samples)
            kept_scores.extend(scores)
        return scores

    @property
    def samples(self) -> list[Sample]:
        with self._lock:
            return [s for k in sorted(self._parts) for s in self._parts[k][0]]

    @property
    def scores(self) -> list[Score]:
        with self._lock:
            return [s for k in sorted(self._parts) for s in self._parts[k][1]]

    def result(self) -> SearchResult:
        samples, scores = self.samples, self.scores
        best: tuple[float, Sample] | None = None
        for sample, score in zip(samples, scores, strict=True):
            s = defined(score)
            if s is not None and (best is None or s < best[0]):
                best = (s, sample)
        return SearchResult(tuple(scores), None if best is None else best[0],
                            None if best is None else best[1], tuple(samples))


def part_of(evaluate: Evaluate, key: int) -> Evaluate:
    """`evaluate.part(key)` when evaluate records in parts (a Recorder), else evaluate itself."""
    part = getattr(evaluate, "part", None)
    return evaluate if part is None else part(key)


class Sampler(Protocol):
    """Walks a space, calling `evaluate` on batches of samples until done or out of budget."""

    name: str

    def run(self, space: Space, evaluate: Evaluate, budget: int | None,
            seed: int) -> SearchResult: ...


def check_budget(name: str, budget: int | None, required: bool) -> int | None:
    """Validate a budget: a non-negative int, or None where the sampler allows it."""
    if budget is None:
        if required:
            raise ConfigError(f"sampler {name} needs a budget (number of samples to evaluate)")
        return None
    if isinstance(budget, bool) or not isinstance(budget, int) or budget < 0:
        raise ConfigError(f"sampler {name}: budget must be an integer >= 0, got {budget!r}")
    return budget


def check_batch(name: str, batch_size: int) -> None:
    if isinstance(batch_size, bool) or not isinstance(batch_size, int) or batch_size < 1:
        raise ConfigError(f"sampler {name}: batch_size must be an integer >= 1, got {batch_size!r}")


def batches(samples: Sequence[Sample], size: int) -> Iterator[Sequence[Sample]]:
    for start in range(0, len(samples), size):
        yield samples[start:start + size]


def evaluate_all(name: str, evaluate: Evaluate, samples: Sequence[Sample],
                 size: int) -> SearchResult:
    """Evaluate `samples` in batches of `size` (checked for sampler `name`), in order; returns
    what was found."""
    check_batch(name, size)
    rec = Recorder(evaluate)
    for batch in batches(samples, size):
        got = rec(batch)
        if len(got) != len(batch):
            raise RuntimeError(f"evaluate returned {len(got)} scores for {len(batch)} samples")
    return rec.result()


def covering_grid(space: Space, budget: int) -> list[Sample] | None:
    """The grid, when the space is finite (no continuous dim with lo < hi) and the budget
    covers it: there is nothing left to search, and drawing `budget` samples would score some
    twice and miss others; None otherwise."""
    if any(d.hi > d.lo for d in space.continuous()):
        return None
    return space.grid() if budget >= space.size() else None


def lowest_so_far(scores: Sequence[Score]) -> list[Score]:
    """Running minimum of the scores, skipping None, nan and inf (None until the first defined)."""
    out: list[Score] = []
    best: float | None = None
    for score in scores:
        s = defined(score)
        if s is not None and (best is None or s < best):
            best = s
        out.append(best)
    return out


REDRAW_STREAM = 1   # the random stream that replaces repeated draws on a finite space


def without_repeats(space: Space, drawn: list[Sample], seed: int) -> list[Sample]:
    """`drawn` with each repeat of an earlier draw replaced by a scene not drawn yet (a finite
    space, fewer draws than scenes): a repeat is read back, not scored, so it cost the budget a
    sample. The first draw of each scene keeps its place; replacements come from their own
    seeded stream, uniform over the scenes left (from the grid when the draws fill more than
    half of it, else drawn again until new: under two tries each)."""
    seen: set[Sample] = set()
    repeats = []
    for i, sample in enumerate(drawn):
        if sample in seen:
            repeats.append(i)
        seen.add(sample)
    if not repeats:
        return drawn
    rng = np.random.default_rng([seed, REDRAW_STREAM])
    if 2 * len(drawn) > space.size():
        rest = [g for g in space.grid() if g not in seen]
        fresh = [rest[k] for k in rng.permutation(len(rest))[:len(repeats)]]
    else:
        fresh = []
        while len(fresh) < len(repeats):
            sample = space.make({name: (dim.values[rng.integers(len(dim.values))]
                                        if isinstance(dim, Categorical) else dim.lo)
                                 for name, dim in space.dims.items()})
            if sample not in seen:
                seen.add(sample)
                fresh.append(sample)
    out = list(drawn)
    for i, sample in zip(repeats, fresh, strict=True):
        out[i] = sample
    return out
