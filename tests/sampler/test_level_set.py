"""The level-set sampler: which cells are blind with a fraction of the grid's evaluations.

Unit tests score a synthetic 10 x 6 map on 10 backgrounds (600 samples, no scanning) with a known
blind region near the sensor, a per-background offset and small seeded noise, and compare the
sampler's cells with the exact grid means. One real run of tests/data/small-grid.toml checks the
CLI, the run's map, --resume and the gate on an estimated map.
"""

from __future__ import annotations

import dataclasses
import io
import json
import math
import zlib
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from falsify.cli import main
from falsify.errors import ConfigError
from falsify.jobs.run import finish
from falsify.results.store import open_run
from falsify.sampler import make_sampler
from falsify.sampler.level_set import LevelSetSampler, blind_cells
from falsify.world.space import Sample, Space, load_space
from tests.conftest import Scorer
from tests.runfixture import write_run

ROOT = Path(__file__).resolve().parents[2]
SMALL = ROOT / "tests" / "data" / "small-grid.toml"   # 3 x 4 positions on 2 streets: 24 samples
T = 0.65
SYNTH = """
name = "level-set-synthetic"
seed = 0
threshold = 0.65

[dims.car_model]
values = ["sedan"]

[dims.x]
{x}

[dims.y]
{y}

[dims.background]
range = [0, {backgrounds}]
"""
X10 = "min = -9.0\nmax = 9.0\nstep = 2.0"
Y6 = "min = 5.0\nmax = 15.0\nstep = 2.0"
# per-background offsets: a hard street lowers every cell it is scored in
OFFSET = (0.06, -0.08, 0.02, 0.0, -0.03, 0.08, -0.05, 0.04, -0.01, -0.03)

Fn = Callable[[Sample], float | None]


def write_space(folder: Path, x: str = X10, y: str = Y6, backgrounds: int = 10) -> Space:
    path = folder / "space.toml"
    path.write_text(SYNTH.format(x=x, y=y, backgrounds=backgrounds))
    return load_space(path)


@pytest.fixture(scope="module")
def space(tmp_path_factory) -> Space:
    """10 x 6 cells, 10 backgrounds each: 600 samples."""
    return write_space(tmp_path_factory.mktemp("space"))


def smooth(x: float, y: float) -> float:
    """Blind close to the sensor (small y), worse off to the sides."""
    return 0.88 - 0.4 * math.exp(-(((y - 5.0) / 4.0) ** 2)) - 0.012 * abs(x)


def noisy(s: Sample, amplitude: float = 0.02) -> float:
    x, y, bg = float(s["x"]), float(s["y"]), int(s["background"])
    u = zlib.crc32(f"{x}:{y}:{bg}".encode()) / 2 ** 32 - 0.5   # seeded, uniform in [-0.5, 0.5)
    return smooth(x, y) + OFFSET[bg] + 2 * amplitude * u


def run(space: Space, fn: Fn = noisy, budget: int | None = None, seed: int = 0, **options):
    scorer = Scorer(fn)
    result = LevelSetSampler(**options).run(space, scorer, budget, seed)
    return result, scorer


def exact(space: Space, fn: Fn = noisy) -> dict[tuple, float | None]:
    """Each cell's grid mean over all its samples (None scores left out, as the grid's map)."""
    scores: dict[tuple, list[float]] = {}
    for s in space.grid():
        v = fn(s)
        scores.setdefault((s["x"], s["y"]), [])
        if v is not None:
            scores[(s["x"], s["y"])].append(v)
    return {k: float(np.mean(v)) if v else None for k, v in scores.items()}


def cells_by_key(result) -> dict:
    return {(c.x, c.y): c for c in result.cells}


# -- the map against the full grid ----------------------------------------------------------------

@pytest.mark.parametrize("seed", [0, 1, 2])
def test_unbounded_run_classifies_every_cell_as_the_grid(space, seed):
    result, scorer = run(space, seed=seed)
    truth = exact(space)
    got = cells_by_key(result)
    assert set(got) == set(truth) and len(got) == 60
    assert all(c.decided and c.estimate is not None for c in got.values())
    wrong = [k for k, c in got.items() if (c.estimate < T) != (truth[k] < T)]
    assert len(wrong) <= 1 and all(abs(truth[k] - T) <= 0.01 for k in wrong), wrong
    false_safe = [k for k, c in got.items() if truth[k] < T - 0.05 and c.estimate >= T]
    assert not false_safe
    # the planted region is found: every cell of the first row (y = 5) is blind, y = 15 none
    blind = {(c.x, c.y) for c in blind_cells(result.cells, T)}
    assert {k for k in truth if k[1] == 5.0} <= blind
    assert not {k for k in blind if k[1] == 15.0}
    assert max(abs(c.estimate - truth[k]) for k, c in got.items()) < 0.05


def test_uses_well_under_the_grid_and_only_grid_samples(space):
    result, scorer = run(space)
    grid = space.grid()
    assert result.evaluations == len(scorer.samples) < 0.6 * len(grid)
    assert len(set(scorer.samples)) == len(scorer.samples)          # no sample scored twice
    assert set(scorer.samples) <= set(grid)
    assert list(result.samples) == scorer.samples
    assert all(n <= 16 for n in scorer.batches)                      # rounds of `round`
    got = cells_by_key(result)
    assert all(c.scored >= 2 and c.samples == 10 for c in got.values())   # `initial` each
    assert sum(c.scored for c in got.values()) == result.evaluations
    # the initial round spreads the backgrounds evenly: each scored 12 times in the first 120
    first = [int(s["background"]) for s in scorer.samples[:120]]
    assert np.bincount(first, minlength=10).tolist() == [12] * 10
    assert result.best == pytest.approx(min(noisy(s) for s in scorer.samples))


def test_same_seed_same_run_other_seed_other_order(space):
    a, sa = run(space, seed=3)
    b, sb = run(space, seed=3)
    c, sc = run(space, seed=4)
    assert sa.samples == sb.samples and sa.batches == sb.batches
    assert a.cells == b.cells and a.curve == b.curve
    assert sa.samples != sc.samples
    # the other seed decides the same cells the same way (well clear of the threshold)
    assert ({k for k, e in cells_by_key(a).items() if e.estimate < T}
            == {k for k, e in cells_by_key(c).items() if e.estimate < T})


@pytest.mark.parametrize("budget", [0, 1, 5, 37, 119, 150, 10_000])
def test_budget_is_never_exceeded(space, budget):
    result, scorer = run(space, budget=budget)
    assert result.evaluations == len(scorer.samples) <= budget
    if budget < 120:   # before every cell has its initial samples: all of it is spent
        assert result.evaluations == budget
    if budget == 10_000:
        assert result.evaluations == run(space)[0].evaluations
    assert len(result.cells) == 60
    if budget == 0:
        assert scorer.batches == []
        assert all(c.estimate is None and c.scored == 0 for c in result.cells)


def test_budget_cut_cells_keep_honest_intervals(space):
    """With only 37 scores, cells without one are estimated from their neighbours, undecided
    where the interval holds the threshold, and every interval contains its estimate."""
    result, _ = run(space, budget=37)
    got = list(result.cells)
    assert sum(c.scored for c in got) == 37
    for c in got:
        assert c.estimate is not None and math.isfinite(c.estimate)
        assert c.lower <= c.estimate <= c.upper
        if c.lower < T <= c.upper:
            assert not c.decided
    assert any(c.scored == 0 for c in got)


def test_fully_scored_cells_are_exact(space):
    """A cell near the threshold is scored to its last sample; its interval is then a point,
    the grid's own mean."""
    result, _ = run(space)
    truth = exact(space)
    full = [c for c in result.cells if c.scored == c.samples]
    assert full   # (-7, 9) and (7, 9) lie within 0.003 of the threshold
    for c in full:
        assert c.lower == c.upper == c.estimate
        assert c.estimate == pytest.approx(truth[(c.x, c.y)], abs=1e-12)
        assert c.decided


def test_none_scores_are_skipped(space):
    """Invalid samples (None, nan) count for nothing: a cell with no score has no value, and
    one with every other sample invalid averages the rest."""
    dead, half = (-9.0, 15.0), (7.0, 9.0)   # half: within 0.004 of the threshold

    def fn(s: Sample) -> float | None:
        key = (s["x"], s["y"])
        if key == dead:
            return None
        if key == half and int(s["background"]) % 2:
            return float("nan")
        return noisy(s)
    result, scorer = run(space, fn)
    got = cells_by_key(result)
    # no score at all: the cell is scored to its end and has no value, as in the grid's map
    # (it was once decided from its neighbours' scores alone, after two invalid samples)
    assert got[dead].estimate is None and got[dead].lower is None and got[dead].upper is None
    assert got[dead].scored == got[dead].samples == 10 and got[dead].decided
    assert dead not in {(c.x, c.y) for c in blind_cells(result.cells, T)}
    truth = exact(space, lambda s: None if (v := fn(s)) is None or math.isnan(v) else v)
    assert truth[dead] is None
    assert got[half].scored == 10 and abs(truth[half] - T) < 0.005
    assert (got[half].estimate == got[half].lower == got[half].upper
            == pytest.approx(truth[half], abs=1e-12))   # the mean of its 5 valid scores
    for k, c in got.items():
        if k not in (dead, half):
            assert c.estimate is not None and (c.estimate < T) == (truth[k] < T)


def test_all_scores_invalid(space):
    result, scorer = run(space, lambda s: None)
    assert result.evaluations == 600 and result.best is None
    assert all(c.estimate is None and c.decided for c in result.cells)


@pytest.mark.parametrize("options, name", [
    ({"round": 0}, "round"), ({"initial": 0}, "initial"), ({"round": 2.5}, "round"),
    ({"confidence": 1.0}, "confidence"), ({"confidence": 0.4}, "confidence"),
    ({"threshold": 0}, "threshold"), ({"threshold": 1.5}, "threshold"),
    ({"prior_dof": 0}, "prior_dof"),
])
def test_bad_options_name_the_option(options, name):
    with pytest.raises(ConfigError, match=name):
        LevelSetSampler(**options)
    with pytest.raises(ConfigError, match=name):
        make_sampler("level-set", **options)


def test_unknown_option_is_refused():
    with pytest.raises(ConfigError, match="unknown option 'batch_size'"):
        make_sampler("level-set", batch_size=4)


def test_a_space_without_x_is_refused_before_scoring(space):
    no_x = dataclasses.replace(space, dims={k: v for k, v in space.dims.items() if k != "x"})
    scorer = Scorer(noisy)
    with pytest.raises(ConfigError, match="'x'"):
        LevelSetSampler().run(no_x, scorer, None, 0)
    assert scorer.samples == []


def test_negative_budget_is_refused(space):
    with pytest.raises(ConfigError, match="budget"):
        LevelSetSampler().run(space, Scorer(noisy), -1, 0)


def test_own_threshold_overrides_the_space(space):
    """threshold=0.9 makes most cells blind; the run decides them against 0.9, not 0.65."""
    result, _ = run(space, threshold=0.9)
    truth = exact(space)
    got = cells_by_key(result)
    assert all(c.decided for c in got.values())
    assert all((c.estimate < 0.9) == (truth[k] < 0.9) for k, c in got.items()
               if abs(truth[k] - 0.9) > 0.01)
    assert len(blind_cells(result.cells, 0.9)) > len(blind_cells(result.cells, T))


def test_higher_confidence_scores_more(space):
    for seed in (0, 1):
        low = run(space, lambda s: noisy(s, 0.1), seed=seed, confidence=0.6)[0].evaluations
        high = run(space, lambda s: noisy(s, 0.1), seed=seed, confidence=0.999)[0].evaluations
        assert low < high


# -- numerical extremes ---------------------------------------------------------------------------

@pytest.mark.parametrize("value", [0.5, 0.9, 0.0, 1.0])
def test_identical_scores_are_decided_after_the_initial_round(space, value):
    result, scorer = run(space, lambda s: value)
    assert result.evaluations == 120   # 2 of each cell's 10 samples
    for c in result.cells:
        assert c.decided and c.scored == 2
        assert all(math.isfinite(v) for v in (c.estimate, c.lower, c.upper, c.sd))
        assert c.estimate == pytest.approx(value, abs=1e-9)
        assert c.lower <= c.estimate <= c.upper
    assert len(blind_cells(result.cells, T)) == (60 if value < T else 0)


def test_scores_exactly_at_the_threshold_are_scored_to_the_end(space):
    """An interval around exactly 0.65 never excludes it: every cell is scored in full, and its
    value is the grid's own mean (0.65 ten times: the float the grid's map holds too)."""
    result, scorer = run(space, lambda s: T)
    assert result.evaluations == 600
    grid_mean = float(pd.Series([T] * 10).mean())
    for c in result.cells:
        assert c.decided and c.scored == c.samples == 10
        assert c.lower == c.upper == c.estimate == pytest.approx(grid_mean, abs=1e-15)
    assert (len(blind_cells(result.cells, T)) == 0) == (grid_mean >= T)


def test_a_single_cell_space(tmp_path):
    one = write_space(tmp_path, x="values = [0.0]", y="values = [9.0]")
    assert len(one.grid()) == 10
    far, _ = run(one, lambda s: 0.3 + 0.01 * int(s["background"]))
    (c,) = far.cells
    assert c.decided and c.estimate < T and far.evaluations == 2

    def near(s: Sample) -> float:   # mean 0.6572: just safe, backgrounds 0.05 apart
        return T + 0.002 + 0.05 * math.sin(1.7 * int(s["background"]))
    mean = float(np.mean([near(s) for s in one.grid()]))
    full = 0
    for seed in range(4):
        result, scorer = run(one, near, seed=seed)
        (c,) = result.cells
        assert c.decided and c.estimate >= T and result.evaluations == c.scored <= 10
        assert c.lower <= c.estimate <= c.upper
        if c.scored == 10:
            full += 1
            assert c.lower == c.upper == pytest.approx(mean, abs=1e-12)
    assert full   # most seeds have to score it to the end


def test_a_single_background(tmp_path):
    """One sample per cell: the initial round scores the whole grid and every cell is exact."""
    sp = write_space(tmp_path, backgrounds=1)
    result, scorer = run(sp)
    assert result.evaluations == 60 == len(set(scorer.samples))
    truth = exact(sp)
    for c in result.cells:
        assert c.lower == c.upper == c.estimate == pytest.approx(truth[(c.x, c.y)], abs=1e-12)


# -- runs: the CLI, the map, --resume and the gate ------------------------------------------------

def cli(args: list[str], capsys) -> tuple[int, str, str]:
    code = main(args)
    out, err = capsys.readouterr()
    return code, out, err


@pytest.fixture(scope="module")
def real_run(tmp_path_factory) -> dict:
    """One real level-set search of small-grid.toml with a budget of 20 of its 24 samples, then
    --resume on the finished run."""
    out = tmp_path_factory.mktemp("level-set") / "run"
    argv = ["search", str(SMALL), "--algorithm", "level-set", "--budget", "20", "--out",
            str(out), "--workers", "1", "--json", "--quiet", "--no-report"]
    first = _capture(argv)
    csv = (out / "maps" / "miou_x_y.csv").read_bytes()
    again = _capture([*argv, "--resume"])
    return {"out": out, "first": first, "again": again, "csv": csv}


def _capture(argv: list[str]) -> tuple[int, dict]:
    """Run the CLI in this process, its stdout parsed as the --json summary."""
    import contextlib
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        code = main(argv)
    return code, json.loads(buf.getvalue())


def test_real_run_summary_is_an_estimate(real_run):
    code, s = real_run["first"]
    assert code == 0 and s["algorithm"] == "level-set" and s["command"] == "search"
    e = s["estimated"]
    assert e["grid_samples"] == 24 and e["scored"] == 20 == s["samples"] <= e["grid_samples"]
    assert e["confidence"] == 0.95 and 0 <= e["undecided_cells"] <= 12
    assert s["computed_this_time"] == 20 and s["cells"] == 12


def test_real_run_map_has_intervals(real_run):
    frame = pd.read_csv(io.BytesIO(real_run["csv"]))
    assert list(frame.columns) == ["x", "y", "miou", "samples", "undefined", "invalid",
                                   "lower", "upper"]
    assert len(frame) == 12 and frame["samples"].sum() == 20
    full, cut = frame[frame["samples"] == 2], frame[frame["samples"] == 1]
    assert len(full) == 8 and len(cut) == 4   # the budget ran out in the initial round
    assert (full["lower"] == full["miou"]).all() and (full["upper"] == full["miou"]).all()
    assert (cut["lower"] < cut["miou"]).all() and (cut["miou"] < cut["upper"]).all()
    # a fully scored cell's value is its rows' mean
    rows = open_run(real_run["out"]).frame
    for _, cell in full.iterrows():
        mine = rows[(rows["x"] == cell["x"]) & (rows["y"] == cell["y"])]["car_iou"]
        assert cell["miou"] == pytest.approx(float(mine.mean()), abs=1e-6)
    # the summary's undecided count is the sampler's own: cells it had not decided (its safe
    # bound is stricter than the interval shown, so a shown interval may be clear of T)
    stored = open_run(real_run["out"]).meta["cell_estimates"]
    open_ = sum(1 for e in stored if not e[7])
    assert real_run["first"][1]["estimated"]["undecided_cells"] == open_
    shown = ((frame["lower"] < T) & (T <= frame["upper"])).sum()
    assert shown <= open_


def test_resume_of_a_finished_run_recomputes_nothing(real_run):
    code, s = real_run["again"]
    first = real_run["first"][1]
    assert code == 0 and s["computed_this_time"] == 0 and s["samples"] == 20
    assert s["blind_spot_cells"] == first["blind_spot_cells"]
    assert s["estimated"] == first["estimated"]
    assert (real_run["out"] / "maps" / "miou_x_y.csv").read_bytes() == real_run["csv"]


def test_resume_with_another_confidence_is_refused(real_run, capsys):
    """The confidence chose the run's samples: a resumed run must keep it."""
    out = real_run["out"]
    before = (out / "results.sqlite").read_bytes()
    code, _, err = cli(["search", str(SMALL), "--algorithm", "level-set", "--budget", "20",
                        "--confidence", "0.9", "--out", str(out), "--resume", "--quiet"], capsys)
    assert code == 2 and "sampler_options" in err
    assert (out / "results.sqlite").read_bytes() == before


def test_gate_counts_the_estimated_map(real_run, capsys):
    frame = pd.read_csv(io.BytesIO(real_run["csv"]))
    values = sorted(frame["miou"])
    thr = round((values[5] + values[6]) / 2, 6)   # six cells below it
    code, out, _ = cli(["gate", str(real_run["out"]), "--threshold", str(thr), "--json"], capsys)
    doc = json.loads(out)
    assert code == 1 and len(doc["blind_spots"]) == 6
    by_cell = {(c["x"], c["y"]): c["miou"] for c in doc["cells"]}
    for _, cell in frame.iterrows():
        assert by_cell[(cell["x"], cell["y"])] == pytest.approx(cell["miou"], abs=1e-6)


def test_confidence_out_of_range_exits_2(tmp_path, capsys):
    out = tmp_path / "r"
    code, _, err = cli(["search", str(SMALL), "--algorithm", "level-set", "--confidence", "1.5",
                        "--out", str(out), "--quiet"], capsys)
    assert code == 2 and "--confidence" in err
    assert not out.exists()   # nothing written


def test_confidence_with_another_sampler_exits_2(tmp_path, capsys):
    out = tmp_path / "r"
    code, _, err = cli(["search", str(SMALL), "--algorithm", "random", "--budget", "5",
                        "--confidence", "0.9", "--out", str(out), "--quiet"], capsys)
    assert code == 2 and "--confidence" in err and "level-set" in err
    assert not out.exists()   # nothing written


def test_search_without_budget_is_refused_for_other_samplers(tmp_path, capsys):
    code, _, err = cli(["search", str(SMALL), "--algorithm", "random", "--out",
                        str(tmp_path / "r"), "--quiet"], capsys)
    assert code == 2 and "--budget" in err


# -- stored runs: what the map, summary and gate read ---------------------------------------------

ESTIMATE_BLIND = (-5.0, 5.0)


def synthetic_level_set_run(folder: Path) -> Path:
    """A level-set run's store without scanning: rows at IoU 0.8 for every cell but
    ESTIMATE_BLIND (never scored), whose estimate is 0.5; one other cell is undecided."""
    space = load_space(SMALL)
    samples = [s for s in space.grid() if (s["x"], s["y"]) != ESTIMATE_BLIND]
    estimates = []
    for x in space.dims["x"].grid():
        for y in space.dims["y"].grid():
            scored = 0 if (x, y) == ESTIMATE_BLIND else 2
            est, lo, hi = (0.5, 0.4, 0.6) if (x, y) == ESTIMATE_BLIND else (0.8, 0.8, 0.8)
            if (x, y) == (3.0, 17.0):
                est, lo, hi = 0.8, 0.6, 0.95
            estimates.append([x, y, est, lo, hi, scored, 2, (x, y) != (3.0, 17.0)])
    return write_run(folder, SMALL, command="search", iou=lambda s: 0.8, samples=samples,
                     meta={"algorithm": "level-set", "budget": None, "cell_estimates": estimates,
                           "sampler_options": {"threshold": T, "confidence": 0.9}})


def test_gate_reads_the_estimate_not_the_rows(tmp_path, capsys):
    run_dir = synthetic_level_set_run(tmp_path / "ls")
    code, out, _ = cli(["gate", str(run_dir), "--json"], capsys)
    doc = json.loads(out)
    assert code == 1
    assert [(c["x"], c["y"]) for c in doc["blind_spots"]] == [ESTIMATE_BLIND]
    assert doc["blind_spots"][0]["miou"] == 0.5 and doc["blind_spots"][0]["samples"] == 0
    # the same rows without the estimates: no cell is blind, the unscored one has no value
    plain = write_run(tmp_path / "plain", SMALL, command="search", iou=lambda s: 0.8,
                      samples=[s for s in load_space(SMALL).grid()
                               if (s["x"], s["y"]) != ESTIMATE_BLIND])
    code, out, _ = cli(["gate", str(plain), "--json"], capsys)
    assert code == 0 and json.loads(out)["blind_spots"] == []


def test_finish_writes_the_estimated_map_and_summary(tmp_path):
    run_dir = synthetic_level_set_run(tmp_path / "ls")
    summary = finish(run_dir, load_space(SMALL), report=False).to_json()
    assert summary["blind_spots"] == 1
    (cell,) = summary["blind_spot_cells"]
    assert (cell["x"], cell["y"]) == ESTIMATE_BLIND
    assert cell["miou"] == 0.5 and cell["lower"] == 0.4 and cell["upper"] == 0.6
    assert summary["estimated"] == {"grid_samples": 24, "scored": 22, "confidence": 0.9,
                                    "undecided_cells": 1}
    header = (run_dir / "maps" / "miou_x_y.csv").read_text().splitlines()[0]
    assert header == "x,y,miou,samples,undefined,invalid,lower,upper"


def test_a_grid_run_map_keeps_its_columns(tmp_path):
    run_dir = write_run(tmp_path / "grid", SMALL, iou=lambda s: 0.8)
    summary = finish(run_dir, load_space(SMALL), report=False).to_json()
    assert "estimated" not in summary
    text = (run_dir / "maps" / "miou_x_y.csv").read_text()
    assert text.splitlines()[0] == "x,y,miou,samples,undefined,invalid"
    assert open_run(run_dir).cell_map().estimated is False
