"""The gate at the edges: a cell exactly at the threshold, a baseline at a slightly different
threshold, and a baseline on a grid finer than a tenth, against hand-computed verdicts."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from falsify.errors import FalsifyError
from falsify.jobs.gate import check_objective, gate_cells, judge, worst_first
from falsify.results.miou_maps import CellMap
from tests.jobs.test_gate import iou_of
from tests.runfixture import SMOKE, write_run

# smoke.toml: x in {-2, 2}, y in {8, 14}, 2 backgrounds; its threshold is 0.65.


def test_a_cell_exactly_at_the_threshold_is_not_a_blind_spot() -> None:
    """Blind means strictly below the threshold: 0.65 at 0.65 passes, 0.6499 does not."""
    zeros = np.zeros((1, 2), np.int64)
    cmap = CellMap("x", "y", (-2.0, 2.0), (8.0,), np.array([[0.65, 0.6499]]), zeros + 2,
                   zeros, zeros)
    cells = gate_cells(cmap, 0.65)
    assert [(c.x, c.miou, c.blind) for c in cells] == [(-2.0, 0.65, False), (2.0, 0.6499, True)]
    assert [c.name for c in worst_first(cells)] == ["cell x=2 y=8"]


def test_a_baseline_at_another_threshold_is_refused_however_close(tmp_path: Path) -> None:
    run = write_run(tmp_path / "run", iou=iou_of({(-2.0, 8.0): 0.5}))
    base = tmp_path / "base.json"
    base.write_text(json.dumps(judge(run, 0.65, max_blind_spots=1).to_json()))
    assert judge(run, 0.65, baseline=base).passed
    with pytest.raises(FalsifyError, match="its blind spots are below mIoU 0.65, this gate's "
                                           "below 0.655"):
        judge(run, 0.655, baseline=base)


def test_a_new_blind_spot_a_twentieth_from_a_known_one_is_new(tmp_path: Path) -> None:
    """x in {0, 0.05, 0.1}: the baseline's blind spot is (0.1, 8); the run's new one (0.05, 8)
    is a different cell and fails the gate."""
    fine = SMOKE.read_text().replace("min = -2.0\nmax = 2.0\nstep = 4.0",
                                     "min = 0.0\nmax = 0.1\nstep = 0.05")
    assert fine != SMOKE.read_text()
    old = write_run(tmp_path / "old", fine, iou=iou_of({(0.1, 8.0): 0.5}))
    new = write_run(tmp_path / "new", fine, iou=iou_of({(0.1, 8.0): 0.5, (0.05, 8.0): 0.5}))
    result = judge(new, 0.65, baseline=old)
    assert [(c.x, c.y) for c in result.new_blind_spots] == [(0.05, 8.0)]
    assert not result.passed and result.exit_code == 1


def test_a_baseline_on_a_larger_grid_is_refused(tmp_path: Path) -> None:
    """A baseline over x {-2, 0, 2} for a run over x {-2, 2}: its blind spots at x = 0 would
    never be checked (a run shrunk to miss them passes), so the grids must be the same."""
    wide = SMOKE.read_text().replace("min = -2.0\nmax = 2.0\nstep = 4.0",
                                     "min = -2.0\nmax = 2.0\nstep = 2.0")
    assert wide != SMOKE.read_text()
    base = write_run(tmp_path / "base", wide, iou=iou_of({(0.0, 8.0): 0.5}))
    run = write_run(tmp_path / "run", iou=iou_of({}))
    with pytest.raises(FalsifyError, match=r"its cells are x \[-2, 0, 2\] × y \[8, 14\], this "
                                           r"run's x \[-2, 2\] × y \[8, 14\]"):
        judge(run, 0.65, baseline=base)


def test_a_baseline_of_the_same_class_under_its_other_name_is_accepted() -> None:
    """person is SemanticKITTI's name of the four-class pedestrian, bicyclist of cyclist."""
    check_objective("base.json", "person", "pedestrian")
    check_objective("base.json", "cyclist", "bicyclist")
    check_objective("base.json", None, "car")   # an old baseline that does not say
    with pytest.raises(FalsifyError, match="its blind spots are of car IoU, this run's of "
                                           "pedestrian IoU"):
        check_objective("base.json", "car", "pedestrian")
