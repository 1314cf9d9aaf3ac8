"""Samplers: strategies that walk a modification space and hand batches of samples to a driver.

Every sampler has one method, `run(space, evaluate, budget, seed)` returning a SearchResult, and
is deterministic given its inputs and the scores it is told, so a resumed run replays from the
store without recomputing.
"""

from falsify.sampler.base import (
    ALGORITHMS,
    NLOPT_ALGORITHMS,
    Evaluate,
    Sampler,
    Score,
    SearchResult,
    lowest_so_far,
    make_sampler,
)

__all__ = [
    "ALGORITHMS",
    "NLOPT_ALGORITHMS",
    "Evaluate",
    "Sampler",
    "Score",
    "SearchResult",
    "lowest_so_far",
    "make_sampler",
]
