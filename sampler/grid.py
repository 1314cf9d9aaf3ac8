"""Grid: every sample of the space's full factorial set, once, in `Space.grid()` order."""

from __future__ import annotations

from dataclasses import dataclass, field

from falsify.sampler.base import BATCH, Evaluate, SearchResult, check_budget, evaluate_all
from falsify.world.space import Space


@dataclass(frozen=True)
class GridSampler:
    """Budget None evaluates the whole grid; an int budget evaluates its first `budget` samples
    (grid order: count, then the dims in config order, last dim fastest)."""

    batch_size: int = BATCH
    name: str = field(default="grid", init=False)

    def run(self, space: Space, evaluate: Evaluate, budget: int | None,
            seed: int) -> SearchResult:
        budget = check_budget(self.name, budget, required=False)
        samples = space.grid()
        return evaluate_all(self.name, evaluate, samples if budget is None else samples[:budget],
                            self.batch_size)
