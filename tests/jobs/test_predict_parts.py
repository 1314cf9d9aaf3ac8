"""`falsify predict` reads, predicts and writes a set a part at a time (PART scans), so a
SemanticKITTI sequence of thousands of scans fits in memory (whole, 1.7 MB a scan, 3.3 MB
scored per point: 7 and 14 GB for sequence 08's 4,071); the scores are the whole sets' to the
bit, and a bad scan or a stop part-way leaves none of the run's files."""

from __future__ import annotations

import json

import numpy as np
import pytest

import falsify.jobs.predict as predict_job
from falsify.cli import main
from falsify.data.scansets import plan_sets, read_sets
from falsify.data.training import held_out_scans
from falsify.jobs.predict import evaluate, evaluate_plans
from falsify.models.runners import load_segmenter
from falsify.sensor.lidar import load_sensor
from tests.conftest import MINI


@pytest.fixture(scope="module")
def npy_sets(tmp_path_factory):
    """Two folders of synthetic range images, 5 and 3 scans."""
    root = tmp_path_factory.mktemp("parts")
    scans = held_out_scans(load_sensor("kitti-hdl64e-front"), 8)
    for name, part in (("a", scans[:5]), ("b", scans[5:])):
        (root / name).mkdir()
        for k, image in enumerate(part):
            np.save(root / name / f"{k:06d}.npy", image)
    return [str(root / "a"), str(root / "b")]


def _whole_and_parts(model_name, paths, sensor, score="pixels", sequences=None):
    model = load_segmenter(model_name)
    plans = plan_sets(paths, sequences)
    whole = evaluate(model, read_sets(plans, sensor, score == "points"), score=score)
    seen = []
    parts = evaluate_plans(model, plans, sensor, score=score, part=2,
                           on_part=lambda k, scans, r: seen.append((k, len(scans),
                                                                    r.predictions.copy())))
    return whole, parts, seen


def test_sets_read_two_scans_at_a_time_score_as_whole_sets(npy_sets) -> None:
    whole, parts, seen = _whole_and_parts(None, npy_sets, load_sensor("kitti-hdl64e-front"))
    assert json.dumps(parts.to_json()) == json.dumps(whole.to_json())
    assert [(k, n) for k, n, _ in seen] == [(0, 2), (0, 2), (0, 1), (1, 2), (1, 1)]
    for k, s in enumerate(whole.sets):   # each part's predictions are the whole set's, in order
        got = np.concatenate([p for j, _, p in seen if j == k])
        assert np.array_equal(got, s.predictions)


@pytest.mark.skipif(not (MINI / "sequences" / "05").is_dir(), reason=f"no SemanticKITTI at {MINI}")
@pytest.mark.parametrize("score", ["pixels", "points"])
def test_semantickitti_per_class_scores_by_parts_are_the_whole_sets(score) -> None:
    """A 20-class network on fit sequences 01 and 05, per SemanticKITTI class, pixels and
    points: the parts' pooled and banded counts are the whole sets'."""
    whole, parts, _ = _whole_and_parts("squeezeseg20", [str(MINI)],
                                       load_sensor("kitti-hdl64e-front"), score, ["01", "05"])
    assert whole.to_json()["pooled"].keys() == parts.to_json()["pooled"].keys()
    assert len(whole.pooled.counts) == 20
    assert json.dumps(parts.to_json()) == json.dumps(whole.to_json())


def test_a_bad_scan_in_a_later_part_leaves_no_file(npy_sets, tmp_path, monkeypatch,
                                                    capsys) -> None:
    from pathlib import Path
    bad = Path(npy_sets[1]) / "000002.npy"
    good = bad.read_bytes()
    np.save(bad, np.zeros((64, 512, 3), np.float32))   # the last set's last scan: wrong shape
    monkeypatch.setattr(predict_job, "PART", 2)
    out = tmp_path / "new" / "preds"
    try:
        assert main(["predict", *npy_sets, "--out", str(out)]) == 2
    finally:
        bad.write_bytes(good)
    assert "000002.npy" in capsys.readouterr().err
    assert not (tmp_path / "new").exists()   # the folders it made are gone with the files
    assert main(["predict", *npy_sets, "--out", str(out), "--json"]) == 0
    assert sorted(p.name for p in (out / "a").iterdir())[:2] == ["000000.png",
                                                                  "000000.pred.npy"]
    assert len(list(out.rglob("*.pred.npy"))) == 8
