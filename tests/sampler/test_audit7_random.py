"""Random and Sobol search on a finite space draw each scene at most once: a repeat is read
back from the store, not scored, so a budget of 40 on a 60-scene space scored about 30 scenes
(random) or 35 (Sobol)."""

from __future__ import annotations

import tomllib

import pytest

from falsify.sampler.random import RandomSampler
from falsify.sampler.sobol import SobolSampler
from falsify.world.space import parse_space
from tests.runfixture import SMOKE


def finite_space(xs: int, ys: int, cars: int = 1):
    """smoke.toml with listed x and y (every dim discrete) and one or two cars."""
    raw = tomllib.loads(SMOKE.read_text())
    raw["dims"]["x"] = {"values": [float(v) for v in range(-xs, xs, 2)]}
    raw["dims"]["y"] = {"values": [8.0 + v for v in range(ys)]}
    if cars == 2:
        raw["dims"]["count"] = {"values": [1, 2]}
        raw["dims"]["x_2"] = {"values": [-6.0, 6.0]}
    return parse_space(raw, source="finite.toml")


@pytest.mark.parametrize("sampler", [RandomSampler(), SobolSampler()], ids=["random", "sobol"])
@pytest.mark.parametrize("xs, ys, cars, budget", [(5, 6, 1, 40), (5, 6, 1, 59), (50, 40, 1, 300),
                                                  (3, 4, 2, 30)])
def test_draws_are_distinct_scenes_of_the_space(sampler, xs, ys, cars, budget) -> None:
    space = finite_space(xs, ys, cars)
    assert budget < space.size()
    got = sampler.samples(space, budget, seed=3)
    assert len(got) == budget and len(set(got)) == budget
    assert set(got) <= set(space.grid())
    assert got == sampler.samples(space, budget, seed=3)   # the same seed, the same draws


def test_first_draws_keep_their_place() -> None:
    """Only the repeats change: a run without a repeat keeps its samples."""
    from falsify.sampler.base import without_repeats

    space = finite_space(5, 6)
    first = RandomSampler().samples(space, 40, seed=3)
    drawn = [first[0], first[1], first[0], first[2], first[1]]
    out = without_repeats(space, drawn, seed=3)
    assert out[:2] == drawn[:2] and out[3] == drawn[3] and len(set(out)) == 5
    assert without_repeats(space, first[:5], seed=3) == first[:5]


def test_a_continuous_space_is_drawn_as_before() -> None:
    space = parse_space(tomllib.loads(SMOKE.read_text()), source="smoke.toml")
    got = RandomSampler().samples(space, 3, seed=0)
    assert len(got) == 3 and all(-2.0 <= float(s["x"]) <= 2.0 for s in got)
