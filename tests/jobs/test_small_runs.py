"""The commands that read a run, on the smallest runs: one valid sample, or none at all."""

from __future__ import annotations

import json
import tomllib
from pathlib import Path

import pytest

from falsify.cli import main
from falsify.world.space import parse_space
from tests.runfixture import SMOKE, write_run

FOG = SMOKE.read_text() + "\n[dims.fog]\nvalues = [0.0, 0.02]\n"


def one_valid(run: Path) -> Path:
    """A fog grid of 16 samples whose first (clean) sample alone is valid, failing."""
    first = parse_space(tomllib.loads(FOG), source="fog.toml").grid()[0]
    return write_run(run, FOG, iou=lambda s: 0.3 if s == first else None)


def all_invalid(run: Path) -> Path:
    return write_run(run, FOG, invalid_every=1)


@pytest.mark.parametrize("make, n", [(one_valid, 1), (all_invalid, 0)])
def test_explain_says_too_few_samples_not_that_no_rule_fits(tmp_path, capsys, make, n):
    run = make(tmp_path / "run")
    assert main(["explain", str(run)]) == 0
    out = capsys.readouterr().out
    assert f"too few valid samples to explain ({n}; a rule needs at least 3)" in out
    assert "no rule covers" not in out
    assert main(["explain", str(run), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["samples"] == n and doc["rules"] == [] and doc["clusters"] == []


@pytest.mark.parametrize("make", [one_valid, all_invalid])
def test_reading_commands_answer_or_name_the_problem(tmp_path, capsys, make):
    run, twin = make(tmp_path / "run"), make(tmp_path / "twin")
    for argv in (["agreement", str(run), str(twin), "--json"],
                 ["report", str(run), "--compare", str(twin), "--no-predict", "--json"]):
        if argv[0] == "agreement" and make is all_invalid:
            # nothing to compare: it printed dashes, exit 0 (exit 1, MISSED, under a limit)
            assert main(argv) == 2
            err = capsys.readouterr().err
            assert f"world run {run}: no valid sample to compare (every row is invalid)" in err
            continue
        assert main(argv) == 0, argv
        json.loads(capsys.readouterr().out)
    # robustness needs a valid clean row and each effect's rows: exit 2 with the reason, or the
    # effect's level reported without a valid sample
    code = main(["robustness", str(run), "--reference", str(twin), "--json"])
    out, err = capsys.readouterr()
    if code == 2:
        assert err.startswith("falsify: error: ") and str(run) in err and "Traceback" not in err
    else:
        assert code == 0
        effect = json.loads(out)["effects"][0]
        assert effect["rr"] is None and "no valid sample at severity 0.02" in effect["note"]
