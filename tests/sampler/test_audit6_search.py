"""Samplers and the search loop at the extremes: budgets that cover a finite space, the dims of
cars a sample does not hold (cross-entropy), a batch asking for a sample twice (the progress),
non-finite scores, level-set cut in its first round or given a map too large for its model, and
NLopt told of a budget below its discrete combinations before it makes them."""

from __future__ import annotations

import importlib.util
import math
from pathlib import Path

import numpy as np
import pytest

from falsify.errors import ConfigError
from falsify.executors.driver import Driver, Progress
from falsify.executors.evaluator import EvalSettings
from falsify.results.store import STORE_NAME, Store, read_frame, read_meta
from falsify.sampler import make_sampler
from tests.conftest import ROOT, Scorer
from tests.runfixture import synthetic_result
from tests.sampler.test_level_set import exact, write_space
from tests.sampler.test_level_set import run as level_set_run
from tests.sampler.test_samplers import run, space_of

needs_optuna = pytest.mark.skipif(importlib.util.find_spec("optuna") is None,
                                  reason="optuna (falsify[bo]) is not installed")
BATCH_SAMPLERS = ["random", "sobol", "cross-entropy", pytest.param("bo", marks=needs_optuna)]
BUNDLED = ROOT / "models" / "weights" / "squeezeseg.onnx"


def finite_space():
    """Two car models on two backgrounds, x and y fixed: four samples in all."""
    return space_of({"car_model": {"values": ["sedan", "suv"]}, "x": {"values": [0.0]},
                     "y": {"values": [8.0]}, "background": {"values": [0, 1]}})


# ---- a budget that covers a finite space ------------------------------------------------------

@pytest.mark.parametrize("name", BATCH_SAMPLERS)
def test_a_budget_covering_a_finite_space_scores_its_grid_once(name):
    """Budget 10 over four samples drew ten with replacement: repeats, and (random, seed 0)
    one of the four never scored. The grid is scored once instead."""
    space = finite_space()
    for budget in (4, 10):
        rec = run(name, space, budget, seed=0)
        assert rec.samples == space.grid(), (name, budget)
    assert len(run(name, space, 3, seed=0).samples) == 3   # below the grid: the budget


@pytest.mark.parametrize("name", BATCH_SAMPLERS)
def test_a_finite_space_of_one_or_two_cars_is_covered(name):
    """Count 1 or 2, the second car's model listed: six samples, each scored once."""
    space = space_of({"car_model": {"values": ["sedan", "suv"]}, "x": {"values": [0.0]},
                      "y": {"values": [8.0]}, "background": {"values": [0]},
                      "count": {"values": [1, 2]}, "x_2": {"values": [3.0]}})
    assert space.size() == 6
    assert run(name, space, 6, seed=0).samples == space.grid()


@pytest.mark.parametrize("name", BATCH_SAMPLERS)
def test_a_free_continuous_dim_keeps_the_whole_budget(name):
    space = space_of({"car_model": {"values": ["sedan"]}, "x": {"min": -1, "max": 1, "step": 1},
                      "y": {"values": [8.0]}, "background": {"values": [0]}})
    samples = run(name, space, 6, seed=0).samples
    assert len(samples) == 6 and len(set(samples)) == 6   # 6 > the 3 grid points: still drawn


@pytest.mark.skipif(not BUNDLED.exists(), reason="bundled model not trained yet")
def test_search_command_scores_a_covered_finite_space_once(tmp_path, capsys):
    """`falsify search` on the four-sample space with --budget 10: four rows and a curve of
    four (it stored three rows and a curve of ten, never scoring suv on background 1)."""
    from falsify.cli import main

    config = tmp_path / "finite.toml"
    config.write_text('name = "finite"\nsensor = "kitti-hdl64e-front"\nseed = 0\n'
                      '[dims.car_model]\nvalues = ["sedan", "suv"]\n[dims.x]\nvalues = [0.0]\n'
                      '[dims.y]\nvalues = [8.0]\n[dims.background]\nvalues = [0, 1]\n')
    out = tmp_path / "run"
    assert main(["search", str(config), "--algorithm", "random", "--budget", "10", "--out",
                 str(out), "--workers", "1", "--no-report", "--quiet"]) == 0
    frame = read_frame(out)
    assert sorted(zip(frame["car_model"], frame["background"], strict=True)) == [
        ("sedan", 0), ("sedan", 1), ("suv", 0), ("suv", 1)]
    assert len(read_meta(out)["curve"]) == 4
    assert read_meta(out)["planned"] == 4   # the plan is the grid, not the budget of 10
    assert "4 samples (4 computed now" in capsys.readouterr().out


# ---- cross-entropy: the dims of cars a sample does not hold -----------------------------------

def test_cross_entropy_leaves_the_dims_of_absent_cars_alone():
    """Samples with one car fail, so they are the elite; their x_2 was pinned to its lowest
    value, not drawn. Counting it dragged x_2's histogram to its first bin (13 of 14 two-car
    samples there); x_2 must stay as it was, spread over its range."""
    space = space_of({"car_model": {"values": ["sedan"]}, "background": {"values": [0]},
                      "x": {"min": -4, "max": 4, "step": 1}, "y": {"values": [8.0]},
                      "count": {"values": [1, 2]}, "x_2": {"min": 0, "max": 10, "step": 1}})
    rec = run("cross-entropy", space, 400, seed=0,
              fn=lambda s: 0.2 if s.count == 1 else 0.9)
    x2 = np.array([float(s["x_2"]) for s in rec.samples[200:] if s.count == 2])
    assert len(x2) >= 5
    assert np.mean(x2 < 1.0) < 0.5, np.histogram(x2, bins=10, range=(0, 10))[0]


def test_cross_entropy_still_sharpens_the_dims_of_held_cars():
    """Two-car samples with x_2 high fail: x_2 moves towards them."""
    space = space_of({"car_model": {"values": ["sedan"]}, "background": {"values": [0]},
                      "x": {"values": [0.0]}, "y": {"values": [8.0]},
                      "count": {"values": [2]}, "x_2": {"min": 0, "max": 10, "step": 1}})
    rec = run("cross-entropy", space, 200, seed=0,
              fn=lambda s: 0.2 if float(s["x_2"]) > 8 else 0.9)
    x2 = np.array([float(s["x_2"]) for s in rec.samples[100:]])
    assert np.mean(x2 > 8) > 0.5


# ---- the driver's progress ---------------------------------------------------------------------

class _Executor:
    """Scores chunks with a fixed IoU, counting what it computed."""

    def __init__(self):
        self.computed = 0

    def map(self, chunks):
        for chunk in chunks:
            self.computed += len(chunk)
            yield [synthetic_result(s, 0.5, i) for i, s in enumerate(chunk)]


def test_driver_counts_a_new_sample_asked_twice_as_two_done(tmp_path: Path):
    """A batch asking for a new sample twice computes it once, and both asks are done: the
    progress bar ended at 2/3 for random's three draws of two samples."""
    space = finite_space()
    a, b = space.grid()[:2]
    progress = Progress(3)
    store = Store(tmp_path / STORE_NAME, space)
    driver = Driver(EvalSettings(space=space), store, progress=progress)
    driver.executor, driver.model_hash = _Executor(), "m"
    scores = driver.evaluate([a, b, a])
    assert driver.executor.computed == 2 and len(store) == 2
    assert scores[0] == scores[2] and scores[0] is not None
    assert (progress.done, progress.computed) == (3, 2)
    driver.evaluate([a, b])                      # stored: read back, counted, not computed
    assert (progress.done, progress.computed, driver.executor.computed) == (5, 2, 2)
    store.close()


def test_nlopt_already_stops_at_the_grid_of_a_finite_space():
    """NLopt's outer loop scores each discrete combination once when nothing is free."""
    space = finite_space()
    for name in ("LN_BOBYQA", "GN_DIRECT_L", "GN_CRS2_LM"):
        assert run(name, space, 10, seed=0).samples == space.grid(), name


# ---- scores that are not numbers in range ------------------------------------------------------

SEARCHERS = ["random", "sobol", "cross-entropy", "level-set", "GN_DIRECT_L", "LN_COBYLA",
             "LN_BOBYQA", "GN_CRS2_LM", pytest.param("bo", marks=needs_optuna)]


@pytest.mark.parametrize("bad", [math.inf, -math.inf, math.nan])
@pytest.mark.parametrize("name", SEARCHERS)
def test_a_non_finite_score_counts_as_no_score(name, bad):
    """inf crashed DIRECT (nlopt runtime_error) and COBYLA (it proposed x = nan: "x: nan is
    outside [-2, 2]"), and -inf was reported as the lowest score; like None, it is now told
    as the penalty and never reported."""
    space = space_of({"car_model": {"values": ["sedan"]}, "background": {"values": [0]},
                      "x": {"min": -2, "max": 2, "step": 1}, "y": {"min": 5, "max": 9, "step": 1}})

    def fn(s):
        return bad if float(s["x"]) > 0 else 0.5 + 0.01 * float(s["y"])

    result = make_sampler(name).run(space, Scorer(fn), 20, 0)
    assert result.best is not None and 0.55 <= result.best <= 0.59
    assert float(result.best_sample["x"]) <= 0
    assert all(v is None or math.isfinite(v) for v in result.lowest)


# ---- level-set: a budget that ends in the first round -----------------------------------------

@pytest.mark.parametrize("budget", [1, 37, 60])
def test_level_set_cut_in_its_first_round_decides_no_cell_from_one_score(tmp_path, budget):
    """Budget 37 on 60 cells of 10 backgrounds: each scored cell holds one score, so nothing
    measures the residual variance, which sat at its floor: all 37 cells were called decided
    on intervals 0.0115 wide, 36 of which missed the grid's value and one decided wrongly."""
    space = write_space(tmp_path)
    truth = exact(space)
    result, _ = level_set_run(space, budget=budget)
    scored = [c for c in result.cells if c.scored]
    assert len(scored) == budget
    for c in scored:
        assert not c.decided
        assert c.lower <= truth[(c.x, c.y)] <= c.upper
        assert c.lower <= c.estimate <= c.upper


def test_level_set_first_round_complete_still_decides(tmp_path):
    """Once cells hold two scores the variance is measured again: cells are decided."""
    space = write_space(tmp_path)
    result, _ = level_set_run(space, budget=120)
    assert sum(c.decided for c in result.cells) >= 50


# ---- level-set: a map too large for its model ---------------------------------------------------

def _never(batch):
    raise AssertionError(f"scored {len(batch)} samples of a map the model cannot fit")


def test_level_set_refuses_a_map_too_large_before_scoring():
    """A fine x step gave 800,002 cells: `search --algorithm level-set --budget 4` ran for
    minutes without scoring a sample (each round's fit is dense over every cell)."""
    space = space_of({"car_model": {"values": ["sedan"]}, "background": {"values": [0, 1]},
                      "x": {"min": -2, "max": 2, "step": 0.001}, "y": {"values": [8.0]}})
    with pytest.raises(ConfigError, match=r"level-set: the map has 4,001 cells \(x: 4,001 "
                                          r"values, y: 1\).*dims\.x or dims\.y steps"):
        make_sampler("level-set").run(space, _never, 4, 0)


def test_level_set_counts_samples_per_cell_in_its_model_size():
    """Few cells but 2,000 backgrounds each: the replicates enter the model too."""
    space = space_of({"car_model": {"values": ["sedan"]}, "background": {"range": [0, 2000]},
                      "x": {"values": [0.0]}, "y": {"values": [8.0]}})
    with pytest.raises(ConfigError, match="1 cell .* and 2,000 samples per cell"):
        make_sampler("level-set").run(space, _never, 4, 0)


@pytest.mark.skipif(not BUNDLED.exists(), reason="bundled model not trained yet")
def test_search_level_set_on_a_huge_map_exits_2_writing_nothing(tmp_path, capsys):
    from falsify.cli import main

    config = tmp_path / "fine.toml"
    config.write_text('name = "fine"\nsensor = "kitti-hdl64e-front"\nseed = 0\n'
                      '[dims.car_model]\nvalues = ["sedan"]\n[dims.x]\nmin = -2.0\nmax = 2.0\n'
                      'step = 0.00001\n[dims.y]\nmin = 8.0\nmax = 14.0\nstep = 6.0\n'
                      '[dims.background]\nvalues = [0, 1]\n')
    out = tmp_path / "run"
    assert main(["search", str(config), "--algorithm", "level-set", "--budget", "4", "--out",
                 str(out), "--quiet", "--no-report"]) == 2
    err = capsys.readouterr().err
    assert "level-set: the map has 800,002 cells" in err and "dims.x" in err
    assert not out.exists()


# ---- NLopt: a budget below the discrete combinations, told before they are made ----------------

def test_nlopt_refuses_a_small_budget_without_making_every_combination(monkeypatch):
    """20,000 backgrounds x 36 yaws x 2 models: 1,440,000 combinations were made (2 s, 0.4 GB;
    a larger space exhausted memory) before `--budget 100` was refused."""
    import falsify.sampler.nlopt as nlopt_module

    def made(space):
        raise AssertionError("every combination was made")

    monkeypatch.setattr(nlopt_module, "discrete_combos", made)
    space = space_of({"car_model": {"values": ["sedan", "suv"]},
                      "background": {"range": [0, 20000]}, "x": {"min": -2, "max": 2, "step": 1},
                      "y": {"values": [8.0]},
                      "yaw": {"values": [float(v) for v in range(0, 360, 10)]}})
    with pytest.raises(ConfigError, match="budget 100 is smaller than the 1,440,000 "
                                          "combinations of discrete dims"):
        make_sampler("LN_BOBYQA").run(space, _never, 100, 0)
    assert nlopt_module.combo_count(space) == 1_440_000
