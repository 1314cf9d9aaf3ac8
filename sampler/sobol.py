"""Sobol: scrambled, seeded Sobol points; one coordinate per free continuous dim (scaled to
[lo, hi]) and one per categorical dim with more than one value (value index floor(u * n))."""

from __future__ import annotations

import warnings
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
from falsify.world.space import Categorical, Continuous, Sample, Space


@dataclass(frozen=True)
class SobolSampler:
    """Coordinates: free continuous dims first, then categorical dims, each in dim order. A space
    with no free coordinate holds one sample, which is evaluated once; more generally a budget
    that covers a finite space (every dim discrete) scores its grid once, in order, and a smaller
    one scores each scene at most once (a repeat is replaced by a random scene not drawn)."""

    batch_size: int = BATCH
    name: str = field(default="sobol", init=False)

    def samples(self, space: Space, budget: int, seed: int) -> list[Sample]:
        cont = [d for d in space.dims.values() if isinstance(d, Continuous) and d.hi > d.lo]
        cat = [d for d in space.dims.values() if isinstance(d, Categorical) and len(d.values) > 1]
        if not cont and not cat:
            return [space.make({})][:budget]
        grid = covering_grid(space, budget)
        if grid is not None:
            return grid
        # imported here: 0.6 s, not at every command's start (the CLI lists the samplers)
        from scipy.stats import qmc

        engine = qmc.Sobol(len(cont) + len(cat), scramble=True, rng=seed)
        with warnings.catch_warnings():  # budgets need not be powers of two
            warnings.simplefilter("ignore", UserWarning)
            u = engine.random(budget)
        out = []
        for row in u:
            values: dict = {}
            for j, d in enumerate(cont):
                values[d.name] = float(np.clip(d.lo + row[j] * (d.hi - d.lo), d.lo, d.hi))
            for j, d in enumerate(cat, start=len(cont)):
                values[d.name] = d.values[min(int(row[j] * len(d.values)), len(d.values) - 1)]
            out.append(space.make(values))
        return out if cont else without_repeats(space, out, seed)

    def run(self, space: Space, evaluate: Evaluate, budget: int | None,
            seed: int) -> SearchResult:
        n = check_budget(self.name, budget, required=True)
        assert n is not None
        return evaluate_all(self.name, evaluate, self.samples(space, n, seed), self.batch_size)
