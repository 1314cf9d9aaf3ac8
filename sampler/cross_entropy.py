"""Cross-entropy search: a product of per-dim histograms, sharpened round after round towards
the samples that failed.

The cross-entropy method (Rubinstein, "The Cross-Entropy Method for Combinatorial and
Continuous Optimization", 1999; as VerifAI uses it for falsification) draws a round of samples
from a parametric distribution, keeps the elite (here: the samples below the space's threshold,
or the lowest `elite` share of the round when fewer than that fail), and moves the distribution
towards the elite's: p <- (1 - smoothing) p + smoothing * (elite frequencies). Each continuous
dim is a histogram over `buckets` equal bins (uniform inside a bin), each categorical dim a
probability per value; a floor keeps every bin possible, so the search still explores.
Deterministic given the seed and the scores it is told, so a resumed run replays it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from falsify.errors import ConfigError
from falsify.sampler.base import (
    Evaluate,
    Recorder,
    SearchResult,
    check_batch,
    check_budget,
    covering_grid,
    defined,
    evaluate_all,
)
from falsify.world.space import Categorical, Sample, Space


@dataclass(frozen=True)
class CrossEntropySampler:
    """Rounds of `batch_size` samples; `buckets` bins per continuous dim; `elite` the share of
    a round kept when fewer than that fail; `smoothing` the step towards the elite; `floor` the
    least probability of any bin or value, as a share of uniform. A budget that covers a finite
    space (every dim discrete) scores its grid once, in order, in rounds of `batch_size`."""

    batch_size: int = 20
    buckets: int = 10
    elite: float = 0.2
    smoothing: float = 0.5
    floor: float = 0.1
    name: str = field(default="cross-entropy", init=False)

    def __post_init__(self) -> None:
        check_batch(self.name, self.batch_size)
        if isinstance(self.buckets, bool) or not isinstance(self.buckets, int) or \
                not 1 <= self.buckets <= 1000:
            raise ConfigError(f"sampler {self.name}: buckets must be an integer in 1..1000")
        for key, lo, hi in (("elite", 0.0, 1.0), ("smoothing", 0.0, 1.0), ("floor", 0.0, 1.0)):
            v = getattr(self, key)
            if isinstance(v, bool) or not isinstance(v, int | float) or not lo < v <= hi:
                raise ConfigError(f"sampler {self.name}: {key} must be in ({lo}, {hi}]")

    def run(self, space: Space, evaluate: Evaluate, budget: int | None,
            seed: int) -> SearchResult:
        n = check_budget(self.name, budget, required=True)
        assert n is not None
        grid = covering_grid(space, n)
        if grid is not None:
            return evaluate_all(self.name, evaluate, grid, self.batch_size)
        rng = np.random.default_rng(seed)
        probs = {name: np.full(self._bins(dim), 1.0 / self._bins(dim))
                 for name, dim in space.dims.items()}
        rec = Recorder(evaluate)
        done = 0
        while done < n:
            size = min(self.batch_size, n - done)
            picks = {name: rng.choice(len(p), size=size, p=p) for name, p in probs.items()}
            offsets = {name: rng.random(size) for name in space.dims}
            batch = [space.make({name: self._value(dim, int(picks[name][i]),
                                                   float(offsets[name][i]))
                                 for name, dim in space.dims.items()}) for i in range(size)]
            scores = rec(batch)
            if len(scores) != len(batch):
                raise RuntimeError(f"evaluate returned {len(scores)} scores for {size} samples")
            self._update(space, probs, batch, scores)
            done += size
        return rec.result()

    def _bins(self, dim) -> int:
        return len(dim.values) if isinstance(dim, Categorical) else self.buckets

    def _value(self, dim, b: int, u: float):
        if isinstance(dim, Categorical):
            return dim.values[b]
        width = (dim.hi - dim.lo) / self.buckets
        return float(min(dim.lo + (b + u) * width, dim.hi))

    def _bin_of(self, dim, value) -> int:
        if isinstance(dim, Categorical):
            return dim.values.index(value)
        if dim.hi == dim.lo:
            return 0
        b = int((float(value) - dim.lo) / (dim.hi - dim.lo) * self.buckets)
        return min(max(b, 0), self.buckets - 1)

    def _update(self, space: Space, probs: dict[str, np.ndarray], batch: list[Sample],
                scores: list) -> None:
        """Move each dim's histogram towards the elite of this round; a car's dims only towards
        the elite samples holding that car (the others' values were pinned, not drawn)."""
        ranked = sorted((v, i) for i, s in enumerate(scores) if (v := defined(s)) is not None)
        if not ranked:
            return
        failing = [i for s, i in ranked if s < space.threshold]
        keep = max(1, int(round(self.elite * len(ranked))))
        if len(failing) < keep and ranked[keep - 1][0] >= ranked[-1][0]:
            return   # no failure and no spread: the round says nothing about where to look
        elite = failing if len(failing) >= keep else [i for _, i in ranked[:keep]]
        for name, dim in space.dims.items():
            # a dim of a car beyond a sample's count was pinned, not drawn: it says nothing
            active = [i for i in elite if space.active(name, batch[i].count)]
            if not active:
                continue
            k = len(probs[name])
            freq = np.bincount([self._bin_of(dim, batch[i][name]) for i in active],
                               minlength=k) / len(active)
            p = (1 - self.smoothing) * probs[name] + self.smoothing * freq
            p = np.maximum(p, self.floor / k)
            probs[name] = p / p.sum()
