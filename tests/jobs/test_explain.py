"""`falsify explain`: rules, sensitivity and clusters recover what was built into a table, and
the command reads a real run, text and JSON, without writing to it."""

from __future__ import annotations

import itertools
import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from falsify.cli import main
from falsify.results.explain import Condition, explain, sensitivity
from falsify.results.metrics import Status
from falsify.world.space import parse_space

ROOT = Path(__file__).resolve().parents[2]
PAPER_DIMS = {"car_model": {"values": ["sedan"]}, "x": {"min": -5, "max": 4, "step": 1},
              "y": {"min": 5, "max": 19, "step": 1}, "background": {"values": [0, 1, 2, 3, 4, 5]}}


def paper_space():
    return parse_space({"seed": 0, "dims": PAPER_DIMS})


def table(iou_of) -> pd.DataFrame:
    """A full grid over PAPER_DIMS with the IoU `iou_of(x, y, background)`."""
    rows = [{"x": float(x), "y": float(y), "background": b, "status": Status.OK,
             "car_iou": iou_of(x, y, b)}
            for x, y, b in itertools.product(range(-5, 5), range(5, 20), range(6))]
    return pd.DataFrame(rows)


def test_recovers_a_far_corner_rule_and_a_blind_street():
    """Far cells at the border fail everywhere, and street 5 fails at every position: the two
    rules come out as built, with exact support and precision."""
    def iou(x, y, b):
        return 0.5 if (y >= 16 and abs(x) >= 3) or b == 5 else 0.9

    e = explain(table(iou), paper_space(), threshold=0.65)
    texts = [r.text() for r in e.rules]
    assert "background == 5" in texts
    far = next(r for r in e.rules if r.text() != "background == 5")
    assert {c.text() for c in far.conditions} == {"y >= 16", "|x| >= 3"}
    assert far.precision == 1.0 and far.mean_iou == pytest.approx(0.5)
    assert e.rules[0].precision == 1.0 and len(e.rules) == 2
    street = next(r for r in e.rules if r.text() == "background == 5")
    assert (street.support, street.failing) == (150, 150)
    # Every failing sample is covered: 150 on street 5, 5 x-values x 4 y-values on the others.
    assert e.failing == 150 + 5 * 5 * 4 and far.failing + street.failing >= e.failing


def test_one_sided_and_categorical_rules():
    def iou(x, y, b):
        return 0.3 if x <= -4 else 0.8

    e = explain(table(iou), paper_space(), threshold=0.65)
    assert [r.text() for r in e.rules] == ["x <= -4"]


def test_no_rule_when_nothing_or_everything_fails():
    assert explain(table(lambda x, y, b: 0.9), paper_space(), 0.65).rules == ()
    assert explain(table(lambda x, y, b: 0.1), paper_space(), 0.65).rules == ()


def test_noise_does_not_hide_the_rule_and_results_are_deterministic():
    rng = np.random.default_rng(3)
    noise = {k: rng.normal(0, 0.05) for k in itertools.product(range(-5, 5), range(5, 20),
                                                                 range(6))}

    def iou(x, y, b):
        return (0.45 if y >= 15 else 0.85) + noise[(x, y, b)]

    a = explain(table(iou), paper_space(), 0.65)
    b = explain(table(iou), paper_space(), 0.65)
    assert a == b
    assert a.rules[0].text() == "y >= 15" and a.rules[0].precision > 0.95


def test_sensitivity_is_the_main_effect_share():
    """IoU = f(y) only: y explains all variance, x and background none (exact on a grid)."""
    frame = table(lambda x, y, b: 0.1 + 0.04 * y)
    s = sensitivity(frame, paper_space(), ["x", "y", "background"])
    assert s["y"] == pytest.approx(1.0) and s["x"] == pytest.approx(0.0, abs=1e-12)
    # Additive in x and y with equal variances: each explains half.
    frame = table(lambda x, y, b: (x + 5) / 9 + (y - 5) / 14)
    s = sensitivity(frame, paper_space(), ["x", "y"])
    vx, vy = np.var(np.arange(10) / 9), np.var(np.arange(15) / 14)
    assert s["x"] == pytest.approx(vx / (vx + vy)) and s["y"] == pytest.approx(vy / (vx + vy))


def test_clusters_find_two_separate_failing_regions():
    def iou(x, y, b):
        near_left = x <= -4 and y <= 6
        far_right = x >= 3 and y >= 18
        return 0.2 if near_left or far_right else 0.9

    e = explain(table(iou), paper_space(), 0.65, k=2)
    centres = sorted((c.centre["x"], c.centre["y"]) for c in e.clusters)
    assert centres[0][0] < -3 and centres[0][1] < 7 and centres[1][0] > 2 and centres[1][1] > 17


def test_condition_masks_and_text():
    col = pd.Series([-4.0, -1.0, 0.0, 3.0])
    assert Condition("x", "|x|>=", 3.0).mask(col).tolist() == [True, False, False, True]
    assert Condition("x", "|x|>=", 3.0).text() == "|x| >= 3"
    assert Condition("background", "==", 5).text() == "background == 5"


def test_cli_on_a_real_run(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(ROOT)
    run = tmp_path / "run"
    assert main(["grid", "configs/smoke.toml", "--out", str(run), "--threshold", "0.95",
                 "--quiet"]) == 0
    capsys.readouterr()
    before = (run / "results.sqlite").read_bytes()
    assert main(["explain", str(run), "--threshold", "0.95", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["samples"] > 0 and doc["threshold"] == 0.95 and doc["algorithm"] == "grid"
    assert set(doc["sensitivity"]) <= {"x", "y", "background"}
    for r in doc["rules"]:
        assert r["failing"] <= r["support"] and 0 < r["precision"] <= 1
    assert main(["explain", str(run), "--threshold", "0.95"]) == 0
    assert "samples with car IoU below 0.95" in capsys.readouterr().out
    assert (run / "results.sqlite").read_bytes() == before


@pytest.mark.parametrize("argv, names", [
    (["--depth", "9"], "--depth"), (["--rules", "0"], "--rules"),
    (["--threshold", "2"], "--threshold"), (["--clusters", "0"], "--clusters")])
def test_bad_options_exit_2_naming_them(tmp_path, capsys, argv, names):
    assert main(["explain", str(tmp_path / "nowhere"), *argv]) == 2
    assert names in capsys.readouterr().err


def test_a_missing_run_is_named(tmp_path, capsys):
    assert main(["explain", str(tmp_path / "nowhere")]) == 2
    assert "nowhere" in capsys.readouterr().err


def test_the_objective_column_is_explained_not_car_iou():
    # car IoU fails at the far cells; the objective (person IoU here) fails on street 5 only
    frame = table(lambda x, y, b: 0.3 if y >= 16 else 0.9)
    frame["person_iou"] = [0.2 if b == 5 else 0.95 for b in frame["background"]]
    e = explain(frame, paper_space(), threshold=0.65, score="person_iou")
    assert e.score == "person_iou" and e.failing == int((frame["background"] == 5).sum())
    assert e.rules[0].text() == "background == 5"
    assert explain(frame, paper_space(), threshold=0.65).rules[0].text() != "background == 5"
