"""`falsify gate`: exit codes, JSON, baseline round trip, JUnit XML, and bad input (exit 2)."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import xml.etree.ElementTree as ET
from dataclasses import replace
from pathlib import Path

import pytest

from falsify.cli import main
from falsify.jobs.run import RunRequest, execute
from falsify.results.store import read_meta, stored_samples
from falsify.world.space import Sample, load_space
from tests.runfixture import ROOT, SMOKE, write_run

# smoke.toml: x in {-2, 2}, y in {8, 14}, backgrounds {0, 1}: 4 cells of 2 samples each.
BLIND = (-2.0, 8.0)


def iou_of(cells: dict[tuple[float, float], float | None]):
    """IoU by cell, 0.8 elsewhere; None makes a cell's samples undefined."""
    def iou(s: Sample) -> float | None:
        return cells.get((float(s["x"]), float(s["y"])), 0.8)
    return iou


@pytest.fixture
def run(tmp_path: Path) -> Path:
    """One blind spot (-2, 8) at mIoU 0.5, one cell (2, 14) without valid samples."""
    return write_run(tmp_path / "run", iou=iou_of({BLIND: 0.5, (2.0, 14.0): None}))


def gate(args: list[str], capsys) -> tuple[int, str, str]:
    code = main(["gate", *args])
    out, err = capsys.readouterr()
    return code, out, err


def test_exit_codes(run: Path, capsys) -> None:
    code, out, _ = gate([str(run)], capsys)
    assert code == 1
    assert "FAIL" in out and "cell x=-2 y=8: mIoU 0.500, 0.150 below" in out
    assert gate([str(run), "--max-blind-spots", "1"], capsys)[0] == 0
    assert gate([str(run), "--threshold", "0.4"], capsys)[0] == 0
    code, out, _ = gate([str(run), "--threshold", "0.9", "--max-blind-spots", "1"], capsys)
    assert code == 1
    # worst first: (-2, 8) at 0.5 before the cells at 0.8
    lines = [ln for ln in out.splitlines() if ln.strip().startswith("cell ")]
    assert lines[0].strip().startswith("cell x=-2 y=8") and len(lines) == 3


def test_json(run: Path, capsys) -> None:
    code, out, _ = gate([str(run), "--json"], capsys)
    doc = json.loads(out)
    assert code == 1 == doc["exit_code"] and doc["passed"] is False
    assert doc["threshold"] == 0.65 and doc["limit"] == 0 and doc["run"] == str(run)
    assert len(doc["cells"]) == 4
    assert [(c["x"], c["y"]) for c in doc["blind_spots"]] == [BLIND]
    spot = doc["blind_spots"][0]
    assert spot["miou"] == pytest.approx(0.5, abs=1e-3) and spot["samples"] == 2
    assert spot["below"] == pytest.approx(0.15, abs=1e-3)
    empty = [c for c in doc["cells"] if c["miou"] is None]
    assert [(c["x"], c["y"], c["blind"]) for c in empty] == [(2.0, 14.0, False)]
    assert doc["new_blind_spots"] == []


def test_baseline_round_trip(run: Path, tmp_path: Path, capsys) -> None:
    code, out, _ = gate([str(run), "--json"], capsys)
    base = tmp_path / "baseline.json"
    base.write_text(out)
    assert gate([str(run), "--baseline", str(base)], capsys)[0] == 0
    assert gate([str(run), "--baseline", str(run)], capsys)[0] == 0

    worse = write_run(tmp_path / "worse", iou=iou_of({BLIND: 0.5, (2.0, 8.0): 0.55}))
    code, out, _ = gate([str(worse), "--baseline", str(base), "--json"], capsys)
    doc = json.loads(out)
    assert code == 1 == doc["exit_code"] and doc["limit"] is None
    assert [(c["x"], c["y"]) for c in doc["new_blind_spots"]] == [(2.0, 8.0)]
    assert len(doc["blind_spots"]) == 2
    code, out, _ = gate([str(worse), "--baseline", str(run)], capsys)
    assert code == 1 and "cell x=2 y=8" in out and "NEW" in out


def test_junit(run: Path, tmp_path: Path, capsys) -> None:
    junit = tmp_path / "ci" / "gate.xml"
    assert gate([str(run), "--junit", str(junit)], capsys)[0] == 1
    suite = ET.parse(junit).getroot()
    assert suite.tag == "testsuite" and suite.get("name") == "falsify gate: run"
    assert {c.get("classname") for c in suite.findall("testcase")} == {"falsify.gate.run"}
    cases = suite.findall("testcase")
    assert sorted(c.get("name") for c in cases) == sorted(
        ["cell x=-2 y=8", "cell x=2 y=8", "cell x=-2 y=14", "cell x=2 y=14"])
    failed = {c.get("name"): c.find("failure") for c in cases if c.find("failure") is not None}
    assert list(failed) == ["cell x=-2 y=8"]
    assert failed["cell x=-2 y=8"].get("message") == "mIoU 0.500 < 0.650"
    skipped = [c.get("name") for c in cases if c.find("skipped") is not None]
    assert skipped == ["cell x=2 y=14"]
    assert suite.get("tests") == "4" and suite.get("failures") == "1"
    assert suite.get("skipped") == "1"
    assert not [p for p in junit.parent.iterdir() if p.name.endswith(".tmp")]


@pytest.mark.parametrize("case", ["missing", "not_a_run", "corrupt", "no_valid", "threshold_zero",
                                  "threshold_big", "threshold_nan", "negative_n",
                                  "baseline_missing", "baseline_garbage", "baseline_shape"])
def test_bad_input_exits_2(case: str, run: Path, tmp_path: Path, capsys) -> None:
    junit = tmp_path / "out.xml"
    target, extra, named = str(run), [], ""
    if case == "missing":
        target = named = str(tmp_path / "nope")
    elif case == "not_a_run":
        (tmp_path / "empty").mkdir()
        target = named = str(tmp_path / "empty")
    elif case == "corrupt":
        bad = tmp_path / "corrupt"
        bad.mkdir()
        (bad / "results.sqlite").write_bytes(b"this is not sqlite" * 100)
        target, named = str(bad), str(bad / "results.sqlite")
    elif case == "no_valid":
        target = str(write_run(tmp_path / "undefined", iou=lambda s: None))
        named = str(Path(target) / "results.sqlite")
    elif case.startswith("threshold"):
        value = {"threshold_zero": "0", "threshold_big": "1.5", "threshold_nan": "nan"}[case]
        extra, named = ["--threshold", value], "--threshold"
    elif case == "negative_n":
        extra, named = ["--max-blind-spots", "-1"], "--max-blind-spots"
    else:
        base = tmp_path / "base.json"
        if case == "baseline_garbage":
            base.write_text("{not json")
        elif case == "baseline_shape":
            base.write_text(json.dumps({"cells": []}))
        extra, named = ["--baseline", str(base)], str(base)
    code, out, err = gate([target, *extra, "--junit", str(junit)], capsys)
    assert code == 2, (out, err)
    assert named in err and err.startswith("falsify: error:")
    assert not junit.exists()


def test_usage_errors_exit_2(run: Path, tmp_path: Path, capsys) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["gate", str(run), "--max-blind-spots", "1", "--baseline", str(run)])
    assert exc.value.code == 2
    assert "not allowed with" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exc:
        main(["gate", str(run), "--max-blind-spots", "many"])
    assert exc.value.code == 2


def test_console_script(run: Path) -> None:
    exe = shutil.which("falsify")
    cmd = [exe] if exe else [sys.executable, "-m", "falsify"]
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.run([*cmd, "gate", str(run), "--json"], capture_output=True, text=True,
                          env=env, timeout=60)
    assert proc.returncode == 1, proc.stderr
    assert json.loads(proc.stdout)["blind_spots"][0]["x"] == BLIND[0]
    proc = subprocess.run([*cmd, "gate", str(run), "--threshold", "2"], capture_output=True,
                          text=True, env=env, timeout=60)
    assert proc.returncode == 2 and "--threshold" in proc.stderr


# -- completeness: a run stopped before its end, or still being written, is not gated -------------

# The grid's first five samples hold every sample of x = -2 and one of (2, 8): the blind cell
# (2, 14) is one a run stopped there never reached.
LATE_BLIND = (2.0, 14.0)


def stopped_run(folder: Path, stored: int = 5, **meta) -> Path:
    """A run of smoke.toml holding the first `stored` of its 8 grid samples, recorded as
    `falsify grid` records a run stopped before its end (`meta` overrides that)."""
    samples = load_space(SMOKE).grid()[:stored]
    return write_run(folder, samples=samples, iou=iou_of({LATE_BLIND: 0.5}),
                     meta={"planned": 8, "complete": False, **meta})


def test_a_stopped_run_is_refused_and_nothing_is_written(tmp_path: Path, capsys) -> None:
    run_dir = stopped_run(tmp_path / "stopped")
    junit = tmp_path / "ci" / "gate.xml"
    code, out, err = gate([str(run_dir), "--json", "--junit", str(junit)], capsys)
    assert code == 2 and out == ""
    assert err.startswith(f"falsify: error: {run_dir}: incomplete run")
    assert "5 of 8 planned samples" in err and "--allow-incomplete" in err
    assert f"falsify grid {SMOKE} --out {run_dir} --resume" in err
    assert not junit.parent.exists()
    # the blind cell it never reached is one the whole run has
    whole = write_run(tmp_path / "whole", iou=iou_of({LATE_BLIND: 0.5}),
                      meta={"planned": 8, "complete": True})
    assert gate([str(whole)], capsys)[0] == 1


@pytest.mark.parametrize("command", [["explain", "RUN"], ["agreement", "RUN", "WHOLE"],
                                     ["agreement", "WHOLE", "RUN"], ["robustness", "RUN"]])
def test_commands_that_judge_a_run_refuse_a_stopped_one(tmp_path: Path, capsys, command) -> None:
    """explain, agreement and robustness read runs as gate does: a stopped one is named."""
    run_dir = stopped_run(tmp_path / "stopped")
    whole = write_run(tmp_path / "whole", meta={"planned": 8, "complete": True})
    args = [{"RUN": str(run_dir), "WHOLE": str(whole)}.get(a, a) for a in command]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert f"{run_dir}: incomplete run, stopped before its end: 5 of 8 planned samples" in err
    assert "--allow-incomplete" in err
    if command[0] != "robustness":   # a smoke run has no effect dims for robustness to read
        assert main([*args, "--allow-incomplete", "--json"]) == 0
        json.loads(capsys.readouterr().out)


def test_allow_incomplete_gates_what_the_run_holds_and_says_so(tmp_path: Path, capsys) -> None:
    run_dir = stopped_run(tmp_path / "stopped")
    code, out, _ = gate([str(run_dir), "--allow-incomplete"], capsys)
    assert code == 0 and out.startswith("falsify gate: PASS")
    assert "INCOMPLETE: 5 of 8 planned samples, stopped before its end" in out
    junit = tmp_path / "gate.xml"
    code, out, err = gate([str(run_dir), "--allow-incomplete", "--json", "--junit", str(junit)],
                          capsys)
    doc = json.loads(out)
    assert code == 0 == doc["exit_code"] and doc["passed"] is True
    assert (doc["samples"], doc["planned"], doc["complete"], doc["writer"]) == (5, 8, False, None)
    assert "INCOMPLETE" in err   # in the job's log, beside the JSON
    props = {p.get("name"): p.get("value") for p in ET.parse(junit).getroot().iter("property")}
    assert (props["samples"], props["planned"], props["complete"]) == ("5", "8", "False")


def test_a_complete_run_gates_as_before(run: Path, tmp_path: Path, capsys) -> None:
    before = gate([str(run), "--json"], capsys)
    for name, meta, stored in (("recorded", {"planned": 8, "complete": True}, 8),
                               # stopped after its last sample, before it recorded its end
                               ("all_rows", {"planned": 8, "complete": False}, 8)):
        done = write_run(tmp_path / name, iou=iou_of({BLIND: 0.5, (2.0, 14.0): None}),
                         samples=load_space(SMOKE).grid()[:stored], meta=meta)
        code, out, err = gate([str(done), "--json"], capsys)
        doc = json.loads(out)
        assert code == before[0] == 1 and err == ""
        assert (doc["samples"], doc["planned"], doc["complete"]) == (8, 8, True)
        assert doc["cells"] == json.loads(before[1])["cells"]
        text = gate([str(done)], capsys)[1]
        assert "INCOMPLETE" not in text and "unknown" not in text


def test_a_finished_search_with_fewer_rows_than_planned_is_complete(tmp_path: Path,
                                                                   capsys) -> None:
    """A level-set search stops once every cell is decided; other samplers may draw a sample
    twice or converge: fewer rows than planned, yet finished."""
    for algorithm in ("level-set", "random"):
        done = write_run(tmp_path / algorithm, command="search", iou=lambda s: 0.8,
                         samples=load_space(SMOKE).grid()[:5],
                         meta={"algorithm": algorithm, "planned": 8, "complete": True})
        code, out, _ = gate([str(done), "--json"], capsys)
        doc = json.loads(out)
        assert code == 0 and (doc["samples"], doc["planned"], doc["complete"]) == (5, 8, True)
    killed = write_run(tmp_path / "killed", command="search", iou=lambda s: 0.8,
                       samples=load_space(SMOKE).grid()[:5],
                       meta={"algorithm": "random", "budget": 8, "planned": 8, "complete": False})
    code, _, err = gate([str(killed)], capsys)
    assert code == 2 and "5 of 8 planned samples" in err
    assert f"falsify search {SMOKE} --out {killed} --algorithm random --budget 8 --resume" in err


def test_a_run_without_the_record_still_gates(run: Path, tmp_path: Path, capsys) -> None:
    """Runs written before falsify recorded `planned` and `complete`: judged as they were, their
    completeness told where the run shows it and 'unknown' where it does not."""
    code, out, _ = gate([str(run), "--json"], capsys)   # every grid sample: complete
    doc = json.loads(out)
    assert code == 1 and (doc["samples"], doc["planned"], doc["complete"]) == (8, 8, True)
    ended = write_run(tmp_path / "ended", command="search", meta={"computed_last": 40})
    doc = json.loads(gate([str(ended), "--json"], capsys)[1])
    assert (doc["samples"], doc["planned"], doc["complete"]) == (40, None, True)
    old = write_run(tmp_path / "old", samples=load_space(SMOKE).grid()[:5],
                    iou=iou_of({LATE_BLIND: 0.5}))
    code, out, _ = gate([str(old)], capsys)
    assert code == 0 and "completeness unknown: 5 of 8 planned samples stored" in out
    code, out, err = gate([str(old), "--json"], capsys)
    doc = json.loads(out)
    assert code == 0 and (doc["samples"], doc["planned"], doc["complete"]) == (5, 8, None)
    assert "completeness unknown" in err
    search = write_run(tmp_path / "search", command="search")
    doc = json.loads(gate([str(search), "--json"], capsys)[1])
    assert (doc["samples"], doc["planned"], doc["complete"]) == (40, None, None)


def test_a_run_being_written_is_refused(run: Path, tmp_path: Path, capsys) -> None:
    code = (f"from falsify.results.runlock import RunLock\n"
            f"with RunLock({str(run)!r}, command='falsify grid held'):\n"
            "    print('held', flush=True)\n    input()\n")
    holder = subprocess.Popen([sys.executable, "-c", code], stdin=subprocess.PIPE,
                              stdout=subprocess.PIPE, text=True)
    junit = tmp_path / "gate.xml"
    try:
        assert holder.stdout.readline() == "held\n"
        code, out, err = gate([str(run), "--junit", str(junit)], capsys)
        assert code == 2 and out == "" and not junit.exists()
        assert f"{run}: still being written by process {holder.pid} (falsify grid held)" in err
        assert "8 of 8 planned samples" in err and "--allow-incomplete" in err
        code, out, _ = gate([str(run), "--allow-incomplete", "--json"], capsys)
        doc = json.loads(out)
        assert code == 1 == doc["exit_code"] and doc["complete"] is False
        assert doc["writer"] == f"process {holder.pid} (falsify grid held)"
    finally:
        holder.communicate("\n", timeout=30)
    assert gate([str(run)], capsys)[0] == 1   # released: judged again
    assert (run / "results.sqlite").exists() and not (run / ".lock").exists()


def test_an_incomplete_baseline_run_is_refused(run: Path, tmp_path: Path, capsys) -> None:
    base = stopped_run(tmp_path / "base")
    code, out, err = gate([str(run), "--baseline", str(base)], capsys)
    assert code == 2 and out == ""
    assert f"--baseline {base}: incomplete run" in err and "5 of 8 planned samples" in err
    assert gate([str(run), "--baseline", str(base), "--allow-incomplete"], capsys)[0] == 1


@pytest.mark.skipif(not (ROOT / "models" / "weights" / "squeezeseg.onnx").exists(),
                    reason="bundled model not trained yet")
def test_a_grid_stopped_mid_way_is_refused_until_resumed(tmp_path: Path, capsys) -> None:
    """The run job records what it planned and when it ends: a grid stopped after its first
    batch (8 of 12 samples) is refused, and passes once --resume has finished it."""
    config = tmp_path / "twelve.toml"
    config.write_text(SMOKE.read_text().replace("values = [0, 1]", "values = [0, 1, 2]"))
    out = tmp_path / "run"

    def stop(progress, final: bool) -> None:
        if progress.done >= 8 and not final:
            raise KeyboardInterrupt   # as Ctrl-C stops it

    req = RunRequest(config=config, out=out, command="grid", report=False)
    with pytest.raises(KeyboardInterrupt):
        execute(req, stop)
    meta = read_meta(out)
    assert (meta["planned"], meta["complete"], stored_samples(out)) == (12, False, 8)
    code, _, err = gate([str(out), "--threshold", "0.01"], capsys)
    assert code == 2 and "8 of 12 planned samples" in err
    assert f"falsify grid {config} --out {out} --resume" in err
    execute(replace(req, resume=True))
    code, out_text, _ = gate([str(out), "--threshold", "0.01", "--json"], capsys)
    doc = json.loads(out_text)
    assert code == 0 and (doc["samples"], doc["planned"], doc["complete"]) == (12, 12, True)
