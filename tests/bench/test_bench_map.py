"""`falsify bench map`: the level-set sampler against the full grid, on the grid's own scores;
its offline figures are those of a live level-set run, and a second call recomputes nothing."""

from __future__ import annotations

import json
from pathlib import Path

import pandas as pd
import pytest

from falsify.bench.map import bench_map, compare_cells
from falsify.cli import main

ROOT = Path(__file__).resolve().parents[2]
SMALL = (ROOT / "tests" / "data" / "small-grid.toml").read_text()


@pytest.fixture(scope="module")
def config(tmp_path_factory) -> Path:
    """3 x 2 positions on 3 streets: 18 samples, 6 cells of 3 replicates."""
    path = tmp_path_factory.mktemp("map") / "map.toml"
    text = SMALL.replace("min = -5.0\nmax = 3.0\nstep = 4.0", "values = [-4.0, 0.0, 4.0]")
    text = text.replace("min = 5.0\nmax = 17.0\nstep = 4.0", "values = [8.0, 17.0]")
    text = text.replace("values = [0, 5]", "values = [0, 1, 5]")
    path.write_text(text)
    return path


@pytest.fixture(scope="module")
def result(config, tmp_path_factory) -> dict:
    out = tmp_path_factory.mktemp("bench") / "out"
    return {"out": out, "json": bench_map(config, out, budgets=(0.5,), seeds=2, workers=1,
                                          threshold=0.85, timed=True)}


def test_rows_cover_each_budget_seed_and_sampler(result):
    r = result["json"]
    assert r["grid_samples"] == 18 and r["cells"] == 6
    keys = {(row["sampler"], row["budget"], row["seed"]) for row in r["rows"]}
    assert keys == {(s, b, k) for s in ("level-set", "uniform") for b in (0.5, None)
                    for k in (0, 1)}
    for row in r["rows"]:
        assert 0 <= row["agreement"] <= 1 and row["evaluations"] <= 18
        if row["budget"] == 0.5:
            assert row["evaluations"] <= 9
        if row["sampler"] == "level-set" and row["budget"] is None:
            assert row["undecided"] == 0
    assert r["machine"]["cpus"] >= 1


def test_the_offline_figure_is_the_live_run(result):
    """The unbounded level-set row of the config's seed scored the samples a real run scores:
    the same count, and the same blind cells as that run's summary."""
    r = result["json"]
    offline = next(row for row in r["rows"] if row["sampler"] == "level-set"
                   and row["budget"] is None and row["seed"] == 0)
    live = r["timed"]
    assert live["evaluations"] == offline["evaluations"]
    summary = json.loads((Path(live["run"]) / "summary.json").read_text())
    est = {(c["x"], c["y"]) for c in summary["blind_spot_cells"]}
    # the grid's own summary is at the config's threshold; the bench compares at its own
    grid = pd.read_csv(result["out"] / "grid" / "maps" / "miou_x_y.csv")
    ref = {(c.x, c.y) for c in grid.itertuples() if c.miou < r["threshold"]}
    assert 0 < len(ref) == r["grid_blind_cells"] < r["cells"]   # the far row only, at 0.85
    assert len(est ^ ref) == offline["false_safe"] + offline["false_blind"]


def test_a_second_call_recomputes_nothing_and_gives_the_same_rows(result, config):
    again = bench_map(config, result["out"], budgets=(0.5,), seeds=2, workers=1, threshold=0.85)
    assert again["rows"] == result["json"]["rows"]


def test_compare_cells_counts_false_safe_and_blind():
    ref = {("a",): 0.5, ("b",): 0.9, ("c",): 0.6}
    got = compare_cells(ref, {("a",): 0.7, ("b",): 0.6, ("c",): None}, None, 0.65)
    assert got["false_safe"] == 2 and got["false_blind"] == 1 and got["agreement"] == 0.0
    assert got["mae"] == pytest.approx((0.2 + 0.3) / 2, abs=1e-4)


@pytest.mark.parametrize("argv, match", [
    (["--budgets", "0"], "--budgets: 0.0 must be a share"),
    (["--budgets", "a,b"], "--budgets 'a,b'"),
    (["--threshold", "2"], "--threshold: 2.0"),
    (["--confidence", "1.5"], "--confidence: 1.5"),
])
def test_bad_options_exit_2_naming_them(config, tmp_path, capsys, argv, match):
    code = main(["bench", "map", "--config", str(config), "--out", str(tmp_path / "o"), *argv])
    assert code == 2 and match in capsys.readouterr().err
    assert not (tmp_path / "o" / "grid").exists()


def test_bench_map_needs_out(config, capsys):
    assert main(["bench", "map", "--config", str(config)]) == 2
    assert "--out" in capsys.readouterr().err
