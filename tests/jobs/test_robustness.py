"""falsify robustness: per effect and severity the mean score, CE / mCE against a reference and
RR / mRR (Robo3D's definitions), checked on runs whose scores are known."""

from __future__ import annotations

import json

import pytest

from falsify.cli import main
from falsify.errors import FalsifyError
from falsify.jobs.robustness import robustness
from tests.runfixture import write_run

CONFIG = """name = "robust"
sensor = "kitti-hdl64e-front"
seed = 0
threshold = 0.65
[dims.car_model]
values = ["sedan"]
[dims.x]
values = [-2.0, 2.0]
[dims.y]
values = [8.0, 12.0]
[dims.background]
values = [0, 1]
[dims.fog]
values = [0.0, 100.0, 50.0]
[dims.beams]
values = [0, 32]
"""

# The network's score by effect: clean 0.8; fog 100 m 0.6, 50 m 0.4; 32 beams 0.5; both 0.1.
MINE = {(0.0, 0): 0.8, (100.0, 0): 0.6, (50.0, 0): 0.4, (0.0, 32): 0.5}
REF = {(0.0, 0): 0.9, (100.0, 0): 0.8, (50.0, 0): 0.6, (0.0, 32): 0.7}


def scores(table):
    def iou(s):
        return table.get((float(s.get("fog", 0.0)), int(s.get("beams", 0))), 0.1)
    return iou


@pytest.fixture
def runs(tmp_path):
    return (write_run(tmp_path / "mine", CONFIG, iou=scores(MINE)),
            write_run(tmp_path / "ref", CONFIG, iou=scores(REF)))


def test_levels_ce_and_rr_follow_the_definitions(runs):
    mine, ref = runs
    r = robustness(mine, ref, column="car_iou")
    assert r.clean == pytest.approx(0.8, abs=2e-3) and r.clean_samples == 8
    assert r.mixed_samples == 16       # fog and 32 beams at once: left out
    fog, beams = (e for e in r.effects)
    assert fog.effect == "fog" and [lv.severity for lv in fog.levels] == [50.0, 100.0]
    assert [lv.samples for lv in fog.levels] == [8, 8]
    # CE_fog = ((1-0.4) + (1-0.6)) / ((1-0.6) + (1-0.8)) = 1.0 / 0.6
    assert fog.ce == pytest.approx(1.0 / 0.6, rel=1e-2)
    # RR_fog = (0.4 + 0.6) / (2 * 0.8)
    assert fog.rr == pytest.approx(1.0 / 1.6, rel=1e-2)
    assert beams.ce == pytest.approx(0.5 / 0.3, rel=1e-2)
    assert beams.rr == pytest.approx(0.5 / 0.8, rel=1e-2)
    assert r.mce == pytest.approx((1.0 / 0.6 + 0.5 / 0.3) / 2, rel=1e-2)
    assert r.mrr == pytest.approx((1.0 / 1.6 + 0.5 / 0.8) / 2, rel=1e-2)


def test_a_network_against_itself_has_ce_one(runs):
    mine, _ = runs
    r = robustness(mine, mine, column="car_iou")
    assert all(e.ce == pytest.approx(1.0) for e in r.effects) and r.mce == pytest.approx(1.0)


def test_without_a_reference_there_is_no_ce(runs, capsys):
    mine, _ = runs
    assert main(["robustness", str(mine), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["mce"] is None and all(e["ce"] is None for e in doc["effects"])
    assert doc["mrr"] == pytest.approx(0.625, abs=5e-3)
    assert main(["robustness", str(mine)]) == 0
    assert "mCE - (no --reference)" in capsys.readouterr().out


def test_bad_input_is_named(tmp_path, runs, capsys):
    mine, _ = runs
    plain = write_run(tmp_path / "plain", CONFIG.split("[dims.fog]")[0])
    with pytest.raises(FalsifyError, match="no effect dim"):
        robustness(plain)
    other = write_run(tmp_path / "other", CONFIG.replace('"robust"', '"other"'))
    with pytest.raises(FalsifyError, match="not a run of the same space"):
        robustness(mine, other)
    no_clean = write_run(tmp_path / "noclean", CONFIG.replace("[0.0, 100.0, 50.0]", "[100.0]")
                         .replace("[0, 32]", "[32]"))
    with pytest.raises(FalsifyError, match="no row without effects"):
        robustness(no_clean)
    assert main(["robustness", str(mine), "--column", "nope"]) == 2
    assert "--column 'nope'" in capsys.readouterr().err
    assert main(["robustness", str(tmp_path / "missing")]) == 2


def one_effect(effect: str, values: str) -> str:
    """CONFIG with only `effect` among the effect dims (Robo3D's one effect a run)."""
    head = CONFIG.split("[dims.fog]")[0]
    return head + f"[dims.{effect}]\nvalues = [{values}]\n"


def test_several_runs_one_effect_each_give_the_same_levels(tmp_path, runs, capsys):
    fog, beams = (one_effect("fog", "0.0, 100.0, 50.0"), one_effect("beams", "0, 32"))
    mine = [write_run(tmp_path / f"mine-{n}", c, iou=scores(MINE))
            for n, c in (("fog", fog), ("beams", beams))]
    ref = [write_run(tmp_path / f"ref-{n}", c, iou=scores(REF))
           for n, c in (("fog", fog), ("beams", beams))]
    split = robustness(mine, ref, column="car_iou")
    product = robustness(runs[0], runs[1], column="car_iou")
    assert split.mixed_samples == 0 and split.clean_samples == 16   # both runs' clean rows
    assert split.clean == pytest.approx(product.clean)
    assert split.mce == pytest.approx(product.mce) and split.mrr == pytest.approx(product.mrr)
    assert main(["robustness", *map(str, mine), "--reference", *map(str, ref), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["mce"] == pytest.approx(product.mce, abs=1e-4)
    with pytest.raises(FalsifyError, match="give one reference run per run"):
        robustness(mine, ref[:1], column="car_iou")
    with pytest.raises(FalsifyError, match="effect fog is in"):
        robustness([mine[0], mine[0]], column="car_iou")
