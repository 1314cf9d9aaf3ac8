"""A run records what it was computed under (versions, CPU, backend, device, inference threads)
in each session of its metadata; a resume under other versions goes on, keeps both environments
and warns once naming what changed; thread counts known to give the same bytes do not warn, and
none of it enters the files two runs are compared by."""

from __future__ import annotations

import json
import platform
import shutil
import sqlite3
import subprocess
import sys
from pathlib import Path

import numpy as np
import onnxruntime
import pandas as pd
import pytest
import trimesh

import falsify
from falsify.cli import main
from falsify.cpu import cpu_name
from falsify.executors.environment import changes, session_changes
from falsify.executors.evaluator import EvalSettings
from falsify.executors.inference import server_threads
from falsify.jobs.run import RunRequest, execute, inference_threads
from falsify.results.store import (
    STORE_NAME,
    TIMING_COLUMNS,
    environment_changes_of,
    environments_of,
    open_run,
    read_frame,
    read_meta,
)
from falsify.world.space import load_space
from tests.cli.test_pipeline import kill_after_rows
from tests.executors.test_audit8_determinism import ONE_VAN

ROOT = Path(__file__).resolve().parents[2]
SMALL = ROOT / "tests" / "data" / "small-grid.toml"   # 24 samples on 2 streets
SMOKE = ROOT / "configs" / "smoke.toml"               # 8 samples


def _environments(run: Path) -> list[list[dict]]:
    return [s.get("environments") for s in read_meta(run)["sessions"]]


@pytest.fixture(scope="module")
def killed(tmp_path_factory) -> Path:
    """The small grid killed with -9 after 8 of its 24 rows, as a user's run would be."""
    run = tmp_path_factory.mktemp("killed") / "run"
    cmd = [sys.executable, "-m", "falsify", "grid", str(SMALL), "--out", str(run), "--quiet",
           "--no-report"]
    n = kill_after_rows(cmd, run / STORE_NAME, 8)
    assert 8 <= n < 24, "the run must be killed in the middle"
    return run


def _killed_run(killed: Path, tmp_path: Path) -> Path:
    """A copy of the killed run of its own, for a test to resume and edit."""
    return Path(shutil.copytree(killed, tmp_path / "run"))


def _edit_sessions(run: Path, edit) -> None:
    """Rewrite the stored sessions with `edit(sessions)`, as a run started under another
    falsify or other libraries would have stored them."""
    with sqlite3.connect(run / STORE_NAME) as db:
        sessions = json.loads(db.execute("SELECT value FROM run WHERE key = 'sessions'")
                              .fetchone()[0])
        db.execute("UPDATE run SET value = ? WHERE key = 'sessions'",
                   (json.dumps(edit(sessions)),))


def test_a_run_records_the_versions_cpu_and_threads_it_ran_on(tmp_path):
    run = tmp_path / "run"
    execute(RunRequest(config=SMOKE, out=run, command="grid", report=False))
    [[env]] = _environments(run)
    assert env["falsify"] == falsify.__version__ and env["python"] == platform.python_version()
    assert (env["numpy"], env["onnxruntime"], env["trimesh"], env["pandas"]) == (
        np.__version__, onnxruntime.__version__, trimesh.__version__, pd.__version__)
    assert env["embreex"] and env["embree"].count(".") == 2
    assert env["cpu"] == (cpu_name() or env["cpu"]) and env["cpu"]
    assert (env["backend"], env["device"]) == ("onnx", "cpu")
    # one worker's ONNX Runtime session runs on inference_threads' count, as the run set it
    assert env["inference_threads"] == inference_threads("onnx", "cpu", 1) == 2
    assert "torch" not in env and "ray" not in env
    assert environments_of(read_meta(run)) == [env] and not environment_changes_of(
        read_meta(run))


def test_an_onnx_run_neither_imports_nor_records_torch(tmp_path):
    """Scoring needs ONNX Runtime alone: recording the environment imports neither torch nor
    ray (their versions are read only where the run uses them)."""
    out = tmp_path / "run"
    code = ("import sys; from falsify.cli import main; "
            f"assert main(['grid', {str(SMOKE)!r}, '--out', {str(out)!r}, '--quiet', "
            "'--no-report', '--workers', '2']) == 0; "
            "print(sorted(m for m in ('torch', 'ray') if m in sys.modules))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0, r.stderr
    assert r.stdout.splitlines()[-1] == "[]"
    [[env]] = _environments(out)
    assert "torch" not in env and env["inference_threads"] == 1   # two workers: 1 thread each


def test_resume_under_another_onnxruntime_warns_once_and_keeps_both(killed, tmp_path,
                                                                     capsys):
    """Killed, then 'upgraded': the stored session says onnxruntime 1.22.0. --resume (on two
    workers, so one thread each against two before) goes on, warns once naming the version
    change and not the threads, and the run keeps both environments; the summary says so."""
    run = _killed_run(killed, tmp_path)

    def older(sessions):
        sessions[0]["environments"][0]["onnxruntime"] = "1.22.0"
        return sessions
    _edit_sessions(run, older)
    assert main(["grid", str(SMALL), "--out", str(run), "--resume", "--workers", "2",
                 "--quiet", "--no-report"]) == 0
    err = capsys.readouterr().err
    warnings = [line for line in err.splitlines() if "warning" in line]
    assert len(warnings) == 1, err
    assert f"onnxruntime 1.22.0 -> {onnxruntime.__version__}" in warnings[0]
    assert "threads" not in warnings[0] and "--resume" in warnings[0]
    first, second = _environments(run)
    assert first[0]["onnxruntime"] == "1.22.0" and first[0]["inference_threads"] == 2
    assert second[0]["onnxruntime"] == onnxruntime.__version__
    assert second[0]["inference_threads"] == 1
    change = [f"onnxruntime 1.22.0 -> {onnxruntime.__version__}"]
    assert read_meta(run)["sessions"][1]["changed"] == change
    assert open_run(run).environment_changes == change
    assert len(open_run(run).environments) == 2
    assert json.loads((run / "summary.json").read_text())["environment_changes"] == change
    assert len(read_frame(run)) == 24
    # Resumed again under the same libraries: nothing new changed, nothing to warn about.
    assert main(["grid", str(SMALL), "--out", str(run), "--resume", "--no-report"]) == 0
    captured = capsys.readouterr()
    assert "warning" not in captured.err
    assert "changed" not in read_meta(run)["sessions"][2]
    assert open_run(run).environment_changes == change   # the run still mixes both
    assert f"more than one environment ({change[0]})" in captured.out
    # the report's card says what the rows were computed under, and that they mix two
    assert main(["report", str(run)]) == 0
    page = (run / "report.html").read_text()
    card = page.split("<dt>Computed on</dt>")[1].split("</dd>")[0]
    assert f"onnxruntime {onnxruntime.__version__}" in card and "onnx on cpu" in card
    assert f"mix environments that may differ in their numbers: {change[0]}" in card.replace(
        "&gt;", ">")


def test_a_run_from_before_environments_were_recorded_resumes_and_reports(killed, tmp_path,
                                                                           capsys):
    """A run written by a falsify that kept no sessions (nor environments): it resumes without
    a warning (nothing is known to have changed), records this session's environment, and its
    report is written."""
    run = _killed_run(killed, tmp_path)
    with sqlite3.connect(run / STORE_NAME) as db:
        db.execute("DELETE FROM run WHERE key = 'sessions'")
    assert environments_of(read_meta(run)) == []
    assert main(["grid", str(SMALL), "--out", str(run), "--resume", "--quiet",
                 "--no-report"]) == 0
    assert "warning" not in capsys.readouterr().err
    sessions = read_meta(run)["sessions"]
    assert "environments" not in sessions[0] and len(sessions[1]["environments"]) == 1
    assert "environment_changes" not in json.loads((run / "summary.json").read_text())
    assert main(["report", str(run)]) == 0 and (run / "report.html").exists()


def test_runs_on_one_and_two_workers_differ_in_threads_only_in_their_environments(tmp_path):
    """--workers 1 runs ONNX Runtime on 2 threads, --workers 2 on 1 each: both give the same
    bytes, so the environments differ but the rows, tables and summary a comparison reads do
    not, and neither run counts as mixed."""
    runs = {w: tmp_path / f"w{w}" for w in (1, 2)}
    for w, out in runs.items():
        execute(RunRequest(config=SMOKE, out=out, command="grid", workers=w, report=False))
    envs = {w: _environments(out)[0][0] for w, out in runs.items()}
    assert (envs[1]["inference_threads"], envs[2]["inference_threads"]) == (2, 1)
    assert changes(envs[1], envs[2]) == []

    def files(run: Path) -> tuple[str, str, dict]:
        summary = json.loads((run / "summary.json").read_text())
        for key in ("run", "elapsed_s"):
            summary.pop(key)
        csv = pd.read_csv(run / "results.csv").drop(columns=list(TIMING_COLUMNS)).to_csv()
        return csv, (run / "maps" / "miou_x_y.csv").read_text(), summary
    assert files(runs[1]) == files(runs[2])
    assert "environment_changes" not in files(runs[1])[2]


ENV = {"falsify": "0.2.0", "python": "3.11.7", "numpy": "2.4.6", "onnxruntime": "1.22.0",
       "cpu": "AMD EPYC (family 25, model 17)", "backend": "onnx", "device": "cpu",
       "inference_threads": 2}


def test_what_counts_as_a_change_of_environment():
    """Versions, CPU, backend and device count; ray (it computes no number) does not; thread
    counts count only outside what is known to give the same bytes: ONNX Runtime's 1 to 4
    intra-op threads, torch held at 1 on the CPU; on a GPU threads compute nothing."""
    assert changes(ENV, ENV | {"onnxruntime": "1.23.0"}) == ["onnxruntime 1.22.0 -> 1.23.0"]
    assert changes(ENV, ENV | {"cpu": "Intel Xeon"}) == [
        "cpu AMD EPYC (family 25, model 17) -> Intel Xeon"]
    assert changes(ENV, ENV | {"device": "cuda"}) == ["device cpu -> cuda"]
    assert changes(ENV, ENV | {"ray": "2.60.0"}) == []
    assert changes(ENV, ENV | {"inference_threads": 4}) == []
    assert changes(ENV, ENV | {"inference_threads": 8}) == ["inference threads 2 -> 8"]
    torch = ENV | {"backend": "torch", "torch": "2.13.0", "inference_threads": 1,
                   "torch_threads": 1}
    assert changes(torch, torch | {"torch": "2.14.0"}) == ["torch 2.13.0 -> 2.14.0"]
    assert changes(torch, torch | {"inference_threads": 2, "torch_threads": 2}) == [
        "inference threads 1 (torch 1) -> 2 (torch 2)"]
    gpu = torch | {"device": "cuda", "gpu": "NVIDIA H200"}
    assert changes(gpu, gpu | {"inference_threads": 2, "torch_threads": 2}) == []
    assert changes(gpu, gpu | {"gpu": "NVIDIA A100"}) == ["gpu NVIDIA H200 -> NVIDIA A100"]
    # A session compares with the run's latest environments, or its own among themselves.
    newer = ENV | {"numpy": "2.5.0"}
    assert session_changes([ENV], [ENV]) == [] and session_changes([], [ENV]) == []
    assert session_changes([], [ENV, newer]) == ["numpy 2.4.6 -> 2.5.0"]
    assert session_changes([ENV], [newer, newer]) == ["numpy 2.4.6 -> 2.5.0"]


def test_shared_inference_runs_torch_on_the_cpu_on_one_thread():
    """torch and plug-ins on the CPU are held at one thread so that their rows do not depend on
    --workers (their kernels sum in another order on two); the shared inference process took
    one thread per worker for them too."""
    space = load_space(SMALL)
    for backend in ("torch", "python"):
        settings = EvalSettings(space=space, backend=backend,
                                threads=inference_threads(backend, "cpu", 2))
        assert server_threads(settings, 2) == server_threads(settings, 8) == 1
    onnx = EvalSettings(space=space, threads=inference_threads("onnx", "cpu", 2))
    assert server_threads(onnx, 2) == 2   # ONNX Runtime: 1 to 4 threads give the same logits


def test_torch_rows_of_shared_inference_equal_a_workers_and_record_torch(tmp_path):
    """The van whose pixel flipped between torch's 1 and 2 threads, scored in the shared
    inference process of two workers and in one worker: the same rows (the process ran torch
    on two threads: unknown_tp 29768 against 29767 on a 2-core EPYC), and both runs record
    torch's version and its one thread."""
    torch = pytest.importorskip("torch")
    config = tmp_path / "one.toml"
    config.write_text(ONE_VAN)
    rows, envs = [], []
    for workers, inference in ((1, "auto"), (2, "shared")):
        out = tmp_path / f"{inference}"
        execute(RunRequest(config=config, out=out, command="grid", backend="torch",
                           workers=workers, inference=inference, report=False))
        rows.append(read_frame(out).drop(columns=list(TIMING_COLUMNS)))
        envs.append(_environments(out)[0][0])
    pd.testing.assert_frame_equal(rows[0], rows[1])
    for env in envs:
        assert env["torch"] == torch.__version__ and env["backend"] == "torch"
        assert env["inference_threads"] == 1 and env["torch_threads"] == 1
    assert changes(envs[0], envs[1]) == []
