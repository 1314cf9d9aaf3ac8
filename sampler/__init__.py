"""Samplers: strategies that walk a modification space and hand batches of samples to a driver.

Every sampler has one method, `run(space, evaluate, budget, seed)` returning a SearchResult, and
is deterministic given its inputs and the scores it is told, so a resumed run replays from the
store without recomputing.
"""

import dataclasses

from falsify.errors import ConfigError
from falsify.sampler.base import (
    ALGORITHMS,
    NLOPT_ALGORITHMS,
    CellEstimate,
    Evaluate,
    Sampler,
    Score,
    SearchResult,
    lowest_so_far,
)
from falsify.sampler.bayes import BayesSampler
from falsify.sampler.cross_entropy import CrossEntropySampler
from falsify.sampler.grid import GridSampler
from falsify.sampler.level_set import LevelSetSampler
from falsify.sampler.nlopt import NloptSampler
from falsify.sampler.random import RandomSampler
from falsify.sampler.sobol import SobolSampler


def make_sampler(name: str, **options: object) -> Sampler:
    """Build a sampler by name; an unknown name or option raises ConfigError listing the allowed."""
    classes: dict[str, type] = {"grid": GridSampler, "random": RandomSampler,
                                "sobol": SobolSampler, "cross-entropy": CrossEntropySampler,
                                "bo": BayesSampler, "level-set": LevelSetSampler}
    if name in classes:
        cls = classes[name]
    elif name in NLOPT_ALGORITHMS:
        cls = NloptSampler
        options = {"name": name, **options}
    else:
        raise ConfigError(f"unknown sampler {name!r}; allowed: {', '.join(ALGORITHMS)}")
    settable = [f.name for f in dataclasses.fields(cls) if f.init and f.name != "name"]
    unknown = sorted(set(options) - set(settable) - {"name"})
    if unknown:
        raise ConfigError(f"sampler {name}: unknown option {unknown[0]!r}; allowed: "
                          f"{', '.join(settable) or '(none)'}")
    return cls(**options)


__all__ = [
    "ALGORITHMS",
    "CellEstimate",
    "NLOPT_ALGORITHMS",
    "Evaluate",
    "Sampler",
    "Score",
    "SearchResult",
    "lowest_so_far",
    "make_sampler",
]
