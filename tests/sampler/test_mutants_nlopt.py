"""NLopt's documented start and penalty: local methods begin at the centre of the box, and an
invalid sample is told as `penalty`, so the optimiser keeps away from invalid regions."""

from __future__ import annotations

import pytest

from tests.sampler.test_samplers import paper_space, run

LOCAL = ["LN_BOBYQA", "LN_COBYLA", "LN_NELDERMEAD", "LN_SBPLX"]


@pytest.mark.parametrize("name", LOCAL)
def test_local_methods_start_at_the_centre_of_the_box(name: str) -> None:
    space = paper_space()   # x in [-5, 4], y in [5, 19]
    first = run(name, space, 5).samples[0]
    assert (first["x"], first["y"]) == (-0.5, 12.0)


@pytest.mark.parametrize("name", ["LN_BOBYQA", "LN_NELDERMEAD"])
def test_invalid_samples_are_told_as_the_penalty(name: str) -> None:
    """The left half (x < 0) is invalid, the right scores 0.5 to 0.54. Told the default
    penalty 1.0 (worse than any score), the search spends at most half its budget there; told
    0.0 (better than any score), it is drawn into the invalid half."""
    space = paper_space()

    def fn(s):
        return None if s["x"] < 0 else 0.5 + 0.01 * s["x"]

    default = run(name, space, 60, fn=fn).scores.count(None)
    zero = run(name, space, 60, fn=fn, penalty=0.0).scores.count(None)
    assert default <= 30 < zero
