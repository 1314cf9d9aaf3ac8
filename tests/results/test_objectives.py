"""Any class as the objective (--objective), per-class scoring of SemanticKITTI-class networks,
and the data and trainer that make such networks."""

from __future__ import annotations

import json
import sqlite3
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from falsify.cli import main
from falsify.data.velodyne import read_kitti
from falsify.errors import ConfigError
from falsify.models.runners import load_segmenter
from falsify.results.metrics import Scoring
from falsify.semantic import TRAIN_CLASSES, train_ids
from falsify.sensor.lidar import load_sensor
from falsify.world.real_scans import label_file

ROOT = Path(__file__).resolve().parents[2]
SMOKE = ROOT / "configs" / "smoke.toml"
SK20 = ROOT / "models" / "weights" / "squeezeseg20.onnx"


def rows(run: Path) -> pd.DataFrame:
    with sqlite3.connect(run / "results.sqlite") as db:
        return pd.read_sql_query("SELECT * FROM samples ORDER BY eval_index", db)


def test_scoring_names_and_aliases() -> None:
    four = Scoring.of(["unknown", "car", "pedestrian", "cyclist"], "person")
    assert four.score_column == "pedestrian_iou" and not four.semantic
    sem = Scoring.of(["car", "pedestrian", "traffic-sign"], "pedestrian")   # legacy names
    assert sem.semantic and sem.scored == ("car", "person", "traffic-sign")
    assert sem.score_column == "person_iou"
    with pytest.raises(Exception, match="allowed: car, person, traffic-sign, miou"):
        Scoring.of(["car", "person", "traffic-sign"], "road")


def test_a_four_class_spec_without_a_class_cannot_be_judged_on_it() -> None:
    """--objective names a class the network predicts: a four-class spec that maps only car is
    refused person (before: scored as pedestrian IoU 0 on every sample)."""
    with pytest.raises(ConfigError, match="'pedestrian' is not a class this model predicts; "
                       "allowed: car, miou"):
        Scoring.of(["unknown", "car"], "person")
    assert Scoring.of(["unknown", "car"], "car").scored == ("unknown", "car", "pedestrian",
                                                             "cyclist")


def test_semantic_scoring_ignores_unlabeled_and_averages_present_classes() -> None:
    s = Scoring.of(list(TRAIN_CLASSES[1:]), "miou")
    truth = np.array([[1, 1, 9, 0]])
    pred = np.array([[1, 9, 9, 13]])           # the last pixel is unlabeled: never counted
    metrics, note = s.score(pred, truth)
    assert metrics["car_iou"] == 0.5 and metrics["road_iou"] == 0.5
    assert metrics["building_iou"] is None     # predicted only on an unlabeled pixel
    assert metrics["miou"] == 0.5 and note == ""


def test_person_objective_with_the_four_class_network(tmp_path: Path, capsys) -> None:
    run = tmp_path / "p"
    assert main(["grid", str(SMOKE), "--out", str(run), "--objective", "person", "--quiet",
                 "--json", "--no-report"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["objective"] == "pedestrian"
    frame = rows(run)
    assert "miou" not in frame and "pedestrian_iou" in frame
    # no pedestrian in these scenes' labels or predictions: every sample is undefined
    assert set(frame["status"]) <= {"undefined", "ok"}
    ok = frame[frame["status"] == "ok"]
    assert ok["pedestrian_iou"].notna().all()
    assert summary["ok"] == len(ok)
    # resuming with another objective is refused, nothing written
    assert main(["grid", str(SMOKE), "--out", str(run), "--resume", "--quiet"]) == 2
    assert "score_column differs" in capsys.readouterr().err


def test_unknown_objective_is_exit_2_with_the_allowed_names(tmp_path: Path, capsys) -> None:
    assert main(["grid", str(SMOKE), "--out", str(tmp_path / "x"), "--objective", "road"]) == 2
    err = capsys.readouterr().err
    assert "--objective: 'road'" in err and "allowed: car, pedestrian, cyclist, miou" in err
    assert not (tmp_path / "x").exists()


@pytest.mark.skipif(not SK20.exists(), reason="models/weights/squeezeseg20.onnx not present")
def test_a_model_without_the_placed_class_asks_for_an_objective(tmp_path: Path, capsys) -> None:
    """No --objective given: the error says the default is the placed objects' class."""
    spec = json.loads(SK20.with_suffix(".json").read_text())
    del spec["classes"]["car"]
    model = tmp_path / "nocar.onnx"
    model.write_bytes(SK20.read_bytes())
    model.with_suffix(".json").write_text(json.dumps(spec))
    assert main(["grid", str(SMOKE), "--out", str(tmp_path / "x"), "--model", str(model)]) == 2
    err = capsys.readouterr().err
    assert "does not predict 'car', the class of the placed objects" in err
    assert "pass --objective (allowed: bicycle," in err and "--objective: 'car'" not in err
    assert not (tmp_path / "x").exists()


@pytest.mark.skipif(not SK20.exists(), reason="models/weights/squeezeseg20.onnx not present")
def test_miou_objective_with_the_20_class_network(tmp_path: Path, capsys) -> None:
    run = tmp_path / "m"
    assert main(["grid", str(SMOKE), "--out", str(run), "--model", "squeezeseg20",
                 "--objective", "miou", "--quiet", "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    frame = rows(run)
    assert summary["objective"] == "miou"
    assert summary["mean_objective"] == round(float(frame["miou"].mean()), 4)
    assert {"car_iou", "road_iou", "traffic_sign_iou", "miou"} <= set(frame)
    maps = sorted(p.name for p in (run / "maps").glob("*.csv"))
    assert "iou_road_x_y.csv" in maps and "miou_x_y.csv" in maps
    cells = pd.read_csv(run / "maps" / "miou_x_y.csv")
    first = frame[(frame["x"] == cells["x"][0]) & (frame["y"] == cells["y"][0])]
    assert cells["miou"][0] == pytest.approx(first["miou"].mean())
    html = (run / "report.html").read_text(encoding="utf-8")
    assert 'id="class-maps"' in html and "road" in html
    assert main(["gate", str(run), "--json"]) in (0, 1)   # the gate reads the objective's map


@pytest.mark.skipif(not SK20.exists(), reason="models/weights/squeezeseg20.onnx not present")
def test_predict_scores_a_20_class_network_per_class(tmp_path: Path, capsys,
                                                     kitti_dir: Path) -> None:
    seq = kitti_dir / "semantickitti-mini" / "sequences" / "05"
    if not seq.is_dir():
        pytest.skip(f"SemanticKITTI mini scans not found at {seq} (see shared/data/README.md)")
    assert main(["predict", str(seq.parent.parent), "--sequences", "05", "--model",
                 "squeezeseg20", "--json", "--out", str(tmp_path / "p")]) == 0
    doc = json.loads(capsys.readouterr().out)
    pooled = doc["pooled"]
    assert set(TRAIN_CLASSES) <= set(pooled) and "miou" in pooled
    # the same counts by hand: unlabeled pixels left out
    sensor, model = load_sensor("kitti-hdl64e-front"), load_segmenter("squeezeseg20")
    scans = [read_kitti(b, label_file(b), sensor) for b in sorted((seq / "velodyne").glob("*.bin"))]
    pred = model.predict(np.stack([s.image for s in scans])).train_ids
    tp = fp = fn = 0
    for k, s in enumerate(scans):
        t = train_ids(s.semantic)
        keep = (s.image[..., 4] > 0) & (t != 0)
        p, t = pred[k][keep] == 1, t[keep] == 1
        tp, fp, fn = tp + int((p & t).sum()), fp + int((p & ~t).sum()), fn + int((~p & t).sum())
    assert (pooled["car"]["tp"], pooled["car"]["fp"], pooled["car"]["fn"]) == (tp, fp, fn)


def test_dataset_semantic_labels_and_workers(tmp_path: Path, capsys) -> None:
    one, two = tmp_path / "one", tmp_path / "two"
    for out, workers in ((one, "1"), (two, "2")):
        assert main(["dataset", str(SMOKE), "--scans", "4", "--labels", "semantickitti",
                     "--workers", workers, "--max-cars", "3", "--out", str(out),
                     "--json"]) == 0
    capsys.readouterr()
    for name in ("000000.npy", "000003.npy", "index.json"):
        assert (one / name).read_bytes() == (two / name).read_bytes()
    a = np.load(one / "000001.npy")
    ids = np.unique(a[..., 5][a[..., 4] > 0]).astype(int)
    assert set(ids) <= set(range(len(TRAIN_CLASSES))) and 9 in ids   # road
    assert json.loads((one / "index.json").read_text())["labels"] == "semantickitti"
    assert main(["dataset", str(SMOKE), "--scans", "2", "--workers", "2", "--format",
                 "semantickitti", "--out", str(tmp_path / "x")]) == 2
    assert "only --format npy" in capsys.readouterr().err
    for bad, said in ((["--workers", "0"], "--workers: 0 must be in 1..64"),
                      (["--labels", "semantickitti", "--format", "semantickitti"],
                       "--labels semantickitti: only --format npy")):
        out = tmp_path / "bad"
        assert main(["dataset", str(SMOKE), "--scans", "2", "--out", str(out), *bad]) == 2
        assert said in capsys.readouterr().err and not out.exists()


def test_trainer_learns_semantickitti_classes(tmp_path: Path, capsys) -> None:
    pytest.importorskip("torch")

    def train_main(argv):
        return main(["train", *argv])

    data = tmp_path / "d"
    assert main(["dataset", str(SMOKE), "--scans", "8", "--labels", "semantickitti",
                 "--max-cars", "3", "--out", str(data), "--json"]) == 0
    val = tmp_path / "v"
    assert main(["dataset", str(SMOKE), "--scans", "2", "--labels", "semantickitti",
                 "--max-cars", "3", "--seed", "1", "--out", str(val), "--json"]) == 0
    out = tmp_path / "t"
    assert train_main(["--data", str(data), "--out", str(out), "--classes", "semantickitti",
                       "--crf-iterations", "0", "--epochs", "1", "--batch", "4",
                       "--val-data", str(val), "--precision", "fp32"]) == 0
    spec = json.loads((out / "squeezeseg.json").read_text())
    assert spec["num_classes"] == 20 and spec["classes"]["traffic-sign"] == 19
    log = json.loads((out / "train_log.jsonl").read_text().splitlines()[-1])
    assert len(log["val_iou"]) == 20 and "val_miou" in log
    assert load_segmenter(out / "squeezeseg.onnx").spec.classes["road"] == (9,)
    capsys.readouterr()
    gpu = __import__("torch").cuda.is_available()
    assert train_main(["--data", str(data), "--out", str(tmp_path / "c"), "--device", "cuda",
                       "--classes", "semantickitti", "--crf-iterations", "0", "--epochs", "1",
                       "--batch", "4", "--no-export"]) == (0 if gpu else 2)
    assert gpu or "--device cuda: torch sees no CUDA device" in capsys.readouterr().err


def test_predict_scores_a_model_without_car_per_class() -> None:
    from types import SimpleNamespace

    from falsify.jobs.predict import semantic_scoring
    road_only = SimpleNamespace(spec=SimpleNamespace(classes={"road": (0,), "sidewalk": (1,)}))
    labelled = SimpleNamespace(semantic=np.zeros((1, 2, 2), np.uint16))
    assert semantic_scoring(road_only, [labelled])
    assert not semantic_scoring(road_only, [labelled, SimpleNamespace(semantic=None)])
