"""`falsify gate` as CI runs it: JUnit XML that JUnit readers parse whatever the names in it, with
failures exactly when the gate fails; outputs that never replace the gate's inputs; hand-edited
baselines refused where they would match no cell; the README's baseline workflow."""

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
from tests.jobs.test_gate import BLIND, iou_of
from tests.runfixture import ROOT, write_run

# smoke.toml's cells: x in {-2, 2}, y in {8, 14}; BLIND (-2, 8) is the blind spot below.
OTHER_BLIND = (2.0, 8.0)


def cli() -> list[str]:
    exe = shutil.which("falsify")
    return [exe] if exe else [sys.executable, "-m", "falsify"]


def env() -> dict[str, str]:
    return {**os.environ, "PYTHONPATH": str(ROOT)}


def read_junit(path: Path) -> ET.Element:
    """The suite as expat (XML 1.0, strict) reads it, its counts as junitparser reads them."""
    from junitparser import JUnitXml
    suite = ET.parse(path).getroot()
    parsed = JUnitXml.fromfile(str(path))
    assert (parsed.tests, parsed.failures, parsed.errors, parsed.skipped) == tuple(
        int(suite.get(k)) for k in ("tests", "failures", "errors", "skipped"))
    return suite


def counts(suite: ET.Element) -> dict[str, int]:
    """The suite's stated counts beside those of its testcases."""
    cases = suite.findall("testcase")
    return {"tests": int(suite.get("tests")), "cases": len(cases),
            "failures": int(suite.get("failures")),
            "failure_cases": sum(c.find("failure") is not None for c in cases),
            "skipped": int(suite.get("skipped")),
            "skipped_cases": sum(c.find("skipped") is not None for c in cases)}


@pytest.mark.parametrize("name", [
    "a&b<c>\"d'e",        # XML's special characters: escaped
    "ctl\x01\x1bx",       # control characters: XML 1.0 holds them in no form
    os.fsdecode(b"raw\xff\xfe"),   # a folder name that is not UTF-8 (argv's surrogates)
    "L" * 240], ids=["xml_specials", "controls", "not_utf8", "long"])
def test_junit_parses_whatever_the_run_and_baseline_are_called(name: str, tmp_path: Path,
                                                               capsys) -> None:
    """Before: a run or baseline named with \\x01 or \\xff wrote a JUnit file that expat, lxml
    and junitparser refuse ("not well-formed", "invalid bytes"), so CI lost the report; after:
    those characters are written as \\x01, \\xff, as the terminal shows them."""
    iou = iou_of({BLIND: 0.5, (2.0, 14.0): None})
    run = tmp_path / name
    os.rename(write_run(tmp_path / "plain", iou=iou), run)
    base = tmp_path / f"{name[:40]}.json"
    assert main(["gate", str(run), "--json"]) == 1
    base.write_text(capsys.readouterr().out)
    junit = tmp_path / "junit.xml"
    for extra in ([], ["--baseline", str(base)]):
        main(["gate", str(run), *extra, "--junit", str(junit)])
        capsys.readouterr()
        raw = junit.read_bytes()
        raw.decode("utf-8")   # the declared encoding
        suite = read_junit(junit)
        props = {p.get("name"): p.get("value") for p in suite.iter("property")}
        shown = name.encode("utf-8", "surrogateescape").decode("utf-8", "backslashreplace")
        shown = shown.replace("\x01", "\\x01").replace("\x1b", "\\x1b")
        assert props["run"] == str(tmp_path / shown)
        if extra:
            assert props["baseline"].endswith(f"{shown[:40]}.json")
        c = counts(suite)
        assert (c["tests"], c["failures"], c["skipped"]) == (
            c["cases"], c["failure_cases"], c["skipped_cases"]) == (4, 0 if extra else 1,
                                                                    2 if extra else 1)


def gate_junit(args: list[str], junit: Path, capsys) -> tuple[int, ET.Element]:
    code = main(["gate", *args, "--junit", str(junit)])
    capsys.readouterr()
    return code, read_junit(junit)


@pytest.mark.parametrize("case", ["over_limit", "within_limit", "known", "new"])
def test_junit_fails_exactly_when_the_gate_does(case: str, tmp_path: Path, capsys) -> None:
    """Before: every blind spot was a <failure>, so a gate that passed (known blind spots
    against --baseline, or within --max-blind-spots) still turned Jenkins UNSTABLE and a
    test-report check red; after: those are <skipped> with the reason, and the suite's failures
    are the cells that fail the gate. The stated counts are always the testcases'."""
    run = write_run(tmp_path / "run", iou=iou_of({BLIND: 0.5, OTHER_BLIND: 0.55}))
    base_run = write_run(tmp_path / "base", iou=iou_of(
        {BLIND: 0.5, OTHER_BLIND: 0.55} if case == "known" else {BLIND: 0.5}))
    args = {"over_limit": ["--max-blind-spots", "1"], "within_limit": ["--max-blind-spots", "2"],
            "known": ["--baseline", str(base_run)], "new": ["--baseline", str(base_run)]}[case]
    code, suite = gate_junit([str(run), *args], tmp_path / "j.xml", capsys)
    c = counts(suite)
    assert (c["tests"], c["failures"], c["skipped"]) == (
        c["cases"], c["failure_cases"], c["skipped_cases"])
    failing = {k.get("name") for k in suite.findall("testcase") if k.find("failure") is not None}
    skipped = {k.get("name"): k.find("skipped") for k in suite.findall("testcase")
               if k.find("skipped") is not None}
    expected = {"over_limit": (1, {"cell x=-2 y=8", "cell x=2 y=8"}),
                "within_limit": (0, set()), "known": (0, set()),
                "new": (1, {"cell x=2 y=8"})}[case]
    assert (code, failing) == expected
    assert c["failures"] > 0 if code else c["failures"] == 0
    assert set(skipped) == {"cell x=-2 y=8", "cell x=2 y=8"} - failing
    for element in skipped.values():
        why = "in the baseline" if case in ("known", "new") else "within --max-blind-spots 2"
        assert why in element.get("message") and "below the threshold" in element.text


def test_close_to_the_threshold_is_told_apart(tmp_path: Path, capsys) -> None:
    """Before: a cell at mIoU 0.6497 under 0.65 read "mIoU 0.650 < 0.650", "0.000 below";
    after: with the decimals that tell them apart."""
    run = write_run(tmp_path / "run", iou=iou_of({BLIND: 0.6497}))
    code, suite = gate_junit([str(run)], tmp_path / "j.xml", capsys)
    message = next(f.get("message") for f in suite.iter("failure"))
    mine, theirs = message.removeprefix("mIoU ").split(" < ")
    assert code == 1 and mine != theirs and float(mine) < float(theirs) == 0.65
    assert main(["gate", str(run)]) == 1
    out = capsys.readouterr().out
    assert "0.650," not in out and " 0.000 below" not in out


@pytest.mark.parametrize("target", ["store", "store_as_run", "baseline_json", "baseline_store"])
def test_junit_never_replaces_what_the_gate_reads(target: str, tmp_path: Path, capsys) -> None:
    """Before: `--junit RUN/results.sqlite` (or the baseline file) was replaced by the XML: the
    run unreadable ("file is not a database") or the baseline lost, exit 0; after: exit 2 naming
    it, every file as it was."""
    run = write_run(tmp_path / "run", iou=iou_of({BLIND: 0.5}))
    base_run = write_run(tmp_path / "base", iou=iou_of({BLIND: 0.5}))
    base_json = tmp_path / "base.json"
    assert main(["gate", str(run), "--json"]) == 1
    base_json.write_text(capsys.readouterr().out)
    run_arg, baseline, junit = {
        "store": (run, None, run / "results.sqlite"),
        "store_as_run": (run / "results.sqlite", None, run / "results.sqlite"),
        "baseline_json": (run, base_json, base_json),
        "baseline_store": (run, base_run, base_run / "results.sqlite")}[target]
    before = junit.read_bytes()
    extra = [] if baseline is None else ["--baseline", str(baseline)]
    assert main(["gate", str(run_arg), *extra, "--junit", str(junit)]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"falsify: error: --junit {junit}: would replace ")
    assert "baseline" in err.split("which")[0] if baseline else "run's store" in err
    assert junit.read_bytes() == before
    assert main(["gate", str(run), *extra]) in (0, 1)   # still readable


def test_junit_or_baseline_onto_the_redirected_output(tmp_path: Path) -> None:
    """Before: `gate RUN --json --junit out.json > out.json` left out.json holding the XML (the
    JSON went to the replaced file), exit 1; `gate RUN --baseline b.json --json > b.json` said
    only "Expecting value: line 1 column 1". After: exit 2, each naming the redirection."""
    run = write_run(tmp_path / "run", iou=iou_of({BLIND: 0.5}))
    out = tmp_path / "out.json"
    with out.open("w") as fh:
        proc = subprocess.run([*cli(), "gate", str(run), "--json", "--junit", str(out)],
                              stdout=fh, stderr=subprocess.PIPE, text=True, env=env(),
                              timeout=120)
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.startswith(f"falsify: error: --junit {out}: is also where this "
                                  "command's standard output goes")
    assert out.read_text() == ""
    with out.open("w") as fh:
        proc = subprocess.run([*cli(), "gate", str(run), "--baseline", str(out), "--json"],
                              stdout=fh, stderr=subprocess.PIPE, text=True, env=env(),
                              timeout=120)
    assert proc.returncode == 2 and f"--baseline {out}: is also where" in proc.stderr
    assert "write the new baseline to another file" in proc.stderr


@pytest.mark.parametrize("text", [
    '{"blind_spots": [], "threshold": NaN}',
    '{"blind_spots": [], "threshold": "0.65"}',
    '{"blind_spots": [{"x": true, "y": 8}]}',
    '{"blind_spots": [{"x": NaN, "y": 8}]}',
    '{"blind_spots": [{"x": -2, "y": Infinity}]}',
    '{"blind_spots": [{"x": 1' + "0" * 400 + ', "y": 8}]}',
    '{"blind_spots": [], "cells": [{"x": 1' + "0" * 400 + ', "y": 8}]}',
    '{"blind_spots": [], "limit": 1' + "0" * 5000 + "}"],
    ids=["nan_threshold", "text_threshold", "true_x", "nan_x", "infinite_y", "400_digit_x",
         "400_digit_cell", "5000_digits"])
def test_a_baseline_value_that_matches_no_cell_is_refused(text: str, tmp_path: Path,
                                                          capsys) -> None:
    """Before: a NaN or text threshold skipped the threshold check, NaN/true/Infinity cells
    matched none and passed, and a 400-digit number was a traceback (OverflowError, or
    ValueError past 4,300 digits); after: exit 2 naming the file."""
    run = write_run(tmp_path / "run", iou=iou_of({BLIND: 0.5}))
    base = tmp_path / "base.json"
    base.write_text(text)
    junit = tmp_path / "j.xml"
    assert main(["gate", str(run), "--baseline", str(base), "--junit", str(junit)]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"falsify: error: --baseline {base}: ") and len(err.splitlines()) == 1
    assert not junit.exists()


def test_the_readme_baseline_workflow(tmp_path: Path) -> None:
    """The README's CI section as a shell runs it in a fresh folder: the baseline of a run with
    blind spots (exit 1, the file written all the same), then a later run against it: exit 0,
    JUnit without failure; a new blind spot: exit 1, one failure."""
    write_run(tmp_path / "run", iou=iou_of({BLIND: 0.5}))
    write_run(tmp_path / "run2", iou=iou_of({BLIND: 0.45}))
    write_run(tmp_path / "run3", iou=iou_of({BLIND: 0.5, OTHER_BLIND: 0.6}))
    (tmp_path / "ci").mkdir()

    def sh(line: str) -> int:
        return subprocess.run(["bash", "-c", line], cwd=tmp_path, env=env(), timeout=120,
                              capture_output=True).returncode

    falsify = " ".join(cli())
    assert sh(f"{falsify} gate run --json > ci/blind-spots.json") == 1
    assert json.loads((tmp_path / "ci" / "blind-spots.json").read_text())["exit_code"] == 1
    assert sh(f"{falsify} gate run2 --baseline ci/blind-spots.json --junit junit.xml") == 0
    suite = read_junit(tmp_path / "junit.xml")
    assert (suite.get("failures"), suite.get("skipped")) == ("0", "1")
    assert sh(f"{falsify} gate run3 --baseline ci/blind-spots.json --junit junit.xml") == 1
    suite = read_junit(tmp_path / "junit.xml")
    assert [c.get("name") for c in suite.findall("testcase") if c.find("failure") is not None] \
        == ["cell x=2 y=8"]
