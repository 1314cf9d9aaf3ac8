"""Evaluation pooled per set and per range band, with ignored pixels left out; `falsify predict`
on the real sets (skipped without ../shared/data)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from falsify.cli import main
from falsify.data.scansets import ScanSet, load_sets
from falsify.jobs.predict import BANDS, band_counts, evaluate
from falsify.results.metrics import confusion
from falsify.sensor.lidar import load_sensor
from tests.conftest import ROOT
from tests.jobs.test_predict import synthetic_scans

BUNDLED = ROOT / "models" / "weights" / "squeezeseg.onnx"


def test_band_counts_by_hand() -> None:
    # six pixels: car TP at 5 m, car FN at 20 m, car FP at 40 m, an ignored car FP at 10 m,
    # an invalid pixel (range 0), and a TP of unknown at 16 m
    pred = np.array([1, 0, 1, 1, 0, 0])
    label = np.array([1, 1, 0, 0, 0, 0])
    rng = np.array([5.0, 20.0, 40.0, 10.0, 0.0, 16.0])
    ignore = np.array([False, False, False, True, False, False])
    c = band_counts(pred, label, rng, ignore)
    assert c.shape == (len(BANDS), 4, 3)
    assert c[:, 1].tolist() == [[1, 0, 0], [0, 0, 1], [0, 1, 0]]       # car TP, FP, FN
    assert c[:, 0, 0].tolist() == [0, 1, 0]                             # unknown TP at 16 m
    assert c.sum() == 6                      # 4 valid kept pixels: TP 2, FN+FP pairs 2x2


@pytest.fixture(scope="module")
def two_scans(tmp_path_factory) -> list[str]:
    """Two rendered scans with cars."""
    return synthetic_scans(tmp_path_factory.mktemp("scans"), 2)


def test_bands_add_up_to_the_pool_and_ignore_counts_nowhere(two_scans) -> None:
    if not BUNDLED.exists():
        pytest.skip("bundled model not trained yet")
    from falsify.models.runners import load_segmenter

    paths = two_scans
    images = np.stack([np.load(p) for p in paths])
    ignore = np.zeros(images.shape[:3], bool)
    ignore[:, :, 200:260] = True                           # the middle of the view
    model = load_segmenter()
    plain = evaluate(model, [ScanSet("plain", images, np.zeros_like(ignore), ("a", "b"))])
    masked = evaluate(model, [ScanSet("masked", images, ignore, ("a", "b"))])
    for result in (plain, masked):
        s = result.sets[0]
        bands = sum(sc.counts[1] for _, sc in s.bands)
        assert (bands == s.pooled.counts[1]).all()        # car counts: bands sum to the pool
        assert s.pooled.car().tp > 0
    pred = plain.sets[0].predictions
    label = np.where(images[..., 4] > 0, images[..., 5], 0).astype(np.uint8)
    expect = confusion(pred[~ignore], label[~ignore])
    assert (masked.sets[0].pooled.counts == expect).all()
    assert masked.sets[0].ignored_pixels == int(ignore.sum())
    assert masked.to_json()["sets"][0]["bands"]["30+ m"]["car"]["tp"] >= 0


def test_sets_group_by_folder(tmp_path: Path) -> None:
    a, b = tmp_path / "a", tmp_path / "b"
    a.mkdir()
    b.mkdir()
    image = np.zeros((64, 512, 6), np.float32)
    for folder in (a, b):
        np.save(folder / "000000.npy", image)
    np.save(a / "000001.npy", image)
    sets = load_sets([str(a / "000000.npy"), str(b), str(a / "000001.npy")],
                     load_sensor("kitti-hdl64e-front"))
    assert [(s.name, len(s)) for s in sets] == [("a", 2), ("b", 1)]


def test_predict_on_the_real_sets(tmp_path: Path, capsys, kitti_dir: Path) -> None:
    if not BUNDLED.exists():
        pytest.skip("bundled model not trained yet")
    npys = sorted(str(p) for p in (kitti_dir / "squeezeseg").glob("*.npy"))
    bins = sorted(str(p) for p in (kitti_dir / "semantickitti").glob("*.bin"))
    out = tmp_path / "p"
    assert main(["predict", *npys, *bins, str(kitti_dir / "object"), "--out", str(out),
                 "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert [s["name"] for s in doc["sets"]] == ["squeezeseg", "semantickitti", "object"]
    assert [s["scans"] for s in doc["sets"]] == [4, 3, 3]
    for s in doc["sets"]:
        car = s["pooled"]["car"]
        assert car["tp"] + car["fn"] > 0
        assert set(s["bands"]) == {"0-15 m", "15-30 m", "30+ m"}
        assert sum(b["car"]["tp"] for b in s["bands"].values()) == car["tp"]
    assert doc["sets"][2]["ignored_pixels"] > 0 and doc["sets"][0]["ignored_pixels"] == 0
    # one folder of predictions per set, as there are several
    assert (out / "object" / "000001.pred.npy").exists()
    assert (out / "semantickitti" / "000001.pred.npy").exists()
    assert main(["predict", str(kitti_dir / "object"), "--out", str(tmp_path / "t")]) == 0
    text = capsys.readouterr().out
    assert "car by range" in text and "30+ m" in text and "pixels ignored" in text


def test_predict_bad_object_dir_exits_2(tmp_path: Path, capsys) -> None:
    root = tmp_path / "object"
    for sub in ("velodyne", "label_2", "calib", "image_2"):
        (root / sub).mkdir(parents=True)
    np.zeros((10, 4), np.float32).tofile(root / "velodyne" / "000000.bin")
    (root / "label_2" / "000000.txt").write_text("Car 0 0\n")
    (root / "calib" / "000000.txt").write_text("P2: 1\n")
    (root / "image_2" / "000000.png").write_bytes(b"")
    out = tmp_path / "out"
    assert main(["predict", str(root), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "calib" in err and "000000.txt" in err and not out.exists()
