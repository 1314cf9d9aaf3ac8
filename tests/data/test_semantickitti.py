"""SemanticKITTI's layout read as it is: roots, sequences/ and sequence folders, plain folders of
.bin scans, labels beside a scan or in ../labels/; missing labels said and left out of scores;
`predict --sequences`; pooled over sequences; pictures per scan. Real-data checks skip without
../shared/data."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from falsify.cli import main
from falsify.data.scansets import ScanSet, load_sets
from falsify.errors import FalsifyError
from falsify.images.png import decode_png
from falsify.images.scan_pictures import FALSE_CAR_RGB, HIT_RGB, MISS_RGB, prediction_picture
from falsify.jobs.predict import evaluate
from falsify.sensor.lidar import load_sensor
from tests.conftest import ROOT

BUNDLED = ROOT / "models" / "weights" / "squeezeseg.onnx"
needs_model = pytest.mark.skipif(not BUNDLED.exists(), reason="bundled model not trained yet")
SENSOR = "kitti-hdl64e-front"
CAR, ROAD, MOVING_CAR = 10, 40, 252


def write_scan(bin_path: Path, label_path: Path | None, seed: int) -> None:
    """A small front-view scan: a ground-and-wall shell with a car-labelled block ahead."""
    rng = np.random.default_rng(seed)
    az = np.radians(np.linspace(-44.0, 44.0, 300))
    el = np.radians(np.linspace(-22.0, 1.5, 40))
    a, e = (g.ravel() for g in np.meshgrid(az, el))
    r = 12.0 + 3.0 * rng.random(a.size)
    car = (np.abs(a) < np.radians(6 + seed)) & (e < np.radians(-3)) & (e > np.radians(-12))
    r[car] = 8.0
    pts = np.stack([r * np.cos(e) * np.cos(a), r * np.cos(e) * np.sin(a), r * np.sin(e),
                    rng.random(a.size)], axis=1).astype(np.float32)
    bin_path.parent.mkdir(parents=True, exist_ok=True)
    pts.tofile(bin_path)
    if label_path is not None:
        label_path.parent.mkdir(parents=True, exist_ok=True)
        sem = np.where(car, CAR if seed % 2 else MOVING_CAR, ROAD).astype(np.uint32)
        ((np.uint32(seed + 1) << 16) | sem).astype(np.uint32).tofile(label_path)


def make_root(root: Path, sequences: dict[str, int], missing: tuple[str, ...] = ()) -> Path:
    """A SemanticKITTI root: sequences/SS/velodyne/NNNNNN.bin, sequences/SS/labels/NNNNNN.label
    (`missing` lists 'SS/NNNNNN' scans left without a label)."""
    for sid, n in sequences.items():
        seq = root / "sequences" / sid
        for k in range(n):
            frame = f"{k:06d}"
            label = None if f"{sid}/{frame}" in missing else seq / "labels" / f"{frame}.label"
            write_scan(seq / "velodyne" / f"{frame}.bin", label, int(sid) + k)
        (seq / "calib.txt").write_text("P0: 1 0 0 0 0 1 0 0 0 0 1 0\n")
    return root


@pytest.fixture(scope="module")
def root(tmp_path_factory) -> Path:
    return make_root(tmp_path_factory.mktemp("sk"), {"00": 2, "03": 1, "08": 2})


def car_pixels(s: ScanSet) -> int:
    return int((s.images[..., 5] == 1).sum())


def test_root_sequences_folder_and_one_sequence_load(root: Path) -> None:
    sensor = load_sensor(SENSOR)
    for given in (root, root / "sequences"):
        sets = load_sets([str(given)], sensor)
        assert [(s.name, len(s)) for s in sets] == [("00", 2), ("03", 1), ("08", 2)]
        assert all(s.unlabelled == () and s.labelled().all() for s in sets)
        assert all(car_pixels(s) > 0 for s in sets)      # labels found in ../labels/
    (one,) = load_sets([str(root / "sequences" / "08")], sensor)
    assert one.name == "08" and len(one) == 2 and car_pixels(one) > 0
    picked = load_sets([str(root)], sensor, sequences=["08", "00"])
    assert [s.name for s in picked] == ["00", "08"]
    # a velodyne/ folder and loose .bin files in it: named by the sequence, labels in ../labels/
    velodyne = root / "sequences" / "03" / "velodyne"
    for given in ([str(velodyne)], [str(velodyne / "000000.bin")]):
        (s,) = load_sets(given, sensor)
        assert s.name == "03" and s.unlabelled == () and car_pixels(s) > 0


def test_plain_folder_of_bins_with_labels_beside_or_missing(tmp_path: Path) -> None:
    folder = tmp_path / "scans"
    write_scan(folder / "a.bin", folder / "a.label", 1)
    write_scan(folder / "b.bin", None, 2)
    (s,) = load_sets([str(folder)], load_sensor(SENSOR))
    assert s.name == "scans" and len(s) == 2
    assert s.unlabelled == (str(folder / "b.bin"),)
    assert s.labelled().tolist() == [True, False]
    assert (s.images[0, ..., 5] == 1).any() and not (s.images[1, ..., 5] > 0).any()


def test_an_empty_folder_is_refused_naming_the_layouts(tmp_path: Path) -> None:
    (tmp_path / "empty").mkdir()
    with pytest.raises(FalsifyError, match="SemanticKITTI root"):
        load_sets([str(tmp_path / "empty")], load_sensor(SENSOR))


class CarEverywhere:
    """A stand-in model that calls every valid pixel a car."""

    class spec:
        name = "car-everywhere"

    model_hash = "0" * 64

    def predict(self, images: np.ndarray):
        class Out:
            classes = (images[..., 4] > 0).astype(np.uint8)
        return Out()


def test_unlabelled_scans_are_predicted_but_never_scored(root: Path) -> None:
    (s,) = load_sets([str(root / "sequences" / "00")], load_sensor(SENSOR))
    alone = ScanSet("a", s.images[:1], s.ignore[:1], s.sources[:1])
    both = ScanSet("b", s.images, s.ignore, s.sources, unlabelled=(s.sources[1],))
    a, b = evaluate(CarEverywhere(), [alone]), evaluate(CarEverywhere(), [both])
    assert (a.pooled.counts == b.pooled.counts).all()          # the second scan counts nowhere
    assert b.sets[0].scan_car_iou[1] is None and b.sets[0].scored == 1
    assert b.sets[0].predictions.shape[0] == 2                   # ... but is predicted
    unknown = s.images.copy()
    unknown[1, ..., 5] = 0                                       # read as all unknown
    as_unknown = evaluate(CarEverywhere(), [ScanSet("c", unknown, s.ignore, s.sources)])
    assert as_unknown.pooled.car().fp > a.pooled.car().fp        # what scoring it would do
    assert b.to_json()["unlabelled"] == [s.sources[1]]


@needs_model
def test_missing_label_named_on_stderr_and_in_json_and_left_out(tmp_path: Path, capsys) -> None:
    r = make_root(tmp_path / "sk", {"00": 2}, missing=("00/000001",))
    out = tmp_path / "out"
    assert main(["predict", str(r), "--out", str(out), "--json"]) == 0
    captured = capsys.readouterr()
    doc = json.loads(captured.out)
    missing = r / "sequences" / "00" / "velodyne" / "000001.bin"
    assert (f"falsify: warning: no labels for {missing} (looked for 000001.label beside it and "
            "in ../labels/)") in captured.err.splitlines()
    assert doc["unlabelled"] == [str(missing)] and doc["scored_scans"] == 1
    (s,) = doc["sets"]
    assert s["scans"] == 2 and s["scored_scans"] == 1 and s["unlabelled"] == [str(missing)]
    assert [p["labelled"] for p in s["per_scan"]] == [True, False]
    # the same counts as predicting the labelled scan alone
    labelled = r / "sequences" / "00" / "velodyne" / "000000.bin"
    assert main(["predict", str(labelled), "--out", str(tmp_path / "one"), "--json"]) == 0
    one = json.loads(capsys.readouterr().out)
    assert one["pooled"] == doc["pooled"]
    assert (out / "000001.pred.npy").exists() and (out / "000001.png").exists()
    assert main(["predict", str(r), "--out", str(tmp_path / "t")]) == 0
    text = capsys.readouterr().out
    assert "1 scans without labels" in text and "1 without labels, not scored" in text


@needs_model
@pytest.mark.parametrize("value", ["8", "99", "ab", "00,", "03,09"])
def test_sequences_bad_value_exits_2(root: Path, tmp_path: Path, capsys, value: str) -> None:
    out = tmp_path / "out"
    assert main(["predict", str(root), "--sequences", value, "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "--sequences" in err and "allowed: 00, 03, 08" in err
    assert not out.exists()


@needs_model
def test_sequences_need_a_root(tmp_path: Path, capsys) -> None:
    write_scan(tmp_path / "scans" / "a.bin", tmp_path / "scans" / "a.label", 1)
    out = tmp_path / "out"
    assert main(["predict", str(tmp_path / "scans"), "--sequences", "00", "--out",
                 str(out)]) == 2
    err = capsys.readouterr().err
    assert "--sequences" in err and "no SemanticKITTI root" in err and not out.exists()


@needs_model
def test_sequences_pick_and_pooled_is_the_sum(root: Path, tmp_path: Path, capsys) -> None:
    out = tmp_path / "out"
    assert main(["predict", str(root), "--sequences", "08,00", "--out", str(out),
                 "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert [(s["name"], s["scans"]) for s in doc["sets"]] == [("00", 2), ("08", 2)]
    assert doc["scans"] == 4 and doc["unlabelled"] == []
    for cls, pooled in doc["pooled"].items():
        for k in ("tp", "fp", "fn"):
            assert pooled[k] == sum(s["pooled"][cls][k] for s in doc["sets"])
    for band, scores in doc["bands"].items():
        assert scores["car"]["tp"] == sum(s["bands"][band]["car"]["tp"] for s in doc["sets"])
    assert sum(b["car"]["fn"] for b in doc["bands"].values()) == doc["pooled"]["car"]["fn"]
    assert doc["pooled"]["car"]["tp"] + doc["pooled"]["car"]["fn"] > 0
    assert sorted(p.name for p in out.iterdir()) == ["00", "08"]
    assert main(["predict", str(root), "--sequences", "08,00", "--out", str(tmp_path / "t")]) == 0
    assert "all 2 labelled sets pooled: 4 scans" in capsys.readouterr().out


@needs_model
def test_pictures_exist_and_are_deterministic(root: Path, tmp_path: Path, capsys) -> None:
    outs = [tmp_path / "a", tmp_path / "b"]
    for out in outs:
        assert main(["predict", str(root / "sequences" / "08"), "--out", str(out)]) == 0
    capsys.readouterr()
    for frame in ("000000", "000001"):
        a, b = ((o / f"{frame}.png").read_bytes() for o in outs)
        assert a == b
        rgb = decode_png(a)
        assert rgb.shape == (64 * 3 + 4 + 64 * 3 + 4 + 512, 512, 3)
        assert (outs[0] / f"{frame}.pred.npy").exists()


def test_the_picture_marks_misses_and_false_cars() -> None:
    image = np.zeros((64, 512, 6), np.float32)
    image[30:40, 200:300, 0] = np.arange(10.0, 20.0)[:, None]   # 10-19 m ahead, one per row
    image[30:40, 200:300, 1] = np.linspace(4, -4, 100)   # across the view
    image[30:40, 200:300, 4] = 10.0
    image[30:40, 200:250, 5] = 1                         # label car on the left half
    pred = np.zeros((64, 512), np.uint8)
    pred[30:35, 200:300] = 1                             # predicted car on the top rows
    pic = prediction_picture(image, pred)
    bev = pic[64 * 3 + 4 + 64 * 3 + 4:]
    for colour in (HIT_RGB, MISS_RGB, FALSE_CAR_RGB):
        assert (bev == colour).all(axis=-1).any()
    labels, preds = pic[:64 * 3], pic[64 * 3 + 4:64 * 3 * 2 + 4]
    assert not (labels == preds).all()                   # the two range images differ
    unlabelled = prediction_picture(image, pred, labelled=False)[64 * 3 * 2 + 8:]
    assert not (unlabelled == MISS_RGB).all(axis=-1).any()
    assert (prediction_picture(image, pred) == pic).all()


@needs_model
def test_predict_on_the_semantickitti_mini_evaluation_sequences(tmp_path: Path, capsys,
                                                                kitti_dir: Path) -> None:
    mini = kitti_dir / "semantickitti-mini"
    if not (mini / "sequences").is_dir():
        pytest.skip(f"SemanticKITTI mini scans not found at {mini} (see shared/data/README.md)")
    out = tmp_path / "p"
    assert main(["predict", str(mini), "--sequences", "00,03,06,08", "--json", "--out",
                 str(out)]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert [(s["name"], s["scans"]) for s in doc["sets"]] == [
        ("00", 3), ("03", 3), ("06", 3), ("08", 3)]
    assert doc["scans"] == 12 and doc["scored_scans"] == 12 and doc["unlabelled"] == []
    car = doc["pooled"]["car"]
    assert car["tp"] == sum(s["pooled"]["car"]["tp"] for s in doc["sets"])
    assert car["fn"] == sum(s["pooled"]["car"]["fn"] for s in doc["sets"])
    assert car["iou"] == pytest.approx(car["tp"] / (car["tp"] + car["fp"] + car["fn"]))
    assert set(doc["bands"]) == {"0-15 m", "15-30 m", "30+ m"}
    for s in doc["sets"]:
        assert s["pooled"]["car"]["tp"] + s["pooled"]["car"]["fn"] > 0
        assert (out / s["name"] / "000005.png").exists()
