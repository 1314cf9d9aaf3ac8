"""`falsify predict` on the bundled model: synthetic and real KITTI scans, pooled metrics."""

from __future__ import annotations

import json

import numpy as np
import pytest

from falsify.cli import main
from falsify.sensor.lidar import load_sensor
from falsify.sensor.simulator import PlacedCar, Simulator
from tests.conftest import ROOT

BUNDLED = ROOT / "models" / "weights" / "squeezeseg.onnx"
pytestmark = pytest.mark.skipif(not BUNDLED.exists(), reason="bundled model not trained yet")


def synthetic_scans(tmp_path, n=3):
    sim = Simulator(load_sensor("kitti-hdl64e-front"))
    paths = []
    for i in range(n):
        scan = sim.render(9000 + i, [PlacedCar("sedan", 9.0 + 3 * i, 1.0, 10.0 * i, 1)])
        p = tmp_path / f"syn{i}.npy"
        np.save(p, scan.image)
        paths.append(str(p))
    return paths


def test_predict_pools_metrics_over_labelled_scans(tmp_path, capsys):
    paths = synthetic_scans(tmp_path)
    out = tmp_path / "pred"
    assert main(["predict", *paths, "--out", str(out), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    car = summary["pooled"]["car"]
    assert car["tp"] + car["fn"] > 0
    # Pooled over the set: TP, FP, FN summed, then IoU (the official evaluation).
    assert car["iou"] == pytest.approx(car["tp"] / (car["tp"] + car["fp"] + car["fn"]))
    assert car["iou"] > 0.5  # the bundled model sees cars on streets it never trained on
    for p in paths:
        pred = np.load(out / (p.rsplit("/", 1)[1].replace(".npy", ".pred.npy")))
        assert pred.shape == (64, 512) and pred.dtype == np.uint8
        scan = np.load(p)
        assert (pred[scan[..., 4] == 0] == 0).all()  # invalid pixels are unknown


def test_predict_on_real_kitti(tmp_path, capsys, kitti_dir):
    npys = sorted(str(p) for p in (kitti_dir / "squeezeseg").glob("*.npy"))
    bins = sorted(str(p) for p in (kitti_dir / "semantickitti").glob("*.bin"))
    assert main(["predict", *npys, "--out", str(tmp_path / "a"), "--json"]) == 0
    real = json.loads(capsys.readouterr().out)
    assert real["scans"] == 4 and real["pooled"]["car"]["iou"] is not None
    assert main(["predict", *bins, "--out", str(tmp_path / "b"), "--json"]) == 0
    sk = json.loads(capsys.readouterr().out)
    assert sk["scans"] == 3 and sk["pooled"]["car"]["tp"] + sk["pooled"]["car"]["fn"] > 0


def test_predict_backends_agree(tmp_path, capsys):
    pytest.importorskip("torch")
    paths = synthetic_scans(tmp_path, 2)
    assert main(["predict", *paths, "--out", str(tmp_path / "o"), "--json"]) == 0
    onnx = json.loads(capsys.readouterr().out)
    assert main(["predict", *paths, "--out", str(tmp_path / "t"), "--backend", "torch",
                 "--json"]) == 0
    torch_ = json.loads(capsys.readouterr().out)
    a = np.load(tmp_path / "o" / "syn0.pred.npy")
    b = np.load(tmp_path / "t" / "syn0.pred.npy")
    assert (a == b).mean() >= 0.9999
    assert onnx["pooled"]["car"]["iou"] == pytest.approx(torch_["pooled"]["car"]["iou"],
                                                         abs=1e-3)


@pytest.mark.parametrize(("make", "message"), [
    (lambda d: d / "none.npy", "none.npy"),
    (lambda d: (np.save(d / "bad.npy", np.zeros((3, 3))), d / "bad.npy")[1], "expected (H, W, 6)"),
    (lambda d: (np.save(d / "small.npy", np.zeros((32, 256, 6), np.float32)),
                d / "small.npy")[1], "expects scans of shape"),
    (lambda d: ((d / "x.txt").write_text("x"), d / "x.txt")[1], "expected a .npy"),
])
def test_predict_bad_input_exits_2(tmp_path, capsys, make, message):
    path = make(tmp_path)
    out = tmp_path / "out"
    assert main(["predict", str(path), "--out", str(out)]) == 2
    assert message in capsys.readouterr().err
    assert not out.exists()


def test_predict_with_a_missing_model(tmp_path, capsys):
    paths = synthetic_scans(tmp_path, 1)
    assert main(["predict", *paths, "--model", str(tmp_path / "m.onnx"), "--out",
                 str(tmp_path / "o")]) == 2
    assert "m.onnx" in capsys.readouterr().err


def test_a_picture_no_prediction_wrote_is_refused_and_kept(tmp_path, capsys):
    """Before: `--out` onto a folder holding a user's syn0.png (or a KITTI object directory's
    own image_2/) replaced it with a prediction picture, exit 0. A picture an earlier
    prediction wrote (its .pred.npy beside it) is still rewritten."""
    paths = synthetic_scans(tmp_path, n=2)
    out = tmp_path / "pred"
    out.mkdir()
    (out / "syn1.png").write_bytes(b"mine")
    assert main(["predict", *paths, "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert f"{out / 'syn1.png'} is there and no prediction wrote it" in err
    assert sorted(p.name for p in out.iterdir()) == ["syn1.png"]
    assert (out / "syn1.png").read_bytes() == b"mine"
    (out / "syn1.png").unlink()
    assert main(["predict", *paths, "--out", str(out)]) == 0
    assert main(["predict", *paths, "--out", str(out)]) == 0    # its own pictures: rewritten
    assert sorted(p.name for p in out.iterdir()) == [
        "syn0.png", "syn0.pred.npy", "syn1.png", "syn1.pred.npy"]
