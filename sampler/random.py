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
)
from falsify.world.space import Categorical, Sample, Space

REDRAW_STREAM = 1   # the random stream that replaces repeated draws on a finite space


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
