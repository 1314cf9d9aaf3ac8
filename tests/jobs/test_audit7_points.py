"""`falsify predict --score points`: every point with a pixel scored with that pixel's prediction
against its own label and at its own range (SemanticKITTI's protocol), counted by hand on small
scans; points without a pixel counted, .npy range images refused, a model that does not fit the
sensor refused before any scan is read, and the default (`pixels`) as before."""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from falsify.cli import main
from falsify.data.kitti_object import KittiObject, format_calib
from falsify.data.scansets import load_sets
from falsify.errors import FalsifyError
from falsify.images.png import encode_png
from falsify.jobs.predict import evaluate
from falsify.sensor.calibration import KittiCalib
from falsify.sensor.lidar import load_sensor
from tests.conftest import FIT_SEQUENCES, MINI
from tests.jobs.test_predict import BUNDLED, synthetic_scans

SENSOR = load_sensor("kitti-hdl64e-front")   # predict's default: 90 degrees ahead, 64 x 512
A = np.array([1.0, 0.03, -0.1])     # two rays of the front sensor, as direction per metre ahead
B = np.array([1.0, -0.05, -0.08])
# (point, raw SemanticKITTI id): three points on ray A, two on ray B, one behind the sensor
# (outside its 90 degrees) and one past its 120 m: the last two have no pixel.
POINTS = [(10 * A, 10), (12 * A, 40), (25 * A, 10), (8 * B, 10), (9 * B, 0),
          (np.array([-10.0, 0.0, -1.0]), 10), (200 * A, 10)]


class CarEverywhere:
    """A stand-in network predicting car on every valid pixel (four classes, or SemanticKITTI's
    train ids with `semantic`), so that every count below follows from the labels alone."""

    model_hash = "0" * 64

    def __init__(self, semantic: bool = False) -> None:
        classes = {"car": 1, "road": 9} if semantic else {"unknown": 0, "car": 1}
        self.spec = SimpleNamespace(name="car-everywhere", classes=classes,
                                    input_kind="range")

    def predict(self, images: np.ndarray) -> SimpleNamespace:
        car = (images[..., 4] > 0).astype(np.uint8)   # class 1 and train id 1 are both car
        return SimpleNamespace(classes=car, train_ids=car)


def pixel(p: np.ndarray) -> tuple[int, int]:
    row, col, inside = SENSOR.pixel_of(p[None])
    assert inside[0]
    return int(row[0]), int(col[0])


def write_sequence(root: Path, points=POINTS) -> Path:
    """A SemanticKITTI root holding sequence 01 with one scan and its .label."""
    seq = root / "sequences" / "01"
    (seq / "velodyne").mkdir(parents=True)
    (seq / "labels").mkdir()
    xyz = np.array([p for p, _ in points], np.float32)
    np.column_stack([xyz, np.full(len(xyz), 0.5, np.float32)]).tofile(
        seq / "velodyne" / "000000.bin")
    np.array([lab | (7 << 16) for _, lab in points], np.uint32).tofile(
        seq / "labels" / "000000.label")
    return root


def car(evaluation) -> tuple[int, int, int]:
    c = evaluation.pooled.car()
    return c.tp, c.fp, c.fn


def band_car(evaluation) -> dict[str, tuple[int, int, int]]:
    return {b: (s.car().tp, s.car().fp, s.car().fn) for b, s in evaluation.bands}


def test_rays_share_pixels() -> None:
    """The fixture's premise: the points of a ray share one pixel, the two rays differ."""
    assert pixel(10 * A) == pixel(12 * A) == pixel(25 * A) != pixel(8 * B) == pixel(9 * B)


def test_points_each_count_with_their_own_label_and_range(tmp_path: Path) -> None:
    """Per pixel, the nearest point of each ray counts (2 cars found); per point, all five:
    road and unlabeled (unknown in four classes) become false cars, and the 25 m car counts in
    its own band, not its pixel's 10 m."""
    root = write_sequence(tmp_path)
    (pixels,) = load_sets([str(root)], SENSOR)
    (points,) = load_sets([str(root)], SENSOR, points=True)
    by_pixel = evaluate(CarEverywhere(), [pixels])
    by_point = evaluate(CarEverywhere(), [points], score="points")
    assert car(by_pixel) == (2, 0, 0) and car(by_point) == (3, 2, 0)
    assert band_car(by_pixel) == {"0-15 m": (2, 0, 0), "15-30 m": (0, 0, 0), "30+ m": (0, 0, 0)}
    assert band_car(by_point) == {"0-15 m": (2, 2, 0), "15-30 m": (1, 0, 0), "30+ m": (0, 0, 0)}
    assert by_point.sets[0].points_outside_image == 2 and by_point.points_outside_image == 2
    assert by_point.to_json()["score"] == "points" and by_pixel.to_json()["score"] == "pixels"
    assert "points_outside_image" not in by_pixel.to_json()
    # SemanticKITTI's classes: the unlabeled point is left out, the road point is a missed road
    by_point = evaluate(CarEverywhere(semantic=True), [points], score="points")
    assert car(by_point) == (3, 1, 0)
    road = by_point.pooled.classes[9]
    assert (road.name, road.tp, road.fp, road.fn) == ("road", 0, 0, 1)
    assert car(evaluate(CarEverywhere(semantic=True), [pixels])) == (2, 0, 0)


def write_object_dir(root: Path) -> Path:
    """A KITTI object directory of one frame: a Car box holding two points of ray A (a third,
    beyond it, is background), a Van box holding two points of one ray (ignored), a point the
    camera does not see (ignored) and one behind the sensor (no pixel)."""
    for d in ("velodyne", "label_2", "calib", "image_2"):
        (root / d).mkdir(parents=True)
    c = np.array([-10.0, 0.0, -1.0])
    van = np.array([1.0, -0.33, -0.08])
    pts = np.array([9.5 * A, 10.5 * A, 20 * A, 15 * van, 15.5 * van, [10.0, 9.5, -1.0], c])
    np.column_stack([pts, np.zeros(len(pts))]).astype(np.float32).tofile(
        root / "velodyne" / "000000.bin")
    # velodyne (x ahead, y left, z up) -> camera (x right, y down, z ahead)
    p2 = np.array([[700.0, 0, 600, 0], [0, 700, 180, 0], [0, 0, 1, 0]])
    axes = np.array([[0.0, -1, 0, 0], [0, 0, -1, 0], [1, 0, 0, 0]])
    (root / "calib" / "000000.txt").write_text(format_calib(KittiCalib((p2,) * 4, np.eye(3),
                                                                       axes)))
    boxes = [KittiObject("Car", 0, 0, 0, (0, 0, 10, 10), (1.5, 1.8, 4.0), (-0.3, 1.8, 10), 0),
             KittiObject("Van", 0, 0, 0, (0, 0, 10, 10), (1.5, 1.8, 4.0), (5.0, 1.8, 15), 0)]
    (root / "label_2" / "000000.txt").write_text("".join(b.line() + "\n" for b in boxes))
    (root / "image_2" / "000000.png").write_bytes(encode_png(np.zeros((375, 1242, 3))))
    return root


def test_kitti_object_points_take_their_class_from_the_boxes(tmp_path: Path) -> None:
    """Per pixel one car point counts; per point both in the Car box, the one beyond it a false
    car, the Van's two points and the one outside the camera's image ignored, as their pixels
    are."""
    root = write_object_dir(tmp_path / "object")
    (pixels,) = load_sets([str(root)], SENSOR)
    (points,) = load_sets([str(root)], SENSOR, points=True)
    assert int(pixels.ignore.sum()) == 2   # the Van's pixel and the camera's unseen one
    by_pixel = evaluate(CarEverywhere(), [pixels])
    by_point = evaluate(CarEverywhere(), [points], score="points")
    assert car(by_pixel) == (1, 0, 0)     # ray A's pixel holds its nearest point, a car's
    assert car(by_point) == (2, 1, 0)     # the background point behind it: a false car
    s = by_point.sets[0]
    assert (s.ignored_points, s.points_outside_image) == (3, 1)


@pytest.mark.skipif(not BUNDLED.exists(), reason="bundled model not trained yet")
def test_cli_says_which_protocol_and_counts_points_outside(tmp_path: Path, capsys) -> None:
    root = write_sequence(tmp_path / "sk")
    assert main(["predict", str(root), "--out", str(tmp_path / "a"), "--json",
                 "--score", "points"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["score"] == "points" and out["points_outside_image"] == 2
    assert out["sets"][0]["points_outside_image"] == 2
    assert main(["predict", str(root), "--out", str(tmp_path / "b"), "--score", "points"]) == 0
    text = capsys.readouterr().out
    assert "scored per point" in text and "2 points outside the sensor's image" in text
    assert main(["predict", str(root), "--out", str(tmp_path / "c"), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["score"] == "pixels" and "points_outside_image" not in out


def refused(argv: list[str], out: Path, capsys) -> str:
    assert main(["predict", *argv, "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and not out.exists()
    return err


def test_npy_range_images_cannot_be_scored_per_point(tmp_path: Path, capsys) -> None:
    (npy,) = synthetic_scans(tmp_path, 1)
    err = refused([npy, "--score", "points"], tmp_path / "out", capsys)
    assert npy in err and "--score points" in err and "no" in err and "--score pixels" in err
    with pytest.raises(FalsifyError, match="cannot be scored per point"):
        load_sets([npy], SENSOR, points=True)
    with pytest.raises(SystemExit) as exit_:
        main(["predict", npy, "--score", "voxels", "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and "--score" in err and "'pixels', 'points'" in err


@pytest.mark.skipif(not BUNDLED.exists(), reason="bundled model not trained yet")
def test_a_model_of_another_width_is_refused_before_any_scan_is_read(tmp_path: Path,
                                                                     capsys) -> None:
    """The bundled 64 x 512 network on the 64 x 2048 SemanticKITTI sensor: grid's message, not
    the runner's batch shape, and before the (empty, unreadable) scan is read."""
    (tmp_path / "empty.bin").write_bytes(b"")
    err = refused([str(tmp_path / "empty.bin"), "--sensor", "semantickitti-hdl64e"],
                  tmp_path / "out", capsys)
    assert "64×512" in err and "semantickitti-hdl64e makes 64×2048" in err
    assert "expects scans of shape" not in err and "empty" not in err


@pytest.mark.skipif(not BUNDLED.exists(), reason="bundled model not trained yet")
def test_real_fit_sequence_every_point_is_scored_or_counted(tmp_path: Path, capsys) -> None:
    """A real fit sequence: per point, the scored points and those outside the 90-degree front
    sensor add up to every point of the scans; the default still scores pixels, as before."""
    seq = MINI / "sequences" / FIT_SEQUENCES[0]
    if not seq.is_dir():
        pytest.skip(f"SemanticKITTI mini not found at {MINI}")
    total = sum(p.stat().st_size // 16 for p in (seq / "velodyne").glob("*.bin"))
    assert main(["predict", str(seq), "--out", str(tmp_path / "a"), "--json",
                 "--score", "points"]) == 0
    points = json.loads(capsys.readouterr().out)
    scored = sum(c["tp"] + c["fn"] for k, c in points["pooled"].items() if k != "miou")
    assert scored + points["points_outside_image"] == total
    assert 0.6 * total < points["points_outside_image"] < 0.85 * total   # 270 of 360 degrees
    assert main(["predict", str(seq), "--out", str(tmp_path / "b"), "--json"]) == 0
    pixels = json.loads(capsys.readouterr().out)
    assert pixels["score"] == "pixels"
    (scans,) = load_sets([str(seq)], SENSOR)
    assert sum(c["tp"] + c["fn"] for k, c in pixels["pooled"].items()
               if k != "miou") == scans.images[..., 4].size   # every pixel, as before
