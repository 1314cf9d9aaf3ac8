"""Cell maps: snapping samples to the nearest grid value, per-cell counts and means, blind spots
worst first, the per-cell comparison and a map's error, against hand-computed values."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from falsify.results.miou_maps import CellMap, compare, map_error, miou_map, snap
from falsify.world.space import load_space
from tests.runfixture import SMOKE

# smoke.toml: x in {-2, 2}, y in {8, 14}


def row_map(values: list[float]) -> CellMap:
    """A one-row map over x = 0, 1, 2, ... at y = 0."""
    n = len(values)
    zeros = np.zeros((1, n), np.int64)
    return CellMap("x", "y", tuple(float(i) for i in range(n)), (0.0,),
                   np.array([values], float), zeros + 1, zeros, zeros)


def test_samples_snap_to_the_nearest_grid_value() -> None:
    space = load_space(SMOKE)
    xs = pd.Series([-3.0, -0.5, 0.5, 1.9, 2.5])
    assert snap(xs, space, "x").tolist() == [-2.0, -2.0, 2.0, 2.0, 2.0]
    ys = pd.Series([7.0, 10.9, 11.1, 13.0])
    assert snap(ys, space, "y").tolist() == [8.0, 8.0, 14.0, 14.0]


def test_a_searched_sample_lands_in_its_nearest_cell() -> None:
    frame = pd.DataFrame({"x": [-0.5, 0.5], "y": [10.0, 12.0], "status": ["ok", "ok"],
                          "car_iou": [0.25, 0.75]})
    cmap = miou_map(frame, load_space(SMOKE))   # rows y 8, 14; columns x -2, 2
    assert cmap.miou[0, 0] == 0.25 and cmap.miou[1, 1] == 0.75
    assert np.isnan(cmap.miou[0, 1]) and np.isnan(cmap.miou[1, 0])


def test_a_cell_counts_valid_undefined_and_invalid_samples_apart() -> None:
    """Three scored samples (mean, not median), one undefined, two invalid."""
    frame = pd.DataFrame({"x": [-2.0] * 6, "y": [8.0] * 6,
                          "status": ["ok", "ok", "ok", "undefined", "invalid", "invalid"],
                          "car_iou": [0.2, 0.3, 0.9, None, None, None]})
    cmap = miou_map(frame, load_space(SMOKE))
    assert (cmap.samples[0, 0], cmap.undefined[0, 0], cmap.invalid[0, 0]) == (3, 1, 2)
    assert cmap.miou[0, 0] == pytest.approx(1.4 / 3)
    cell = cmap.cells()[0]
    assert (cell.a, cell.b, cell.samples, cell.undefined, cell.invalid) == (-2.0, 8.0, 3, 1, 2)


def test_blind_spots_are_listed_worst_first() -> None:
    cmap = row_map([0.5, 0.3, 0.9, 0.6])
    assert [(c.a, c.miou) for c in cmap.blind_spots(0.65)] == [(1.0, 0.3), (0.0, 0.5),
                                                               (3.0, 0.6)]


def test_compare_is_after_minus_before_best_first_over_cells_both_score() -> None:
    before = row_map([0.5, 0.6, 0.4])
    after = row_map([0.7, np.nan, 0.45])
    got = compare(before, after)
    assert got["x"].tolist() == [0.0, 2.0]
    assert got["change"].tolist() == pytest.approx([0.2, 0.05])


def test_map_error_blind_spots_are_strictly_below_the_threshold() -> None:
    """A reference cell exactly at the threshold is not a blind spot: both maps agree."""
    ref = row_map([0.65, 0.5, 0.9])
    err = map_error(ref, np.array([[0.65, 0.5, 0.9]]), 0.65)
    assert err.jaccard == 1.0 and err.blind_spots == 1
    assert err.mean_abs == 0.0 and err.lost_cells == 0
