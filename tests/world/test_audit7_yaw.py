"""A heading grid holds each heading once: -180 and 180 degrees are one scene, which a grid over
-180..180 scored twice (and a level-set map counted as two samples of its cell)."""

from __future__ import annotations

import pytest

from falsify.errors import ConfigError
from falsify.world.space_dims import read_continuous_or_values


@pytest.mark.parametrize("spec, grid", [
    ({"min": -180.0, "max": 180.0, "step": 45.0},
     (-180.0, -135.0, -90.0, -45.0, 0.0, 45.0, 90.0, 135.0)),
    ({"min": 0.0, "max": 360.0, "step": 120.0}, (0.0, 120.0, 240.0)),
    ({"min": -360.0, "max": 360.0, "step": 90.0}, (-360.0, -270.0, -180.0, -90.0)),
    # 70 degrees come round only after 36 steps: no heading repeats within the range
    ({"min": -180.0, "max": 180.0, "step": 70.0}, (-180.0, -110.0, -40.0, 30.0, 100.0, 170.0)),
    ({"min": -90.0, "max": 90.0, "step": 90.0}, (-90.0, 0.0, 90.0)),
    ({"min": 0.0, "max": 350.0, "step": 10.0}, tuple(float(v) for v in range(0, 351, 10))),
    # a step of 0.1 (not exact in binary) still comes round after 3,600 steps
    ({"min": 0.0, "max": 360.0, "step": 0.1}, None),
])
def test_a_heading_range_stops_before_it_comes_round(spec, grid) -> None:
    dim = read_continuous_or_values("yaw", spec, "")
    if grid is None:
        assert dim.size == 3600 and len(set(dim.grid())) == 3600
    else:
        assert dim.grid() == grid and dim.size == len(grid)
    # the range itself is kept for a continuous search
    assert (dim.lo, dim.hi) == (spec["min"], spec["max"])


def test_other_objects_headings_come_round_too() -> None:
    assert read_continuous_or_values("yaw_2", {"min": -180.0, "max": 180.0, "step": 90.0},
                                     "").size == 4
    # a position's range has no turn
    assert read_continuous_or_values("x", {"min": -180.0, "max": 180.0, "step": 90.0},
                                     "").size == 5


@pytest.mark.parametrize("values, said", [([-180.0, 0.0, 180.0], "-180 and 180"),
                                          ([0, 90, 360], "0 and 360"),
                                          ([-90.0, 270.0], "-90 and 270")])
def test_listed_headings_that_are_one_are_refused(values, said) -> None:
    with pytest.raises(ConfigError, match=f"dims.yaw.values: {said} degrees are one heading"):
        read_continuous_or_values("yaw", {"values": values}, "")
