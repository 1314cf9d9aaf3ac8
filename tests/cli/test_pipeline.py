"""The falsification pipeline end to end on the bundled model: store, resume, maps, CLI errors."""

from __future__ import annotations

import json
import os
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd
import pytest

from falsify.cli import main
from falsify.executors.evaluator import EvalSettings, Evaluator
from falsify.jobs.run import RunRequest, execute
from falsify.results.store import TIMING_COLUMNS, read_frame, read_meta
from falsify.world.space import load_space
from tests.conftest import CONFIGS, NO_TORCH, ROOT

BUNDLED = ROOT / "models" / "weights" / "squeezeseg.onnx"
pytestmark = pytest.mark.skipif(not BUNDLED.exists(), reason="bundled model not trained yet")


def small_config(tmp_path: Path, xs=(-2.0, 2.0, 2.0), ys=(8.0, 12.0, 4.0), backgrounds=(0, 1),
                 extra: str = "", sensor: str = "kitti-hdl64e-front") -> Path:
    text = f'''name = "small"
sensor = "{sensor}"
seed = 0
[dims.car_model]
values = ["sedan"]
[dims.x]
min = {xs[0]}
max = {xs[1]}
step = {xs[2]}
[dims.y]
min = {ys[0]}
max = {ys[1]}
step = {ys[2]}
[dims.background]
values = {list(backgrounds)}
{extra}'''
    path = tmp_path / "small.toml"
    path.write_text(text)
    return path


def rows(run: Path) -> pd.DataFrame:
    return read_frame(run).drop(columns=list(TIMING_COLUMNS))


def test_grid_smoke_end_to_end(tmp_path, capsys):
    run = tmp_path / "run"
    assert main(["grid", str(CONFIGS / "smoke.toml"), "--out", str(run), "--json",
                 "--quiet"]) == 0
    summary = json.loads(capsys.readouterr().out)
    frame = read_frame(run)
    assert len(frame) == 8 == summary["samples"]
    assert set(frame["status"]) <= {"ok", "undefined", "invalid"}
    assert frame["model_hash"].nunique() == 1 and frame["config_hash"].nunique() == 1
    assert (run / "maps" / "miou_x_y.csv").exists()
    assert (run / "results.csv").exists()
    cells = pd.read_csv(run / "maps" / "miou_x_y.csv")
    assert len(cells) == 4
    assert summary["blind_spots"] == int((cells["miou"] < 0.65).sum())
    # the bundled network has no blind spot here (mean 0.91), so no retraining set: the set's
    # files are checked where cells are blind (tests/jobs/test_retrain_format.py)
    assert summary["blind_spots"] == summary["retraining_samples"] == 0
    assert not (run / "retrain").exists()


def kill_after_rows(cmd: list[str], db: Path, rows: int) -> int:
    """Start `cmd`, SIGKILL it once its store holds `rows` rows (or it ends, or 120 s pass);
    the row count last seen."""
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.time() + 120
    n = 0
    while time.time() < deadline and proc.poll() is None:
        if db.exists():
            try:
                with sqlite3.connect(db, timeout=1) as c:
                    n = c.execute("SELECT COUNT(*) FROM samples").fetchone()[0]
            except sqlite3.OperationalError:
                n = 0
            if n >= rows:
                break
        time.sleep(0.05)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    return n


@pytest.mark.slow
def test_killed_run_resumes_to_the_same_rows(tmp_path):
    config = small_config(tmp_path, xs=(-4.0, 4.0, 2.0), ys=(6.0, 18.0, 3.0))  # 5×5×2 = 50
    full, killed = tmp_path / "full", tmp_path / "killed"
    assert main(["grid", str(config), "--out", str(full), "--quiet", "--no-report"]) == 0
    cmd = [sys.executable, "-m", "falsify", "grid", str(config), "--out", str(killed),
           "--quiet", "--no-report"]
    n = kill_after_rows(cmd, killed / "results.sqlite", 10)
    assert 10 <= n < 50, "the run must be killed in the middle"
    partial = len(read_frame(killed))
    assert partial >= n
    r = subprocess.run(cmd + ["--resume", "--json"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    summary = json.loads(r.stdout)
    assert summary["computed_this_time"] == 50 - partial
    pd.testing.assert_frame_equal(rows(full), rows(killed))


def test_existing_run_needs_resume_and_same_config(tmp_path, capsys):
    config = small_config(tmp_path)
    run = tmp_path / "run"
    assert main(["grid", str(config), "--out", str(run), "--quiet", "--no-report"]) == 0
    before = (run / "results.sqlite").read_bytes()
    assert main(["grid", str(config), "--out", str(run), "--quiet"]) == 2
    assert "pass --resume" in capsys.readouterr().err
    (tmp_path / "o").mkdir()
    other = small_config(tmp_path / "o", backgrounds=(0, 2))
    assert main(["grid", str(other), "--out", str(run), "--quiet", "--resume"]) == 2
    assert "config_hash differs" in capsys.readouterr().err
    assert main(["grid", str(config), "--out", str(run), "--quiet", "--resume",
                 "--no-report"]) == 0
    assert len(read_frame(run)) == 12  # 3 x 2 positions on 2 backgrounds, none twice
    assert (run / "results.sqlite").read_bytes()[:100] == before[:100]


@pytest.mark.parametrize(("args", "message"), [
    (["search", "CFG", "--out", "OUT", "--algorithm", "GN_FOO", "--budget", "5"],
     "invalid choice"),
    (["search", "CFG", "--out", "OUT", "--algorithm", "random"], "--budget"),
    (["grid", "CFG", "--out", "OUT", "--workers", "0"], "--workers: 0"),
    (["grid", "CFG", "--out", "OUT", "--model", "missing.onnx"], "missing.onnx"),
    (["grid", "CFG", "--out", "OUT", "--threshold", "2"], "--threshold"),
    (["grid", "CFG", "--out", "OUT", "--fidelity", "ultra"], "invalid choice"),
    (["grid", "CFG", "--out", "OUT", "--resume"], "no run to resume"),
    (["grid", "nope.toml", "--out", "OUT"], "nope.toml"),
])
def test_bad_arguments_exit_2_and_write_nothing(tmp_path, capsys, args, message):
    config = small_config(tmp_path)
    out = tmp_path / "out"
    argv = [a.replace("CFG", str(config)).replace("OUT", str(out)) for a in args]
    with pytest.raises(SystemExit) as err:
        sys.exit(main(argv))
    assert err.value.code == 2
    assert message in capsys.readouterr().err
    assert not out.exists()


def test_model_for_another_resolution_is_rejected_before_any_sample(tmp_path, capsys):
    sensor = tmp_path / "s.toml"
    sensor.write_text((ROOT / "configs/sensors/kitti-hdl64e-front.toml").read_text()
                      .replace("columns = 512", "columns = 256"))
    config = small_config(tmp_path, sensor=str(sensor))
    assert main(["grid", str(config), "--out", str(tmp_path / "o"), "--quiet"]) == 2
    assert "makes 64×256" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_random_and_sobol_are_reproducible_by_seed(tmp_path):
    config = small_config(tmp_path, xs=(-4.0, 4.0, 1.0), ys=(6.0, 18.0, 1.0))
    for algo in ("random", "sobol"):
        runs = []
        for k, seed in enumerate((3, 3, 4)):
            out = tmp_path / f"{algo}{k}"
            assert main(["search", str(config), "--algorithm", algo, "--budget", "6", "--seed",
                         str(seed), "--out", str(out), "--quiet", "--no-report"]) == 0
            runs.append(rows(out))
        pd.testing.assert_frame_equal(runs[0], runs[1])
        assert not runs[0][["x", "y"]].equals(runs[2][["x", "y"]])


def test_nlopt_search_stays_in_bounds_and_budget(tmp_path, capsys):
    config = small_config(tmp_path, xs=(-4.0, 4.0, 1.0), ys=(6.0, 18.0, 1.0), backgrounds=(0,))
    out = tmp_path / "nl"
    assert main(["search", str(config), "--algorithm", "LN_BOBYQA", "--budget", "8", "--out",
                 str(out), "--quiet", "--no-report", "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    frame = read_frame(out)
    assert 1 <= len(frame) <= 8 and summary["samples"] == len(frame)
    assert frame["x"].between(-4, 4).all() and frame["y"].between(6, 18).all()


def test_undefined_and_invalid_samples_are_stored_with_reasons(tmp_path):
    sensor = tmp_path / "short.toml"
    sensor.write_text((ROOT / "configs/sensors/kitti-hdl64e-front.toml").read_text()
                      .replace("max_range = 120.0", "max_range = 6.0"))
    config = small_config(tmp_path, xs=(0.0, 0.0, 1.0), ys=(3.0, 19.0, 16.0), backgrounds=(0,),
                          sensor=str(sensor))
    out = tmp_path / "u"
    assert main(["grid", str(config), "--out", str(out), "--quiet", "--no-report"]) == 0
    frame = read_frame(out).set_index("y")
    assert frame.loc[3.0, "status"] == "invalid"
    assert "ego vehicle" in frame.loc[3.0, "reason"]
    far = frame.loc[19.0]   # beyond the sensor's 6 m: the car returns nothing to score
    assert far["status"] == "invalid" and pd.isna(far["car_iou"])
    assert "no point of the placed object reaches the sensor" in far["reason"]


def test_a_car_the_sensor_cannot_see_is_invalid_not_scored_on_the_street(tmp_path, capsys):
    """Behind a front-facing sensor the placed car returns no point; the street's parked cars
    would otherwise give the sample a car IoU that says nothing of the car under test."""
    config = small_config(tmp_path, xs=(0.0, 0.0, 1.0), ys=(-20.0, 8.0, 28.0), backgrounds=(1,))
    out = tmp_path / "behind"
    assert main(["grid", str(config), "--out", str(out), "--quiet", "--no-report"]) == 0
    frame = read_frame(out).set_index("y")
    assert frame.loc[-20.0, "status"] == "invalid"
    assert "outside the sensor's view" in frame.loc[-20.0, "reason"]
    assert pd.isna(frame.loc[-20.0, "car_iou"])
    assert frame.loc[8.0, "status"] == "ok"
    capsys.readouterr()
    config = small_config(tmp_path, xs=(0.0, 0.0, 1.0), ys=(-20.0, -20.0, 1.0), backgrounds=(1,))
    assert main(["grid", str(config), "--out", str(tmp_path / "none"), "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "1 invalid" in out and "lowest car IoU: - (no valid sample)\n" in out
    assert "mean car IoU: -\n" in out


def test_two_workers_give_the_same_rows_as_one(tmp_path):
    config = small_config(tmp_path, xs=(-4.0, 4.0, 4.0), ys=(6.0, 18.0, 6.0))
    one, two = tmp_path / "one", tmp_path / "two"
    assert main(["grid", str(config), "--out", str(one), "--quiet", "--no-report"]) == 0
    assert main(["grid", str(config), "--out", str(two), "--quiet", "--no-report",
                 "--workers", "2"]) == 0
    pd.testing.assert_frame_equal(rows(one), rows(two), check_exact=False, atol=1e-6)


def test_grid_report_and_gate_run_without_torch(tmp_path):
    """CI users should not pay for torch: scoring, reporting and gating never import it."""
    run = tmp_path / "run"
    code = (NO_TORCH + "from falsify.cli import main\n"
            f"assert main(['grid', {str(CONFIGS / 'smoke.toml')!r}, '--out', {str(run)!r},"
            " '--quiet']) == 0\n"
            f"code = main(['gate', {str(run)!r}, '--max-blind-spots', '4'])\n"
            "assert 'torch' not in sys.modules\n"
            "sys.exit(code)\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert (run / "report.html").exists()


@pytest.mark.parametrize("fidelity", ["fastest", "fast", "balanced"])
def test_fidelity_presets_run_their_model_variant(tmp_path, capsys, fidelity):
    out = tmp_path / fidelity
    assert main(["grid", str(CONFIGS / "smoke.toml"), "--out", str(out), "--quiet",
                 "--no-report", "--fidelity", fidelity, "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["samples"] == 8
    from falsify.results.store import read_meta
    meta = read_meta(out)
    assert meta["fidelity"] == fidelity and "int8" in meta["model_path"]
    assert meta["lod"] == 2   # recorded: the report replays with it whatever presets become
    assert main(["grid", str(CONFIGS / "smoke.toml"), "--out", str(tmp_path / "t"),
                 "--fidelity", fidelity, "--backend", "torch"]) == 2


def search(config: Path, out: Path, algorithm: str, workers: int, budget: int = 15, **kw):
    return execute(RunRequest(config=config, out=out, command="search", algorithm=algorithm,
                              budget=budget, seed=4, workers=workers, report=False), **kw)


def exported(run: Path) -> dict[str, str]:
    """Every file a run wrote, timings dropped from the results table and the summary."""
    out = {}
    for f in sorted(run.rglob("*")):
        if f.is_dir() or f.name.startswith("results.sqlite"):
            continue
        name = str(f.relative_to(run))
        if name == "results.csv":
            out[name] = pd.read_csv(f).drop(columns=list(TIMING_COLUMNS)).to_csv()
        elif name == "summary.json":
            summary = json.loads(f.read_text())
            for key in ("run", "elapsed_s"):
                summary.pop(key)
            out[name] = json.dumps(summary)
        elif f.suffix != ".parquet":   # the same table as results.csv, timings included
            out[name] = f.read_bytes().hex()
    return out


@pytest.mark.parametrize("algorithm", ["GN_CRS2_LM", "LN_BOBYQA"])
def test_concurrent_search_gives_the_rows_curve_and_files_of_one_worker(tmp_path, algorithm):
    """Two workers run two backgrounds' NLopt runs at once: the rows, the curve and the exported
    files are those of the sequential loop on one worker."""
    config = small_config(tmp_path, xs=(-4.0, 4.0, 1.0), ys=(6.0, 18.0, 1.0),
                          backgrounds=(0, 1, 2))
    one, two = tmp_path / "one", tmp_path / "two"
    a = search(config, one, algorithm, workers=1)
    b = search(config, two, algorithm, workers=2)
    assert a.search == b.search and a.search.evaluations == 15
    pd.testing.assert_frame_equal(rows(one), rows(two), check_exact=False, atol=1e-6)
    assert read_meta(one)["curve"] == read_meta(two)["curve"] == list(a.search.curve)
    assert list(read_frame(one)["sample_key"]) == list(dict.fromkeys(
        read_frame(one)["sample_key"]))
    files_one, files_two = exported(one), exported(two)
    assert "results.csv" in files_one and files_one == files_two


@pytest.mark.slow
def test_interrupted_concurrent_search_resumes_to_the_same_rows(tmp_path):
    """An interrupt raised in one combination's thread stops the run; --resume computes only
    what is missing and ends with the rows of an uninterrupted run."""
    config = small_config(tmp_path, xs=(-4.0, 4.0, 1.0), ys=(6.0, 18.0, 1.0),
                          backgrounds=(0, 1, 2))
    full, cut = tmp_path / "full", tmp_path / "cut"
    whole = search(config, full, "GN_CRS2_LM", workers=2)

    def interrupt(progress, final):
        if progress.computed >= 5:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        search(config, cut, "GN_CRS2_LM", workers=2, on_progress=interrupt)
    partial = len(read_frame(cut))
    assert 5 <= partial < len(read_frame(full))
    again = execute(RunRequest(config=config, out=cut, command="search", algorithm="GN_CRS2_LM",
                               budget=15, seed=4, workers=2, report=False, resume=True))
    assert again.computed_this_time == len(read_frame(full)) - partial
    assert again.search == whole.search
    pd.testing.assert_frame_equal(rows(full), rows(cut), check_exact=False, atol=1e-6)


@pytest.mark.slow
def test_killed_concurrent_search_resumes_to_the_rows_of_one_worker(tmp_path):
    """kill -9 in the middle of a two-worker NLopt search (rows arriving from two combinations
    at once), then --resume: nothing recomputed or duplicated, the rows of one worker's run."""
    config = small_config(tmp_path, xs=(-4.0, 4.0, 1.0), ys=(6.0, 18.0, 1.0),
                          backgrounds=(0, 1, 2))
    full, killed = tmp_path / "full", tmp_path / "killed"
    whole = search(config, full, "GN_CRS2_LM", workers=1, budget=36)
    cmd = [sys.executable, "-m", "falsify", "search", str(config), "--algorithm",
           "GN_CRS2_LM", "--budget", "36", "--seed", "4", "--workers", "2", "--out",
           str(killed), "--quiet", "--no-report"]
    n = kill_after_rows(cmd, killed / "results.sqlite", 8)
    total = len(read_frame(full))
    assert 8 <= n < total, "the run must be killed in the middle"
    partial = len(read_frame(killed))
    r = subprocess.run(cmd + ["--resume", "--json"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["computed_this_time"] == total - partial
    assert read_meta(killed)["curve"] == list(whole.search.curve)
    pd.testing.assert_frame_equal(rows(full), rows(killed), check_exact=False, atol=1e-6)


def test_evaluator_builds_the_streets_it_is_told_to_warm():
    """EvalSettings.warm_backgrounds: each worker casts those streets when it starts (benchmarks
    time the steady state), and scores exactly as a cold worker does."""
    space = load_space(CONFIGS / "smoke.toml")
    samples = space.grid()
    streets = tuple(sorted({s.background for s in samples}))
    warm = Evaluator(EvalSettings(space=space, warm_backgrounds=streets))
    assert {bg for bg, _ in warm.sim._hits} == set(streets)
    cold = Evaluator(EvalSettings(space=space))
    assert not cold.sim._hits
    assert ([r.metrics for r in warm.score_batch(samples)]
            == [r.metrics for r in cold.score_batch(samples)])
