"""`falsify gate`: exit codes, JSON, baseline round trip, JUnit XML, and bad input (exit 2)."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

from falsify.cli import main
from falsify.world.space import Sample
from tests.runfixture import ROOT, write_run

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
    assert suite.tag == "testsuite" and suite.get("name") == "falsify.jobs.gate"
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
