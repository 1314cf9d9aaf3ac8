"""Random: independent uniform samples, each continuous dim over [lo, hi], each categorical dim
over its values, from a numpy Generator seeded by the run's seed."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from falsify.sampler.base import (
    BATCH,
    Evaluate,
    SearchResult,
    check_budget,
    covering_grid,
    evaluate_all,
    without_repeats,
)
from falsify.world.space import Categorical, Sample, Space


@dataclass(frozen=True)
class RandomSampler:
    """Draws all `budget` samples up front (one column per dim, in dim order), so the samples do
    not depend on the batch size; dims of cars beyond a sample's count are pinned by Space.make.
    A budget that covers a finite space (every dim discrete) scores its grid once, in order; a
    smaller one draws each scene at most once."""

    batch_size: int = BATCH
    name: str = field(default="random", init=False)

    def samples(self, space: Space, budget: int, seed: int) -> list[Sample]:
        grid = covering_grid(space, budget)
        if grid is not None:
            return grid
        rng = np.random.default_rng(seed)
        columns: dict[str, list] = {}
        for name, dim in space.dims.items():
            if isinstance(dim, Categorical):
                idx = rng.integers(0, len(dim.values), size=budget)
                columns[name] = [dim.values[i] for i in idx]
            else:
                columns[name] = [float(v) for v in rng.uniform(dim.lo, dim.hi, size=budget)]
        drawn = [space.make({name: col[i] for name, col in columns.items()})
                 for i in range(budget)]
        if any(d.hi > d.lo for d in space.continuous()):
            return drawn   # a continuous dim: no two draws are one scene
        return without_repeats(space, drawn, seed)

    def run(self, space: Space, evaluate: Evaluate, budget: int | None,
            seed: int) -> SearchResult:
        n = check_budget(self.name, budget, required=True)
        assert n is not None
        return evaluate_all(self.name, evaluate, self.samples(space, n, seed), self.batch_size)

