"""KITTI's object layout: label, calib and velodyne files read and written, boxes in the camera
frame holding their Velodyne points (the camera-to-Velodyne transform), and
`falsify dataset --format kitti-object`: readable by our own reader, deterministic, and
consistent (points in 3D boxes land in the 2D boxes)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from falsify.cli import main
from falsify.data.kitti_object import (
    KittiObject,
    format_calib,
    frames,
    points_in_box,
    points_in_rect,
    read_calib,
    read_labels,
    read_velodyne,
)
from falsify.data.training import TrafficOptions, scene_for
from falsify.errors import FalsifyError
from falsify.jobs.calib import check_kitti_dir
from falsify.sensor.calibration import KittiCalib
from falsify.sensor.lidar import load_sensor
from falsify.sensor.simulator import Simulator
from tests.conftest import CONFIGS

P2 = np.array([[700.0, 0, 600, 0], [0, 700, 180, 0], [0, 0, 1, 0]])
# Velodyne (x fwd, y left, z up) -> camera (x right, y down, z fwd), no rectification.
AXES = KittiCalib((P2,) * 4, np.eye(3), np.array([[0.0, -1, 0, 0], [0, 0, -1, 0], [1, 0, 0, 0]]))


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    out = tmp_path_factory.mktemp("ko") / "kitti"
    assert main(["dataset", str(CONFIGS / "paper.toml"), "--scans", "2", "--out", str(out),
                 "--format", "kitti-object", "--max-cars", "6", "--json"]) == 0
    return out


def test_export_layout_and_contents(exported):
    for d, ext in (("velodyne", "bin"), ("image_2", "png"), ("calib", "txt"), ("label_2", "txt")):
        assert sorted(p.name for p in (exported / d).iterdir()) == [f"00000{k}.{ext}"
                                                                   for k in range(2)]
    pts = read_velodyne(exported / "velodyne" / "000000.bin")
    assert pts.shape[1] == 4 and len(pts) > 10000
    calib = read_calib(exported / "calib" / "000000.txt")
    assert np.allclose(calib.R0_rect, np.eye(3))
    labels = read_labels(exported / "label_2" / "000000.txt")
    assert any(o.type == "Car" for o in labels)
    # Frame 0's street and ego pose (drawn before its traffic), to find the ground under a box.
    sim = Simulator(load_sensor("kitti-hdl64e-front"))
    bg_id, pose, _ = scene_for(0, 0, sim, TrafficOptions(max_cars=6))
    for o in labels:
        h, w, length = o.dimensions
        assert 0.3 < h < 3.5 and 0.2 < w < 3 and 0.2 < length < 7
        left, top, right, bottom = o.box2d
        assert -0.5 <= left < right <= 1241.5 and -0.5 <= top < bottom <= 374.5
        # kitti-centre sits at the LiDAR: camera (x right, y down, z forward) -> LiDAR frame.
        x_c, y_c, z_c = o.location
        bottom_w = pose.origin(sim.sensor) + pose.rotation(sim.sensor) @ [z_c, -x_c, -y_c]
        ground = sim.pose_on(bg_id, bottom_w[0], bottom_w[1], 0.0)[0]
        assert abs(bottom_w[2] - ground) < 0.2, o  # stands on the terrain where it is
        assert o.occluded in (0, 1, 2, 3) and 0 <= o.truncated <= 1


def test_export_points_in_boxes_land_in_2d_boxes(exported):
    report = check_kitti_dir(exported, None)
    cars = report.pooled(("Car",))
    assert cars["points_in_boxes"] > 2000 and cars["fraction"] >= 0.95, cars


def test_export_is_deterministic_and_resumable(exported, tmp_path, capsys):
    again = tmp_path / "again"
    assert main(["dataset", str(CONFIGS / "paper.toml"), "--scans", "1", "--out", str(again),
                 "--format", "kitti-object", "--max-cars", "6"]) == 0
    for d, ext in (("velodyne", "bin"), ("image_2", "png"), ("calib", "txt"), ("label_2", "txt")):
        name = f"000000.{ext}"
        assert (again / d / name).read_bytes() == (exported / d / name).read_bytes(), d
    capsys.readouterr()
    assert main(["dataset", str(CONFIGS / "paper.toml"), "--scans", "1", "--out", str(again),
                 "--format", "kitti-object", "--max-cars", "6", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["written"] == 0


def test_label_line_round_trip(tmp_path):
    obj = KittiObject("Car", 0.12, 1, -1.57, (100.25, 150.5, 300.0, 260.75), (1.5, 1.8, 4.2),
                      (-2.5, 1.7, 18.25), 1.2)
    path = tmp_path / "l.txt"
    path.write_text(obj.line() + "\n" + obj.line() + " 0.93\n")
    back = read_labels(path)
    assert back == [obj, obj]
    corners = obj.corners()
    inside = obj.contains(np.vstack([corners.mean(axis=0), corners.mean(axis=0) + [0, -5, 0]]))
    assert inside.tolist() == [True, False]


def test_points_inside_a_rotated_box() -> None:
    # A 4 m long, 2 m wide, 1.5 m high box, bottom centre 10 m ahead and 2 m left of the sensor
    # at ground level (camera y = +1.7 m: down), turned by rotation_y = 0.6 rad.
    ry = 0.6
    box = KittiObject("Car", 0, 0, 0, (0, 0, 0, 0), (1.5, 2.0, 4.0), (-2.0, 1.7, 10.0), ry)
    rng = np.random.default_rng(0)
    pts = rng.uniform([6, -2, -3], [14, 6, 1], size=(20000, 3))
    inside = points_in_box(pts, box, AXES)
    # Expected, worked out by hand in the Velodyne frame: the length axis is the camera x axis
    # turned by rotation_y about the camera's y (down) axis, then mapped to Velodyne axes.
    c, s = math.cos(ry), math.sin(ry)
    length_cam = np.array([c, 0.0, -s])                  # R_y @ (1, 0, 0)
    length_velo = np.array([length_cam[2], -length_cam[0], -length_cam[1]])
    width_velo = np.cross([0.0, 0.0, 1.0], length_velo)
    d = pts - np.array([10.0, 2.0, -1.7 + 0.75])
    expected = ((np.abs(d @ length_velo) <= 2.0) & (np.abs(d @ width_velo) <= 1.0)
                & (np.abs(d[:, 2]) <= 0.75))
    assert expected.sum() > 500
    assert (inside == expected).all()
    # the corners, back in the Velodyne frame, span the ground (-1.7 m) to 1.5 m above it
    corners = np.linalg.solve(AXES.Tr_velo_to_cam[:, :3], box.corners().T).T
    assert corners[:, 2].min() == pytest.approx(-1.7) and corners[:, 2].max() == pytest.approx(
        -0.2)
    assert corners.mean(axis=0) == pytest.approx([10.0, 2.0, -0.95])


def test_image_rectangle_selects_the_frustum() -> None:
    pts = np.array([[10.0, 0.0, 0.0], [10.0, 5.0, 0.0], [-10.0, 0.0, 0.0]])
    # straight ahead projects to the principal point (600, 180); left and behind do not
    assert points_in_rect(pts, (590.0, 170.0, 610.0, 190.0), AXES).tolist() == [True, False,
                                                                               False]


def test_frame_000001_boxes_hold_their_points(kitti_dir: Path) -> None:
    root = kitti_dir / "object"
    pts = read_velodyne(root / "velodyne" / "000001.bin")[:, :3]
    calib = read_calib(root / "calib" / "000001.txt")
    boxes = {b.type: b for b in read_labels(root / "label_2" / "000001.txt") if b.has_3d}
    counts = {k: int(points_in_box(pts, b, calib).sum()) for k, b in boxes.items()}
    # The car is 58 m away and sparsely hit (9 points); the truck at 69 m holds 70.
    assert counts["Car"] >= 5 and counts["Truck"] >= 50 and counts["Cyclist"] >= 10, counts
    # Each box's points project into the object's 2D box in the image: the transform is right.
    for kind, box in boxes.items():
        inside = pts[points_in_box(pts, box, calib)]
        u, v, _ = calib.rect_to_image(calib.velo_to_rect(inside))
        left, top, right, bottom = box.box2d
        assert (u > left - 5).all() and (u < right + 5).all(), kind
        assert (v > top - 5).all() and (v < bottom + 5).all(), kind
    # Read as if label_2 were in the Velodyne frame, the boxes miss their points entirely.
    naive = KittiCalib(calib.P, np.eye(3), np.eye(3, 4))
    assert all(points_in_box(pts, b, naive).sum() == 0 for b in boxes.values())


_CALIB = format_calib(AXES)


@pytest.mark.parametrize(("name", "text", "message"), [
    ("l.txt", "Tank 0 0 0 1 2 3 4 1 1 1 0 0 5 0", "unknown type 'Tank'; allowed: Car"),
    ("l.txt", "Car 0 0 0 1 2 3", "7 fields, expected 15"),
    ("l.txt", "Car 0 0 0 1 2 3 4 1 1 x 0 0 5 0", "must be numbers"),
    ("c.txt", "P2: 1 2 3\n", "missing P0"),
    ("c.txt", _CALIB.replace("P2: ", "P2: 1 2 3 #"), "P2: not a list of numbers"),
    ("c.txt", _CALIB.replace("R0_rect: ", "R0_rect: 1 "), "R0_rect has 10 values, expected 9"),
])
def test_bad_files_name_themselves(tmp_path, name, text, message):
    path = tmp_path / name
    path.write_text(text + "\n")
    reader = read_labels if name == "l.txt" else read_calib
    with pytest.raises(FalsifyError, match=message) as err:
        reader(path)
    assert str(path) in str(err.value)


def test_unreadable_files_name_themselves(tmp_path):
    binary = tmp_path / "l.txt"
    binary.write_bytes(b"Car \xff\xfe")
    with pytest.raises(FalsifyError, match="l.txt: not UTF-8 text .labels."):
        read_labels(binary)
    with pytest.raises(FalsifyError, match="nope.txt: cannot read calib"):
        read_calib(tmp_path / "nope.txt")
    torn = tmp_path / "v.bin"
    torn.write_bytes(np.zeros(9, np.float32).tobytes())  # two points and a quarter
    with pytest.raises(FalsifyError, match="v.bin: size is not a multiple of 4 float32"):
        read_velodyne(torn)


def test_frames_name_a_frame_missing_a_file(tmp_path):
    for d, ext in (("velodyne", "bin"), ("image_2", "png"), ("calib", "txt"), ("label_2", "txt")):
        (tmp_path / d).mkdir()
        (tmp_path / d / f"000000.{ext}").write_bytes(b"")
    assert frames(tmp_path) == ["000000"]
    (tmp_path / "label_2" / "000000.txt").unlink()
    with pytest.raises(FalsifyError, match="label_2/000000.txt: missing"):
        frames(tmp_path)
    for f in (tmp_path / "velodyne").iterdir():
        f.unlink()
    with pytest.raises(FalsifyError, match="no velodyne/"):
        frames(tmp_path)


def test_dataset_bad_camera_exits_2(tmp_path, capsys):
    out = tmp_path / "o"
    assert main(["dataset", str(CONFIGS / "paper.toml"), "--scans", "1", "--out", str(out),
                 "--format", "kitti-object", "--camera", "fisheye"]) == 2
    assert "unknown camera 'fisheye'" in capsys.readouterr().err
    assert not out.exists()
