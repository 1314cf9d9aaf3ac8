"""Audit of the reported numbers at their extremes: per-sample scores, mCE / mRR (Robo3D), the
agreement's distances, cell maps at the threshold, and the gate's baseline comparison."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from scipy.stats import wasserstein_distance

from falsify.cli import main
from falsify.errors import FalsifyError
from falsify.jobs.agreement import wasserstein1
from falsify.jobs.gate import judge
from falsify.jobs.robustness import robustness, robustness_text
from falsify.results.distances import wasserstein_hist
from falsify.results.metrics import Scoring, confusion
from falsify.results.miou_maps import miou_map
from falsify.world.space import load_space
from tests.jobs.test_robustness import CONFIG, MINE, REF, scores
from tests.runfixture import SMOKE, write_run


# -- per-sample scores ---------------------------------------------------------------------
def test_confusion_takes_uint64_predictions() -> None:
    """int64 + uint64 is float64 in numpy, which bincount refused (a traceback)."""
    pred = np.array([1, 2, 3], np.uint64)
    label = np.array([1, 1, 3], np.uint8)
    assert confusion(pred, label).tolist() == [[0, 0, 0], [1, 0, 1], [0, 1, 0], [1, 0, 0]]


def test_a_placed_class_absent_from_the_sample_leaves_its_inserted_iou_undefined() -> None:
    """A pedestrian-and-cyclist run's cyclist sample: inserted_pedestrian_iou is undefined, not
    0 because the network painted a pedestrian somewhere in the scan; the cyclist's is scored."""
    scoring = Scoring(objective="pedestrian", parts=True, placed=("cyclist", "pedestrian"))
    #              inserted cyclist | real pedestrian | background
    truth = np.array([3, 3, 3, 3, 2, 2, 0, 0, 0, 0])
    pred = np.array([3, 3, 3, 0, 2, 0, 2, 0, 0, 0])
    inserted = np.array([1, 1, 1, 1, 0, 0, 0, 0, 0, 0], bool)
    m, _ = scoring.score(pred, truth, inserted)
    assert m["inserted_pedestrian_iou"] is None and m["inserted_pedestrian_recall"] is None
    assert m["inserted_iou"] is None and m["inserted_recall"] is None
    assert m["inserted_cyclist_iou"] == pytest.approx(3 / 4)
    assert m["real_iou"] == pytest.approx(1 / 3)   # the scan's own pedestrians keep their fp
    assert m["pedestrian_iou"] == pytest.approx(1 / 3)


def test_four_class_miou_averages_only_the_classes_the_model_maps() -> None:
    """A car-only four-class model is judged on car: a pedestrian in the label is not a class
    it could predict, so it must not enter miou as IoU 0 (0.25 instead of 0.5)."""
    s = Scoring.of(["unknown", "car"], "miou")
    pred, truth = np.array([1, 1, 0]), np.array([1, 2, 0])
    metrics, note = s.score(pred, truth)
    assert metrics["car_iou"] == 0.5 and metrics["pedestrian_iou"] == 0.0   # still a column
    assert metrics["miou"] == 0.5 and note == ""
    metrics, note = s.score(np.array([0, 0, 0]), np.array([2, 2, 0]))
    assert metrics["miou"] is None and "the model predicts" in note
    # a model mapping all four still averages all three object classes
    full = Scoring.of(["unknown", "car", "pedestrian", "cyclist"], "miou")
    assert full.score(pred, truth)[0]["miou"] == 0.25


# -- robustness (Robo3D: Kong et al., ICCV 2023) -------------------------------------------
@pytest.fixture
def robust_runs(tmp_path: Path) -> tuple[Path, Path, Path]:
    """Mine with no valid sample at fog 50 m; the reference; a reference scoring 1 throughout."""
    mine = dict(MINE)
    mine[(50.0, 0)] = None
    one = dict.fromkeys(REF, 1.0)
    return (write_run(tmp_path / "mine", CONFIG, iou=scores(mine)),
            write_run(tmp_path / "ref", CONFIG, iou=scores(REF)),
            write_run(tmp_path / "one", CONFIG, iou=scores(one)))


def test_a_severity_without_a_valid_sample_leaves_rr_and_ce_undefined(robust_runs,
                                                                       capsys) -> None:
    """Dropping fog 50 m gave RR_fog = 0.6 / (1 * 0.8) = 0.75 and CE_fog over one level: L_e
    shrank unsaid. Robo3D sums over every severity, so RR_fog and CE_fog are undefined."""
    mine, ref, _ = robust_runs
    r = robustness(mine, ref, column="car_iou")
    fog, beams = r.effects
    assert [(lv.severity, lv.score, lv.samples) for lv in fog.levels][0] == (50.0, None, 0)
    assert fog.rr is None and fog.ce is None and "severity 50" in fog.note
    assert beams.rr == pytest.approx(0.5 / 0.8, rel=1e-2)
    assert beams.ce == pytest.approx(0.5 / 0.3, rel=1e-2)
    assert r.mrr is None and r.mce is None
    text = robustness_text(r)
    assert "no valid sample at severity 50" in text and "RR undefined for fog" in text
    assert main(["robustness", str(mine), "--reference", str(ref), "--column", "car_iou",
                 "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["mrr"] is None and doc["effects"][0]["levels"][0]["score"] is None


def test_a_reference_scoring_one_says_why_ce_is_undefined(robust_runs) -> None:
    """sum_l (1 - s_ref) = 0: CE is undefined; the text said "(no --reference)" though one
    was given."""
    _, ref, one = robust_runs
    r = robustness(ref, one, column="car_iou")
    assert r.mce is None and all(e.ce is None for e in r.effects)
    assert r.mrr == pytest.approx(0.7 / 0.9, rel=1e-2)      # RR stays defined
    text = robustness_text(r)
    assert "no --reference" not in text and "denominator is 0" in text
    assert "CE undefined for fog, beams" in text


def test_a_reference_without_a_valid_level_names_it(robust_runs) -> None:
    mine, ref, _ = robust_runs
    r = robustness(ref, mine, column="car_iou")
    fog = r.effects[0]
    assert fog.ce is None and fog.rr is not None
    assert "no valid reference sample at severity 50" in fog.note


def test_clean_rows_without_a_valid_score_are_named(tmp_path: Path) -> None:
    table = dict(MINE)
    table[(0.0, 0)] = None
    run = write_run(tmp_path / "noclean", CONFIG, iou=scores(table))
    with pytest.raises(FalsifyError, match="none of its 8 rows without effects has a valid"):
        robustness(run, column="car_iou")


# -- agreement's and the realism's distances ------------------------------------------------
def test_wasserstein1_matches_scipy_and_leaves_nans_out() -> None:
    rng = np.random.default_rng(0)
    for _ in range(200):
        n, m = rng.integers(1, 9, 2)
        u, v = rng.integers(0, 5, n) / 4, rng.random(m)   # ties in u
        assert wasserstein1(u, v) == pytest.approx(wasserstein_distance(u, v), abs=1e-12)
    assert wasserstein1([0.5], [0.2]) == pytest.approx(0.3)
    assert wasserstein1([np.nan, 0.5], [0.2]) == pytest.approx(0.3)    # was NaN
    assert wasserstein1([np.nan], [0.2]) is None and wasserstein1([], [0.2]) is None


def test_wasserstein_hist_on_unequal_bins() -> None:
    """Bins [0, 1), [1, 3), [3, 10): all mass in the first against all in the last is 6 apart
    (centre 0.5 to 6.5, and so for uniform mass in each bin); the bin widths gave 3."""
    edges = np.array([0.0, 1.0, 3.0, 10.0])
    assert wasserstein_hist(np.array([1.0, 0, 0]), np.array([0, 0, 1.0]), edges) == \
        pytest.approx(6.0)
    rng = np.random.default_rng(1)
    for bins in (np.linspace(0.0, 120.0, 61), np.sort(rng.random(30)) * 10):
        centres = (bins[1:] + bins[:-1]) / 2
        a, b = rng.integers(0, 5, len(centres)), rng.integers(0, 5, len(centres))
        want = wasserstein_distance(centres, centres, a, b)
        assert wasserstein_hist(a.astype(float), b.astype(float), bins) == pytest.approx(want)


# -- cell maps at the threshold --------------------------------------------------------------
def test_a_cell_exactly_at_the_threshold_is_not_blind() -> None:
    """IoUs 0.6 and 0.7 average 0.65 exactly, but 0.6499999999999999 in floats: a blind spot
    "0.000 below the threshold". Blind means strictly below."""
    space = load_space(SMOKE)
    frame = pd.DataFrame({"x": [-2.0, -2.0, 2.0], "y": [8.0, 8.0, 8.0],
                          "status": ["ok"] * 3, "car_iou": [0.6, 0.7, 0.64]})
    cmap = miou_map(frame, space)
    assert cmap.miou[0, 0] == 0.65
    assert [(c.a, c.b) for c in cmap.blind_spots(0.65)] == [(2.0, 8.0)]


# -- the gate's baseline -----------------------------------------------------------------
def _blind_at(x: float, y: float):
    return lambda s: 0.5 if (float(s["x"]), float(s["y"])) == (x, y) else 0.8


@pytest.fixture
def two_grids(tmp_path: Path) -> tuple[Path, Path]:
    """The smoke run (x -2, 2) and a run of another x grid (-4, 0, 4)."""
    smoke = SMOKE.read_text()
    other = smoke.replace("min = -2.0\nmax = 2.0\nstep = 4.0", "min = -4.0\nmax = 4.0\nstep = 4.0")
    assert other != smoke
    return (write_run(tmp_path / "run", smoke, iou=_blind_at(-2.0, 8.0)),
            write_run(tmp_path / "other", other, iou=_blind_at(4.0, 8.0)))


def test_a_baseline_of_another_grid_exits_2_naming_both(two_grids, tmp_path: Path,
                                                         capsys) -> None:
    """It was compared silently: every run cell the baseline lacks came out "new"."""
    run, other = two_grids
    assert main(["gate", str(run), "--baseline", str(other)]) == 2
    err = capsys.readouterr().err
    assert "--baseline" in err and "x [-4, 0, 4] × y [8, 14]" in err
    assert "x [-2, 2] × y [8, 14]" in err
    assert main(["gate", str(other), "--json"]) == 1
    base = tmp_path / "other.json"
    base.write_text(capsys.readouterr().out)
    assert main(["gate", str(run), "--baseline", str(base)]) == 2
    assert "x [-4, 0, 4]" in capsys.readouterr().err
    assert judge(run, baseline=run).passed           # the same grid still compares


def test_a_json_baseline_at_another_threshold_exits_2(two_grids, tmp_path: Path,
                                                       capsys) -> None:
    """A baseline gated at 0.9 holds every cell as blind: nothing here could be new."""
    run, _ = two_grids
    assert main(["gate", str(run), "--threshold", "0.9", "--json"]) == 1
    base = tmp_path / "base.json"
    base.write_text(capsys.readouterr().out)
    assert main(["gate", str(run), "--baseline", str(base)]) == 2
    err = capsys.readouterr().err
    assert "below mIoU 0.9" in err and "0.65" in err and "--threshold 0.9" in err
    assert main(["gate", str(run), "--baseline", str(base), "--threshold", "0.9"]) == 0
