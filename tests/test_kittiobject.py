"""KITTI object frames: boxes in the camera frame label Velodyne points, ignored regions count for
nothing, and frame 000001's boxes land on its points (the camera-to-Velodyne transform)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from falsify.errors import FalsifyError
from falsify.kittiobject import (
    Box,
    Calib,
    box_corners_velo,
    points_in_box,
    points_in_image_box,
    read_calib,
    read_labels,
    read_object_frame,
)
from falsify.sensor import load_sensor

# Velodyne (x fwd, y left, z up) -> camera (x right, y down, z fwd), no rectification.
AXES = Calib(p2=np.array([[700.0, 0, 600, 0], [0, 700, 180, 0], [0, 0, 1, 0]]),
             r0_rect=np.eye(3),
             tr_velo_to_cam=np.array([[0.0, -1, 0, 0], [0, 0, -1, 0], [1, 0, 0, 0]]))


def test_points_inside_a_rotated_box() -> None:
    # A 4 m long, 2 m wide, 1.5 m high box, bottom centre 10 m ahead and 2 m left of the sensor
    # at ground level (camera y = +1.7 m: down), turned by rotation_y = 0.6 rad.
    ry = 0.6
    box = Box("Car", (0, 0, 0, 0), (1.5, 2.0, 4.0), (-2.0, 1.7, 10.0), ry)
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
    corners = box_corners_velo(box, AXES)
    assert corners[:, 2].min() == pytest.approx(-1.7) and corners[:, 2].max() == pytest.approx(
        -0.2)
    assert corners.mean(axis=0) == pytest.approx([10.0, 2.0, -0.95])


def test_image_box_selects_the_frustum() -> None:
    pts = np.array([[10.0, 0.0, 0.0], [10.0, 5.0, 0.0], [-10.0, 0.0, 0.0]])
    region = Box("DontCare", (590.0, 170.0, 610.0, 190.0), (-1, -1, -1), (-1000, -1000, -1000),
                 -10)
    # straight ahead projects to the principal point (600, 180); left and behind do not
    assert points_in_image_box(pts, region, AXES).tolist() == [True, False, False]


def test_frame_000001_boxes_hold_their_points(kitti_dir: Path) -> None:
    root = kitti_dir / "object"
    pts = np.fromfile(root / "velodyne" / "000001.bin", np.float32).reshape(-1, 4)[:, :3]
    calib = read_calib(root / "calib" / "000001.txt")
    boxes = {b.kind: b for b in read_labels(root / "label_2" / "000001.txt") if b.has_3d}
    counts = {k: int(points_in_box(pts, b, calib).sum()) for k, b in boxes.items()}
    # The car is 58 m away and sparsely hit (9 points); the truck at 69 m holds 70.
    assert counts["Car"] >= 5 and counts["Truck"] >= 50 and counts["Cyclist"] >= 10, counts
    # Each box's points project into the object's 2D box in the image: the transform is right.
    for kind, box in boxes.items():
        inside = pts[points_in_box(pts, box, calib)].astype(np.float64)
        uvw = calib.p2 @ calib.velo_to_rect @ np.c_[inside, np.ones(len(inside))].T
        u, v = uvw[0] / uvw[2], uvw[1] / uvw[2]
        left, top, right, bottom = box.bbox
        assert (u > left - 5).all() and (u < right + 5).all(), kind
        assert (v > top - 5).all() and (v < bottom + 5).all(), kind
    # Read as if label_2 were in the Velodyne frame, the boxes miss their points entirely.
    naive = Calib(calib.p2, np.eye(3), np.eye(3, 4))
    assert all(points_in_box(pts, b, naive).sum() == 0 for b in boxes.values())


def test_object_frame_labels_and_ignore(kitti_dir: Path) -> None:
    frame = read_object_frame(kitti_dir / "object", "000002", load_sensor("kitti-hdl64e-front"))
    label = frame.scan.image[..., 5]
    assert frame.scan.image.shape == (64, 512, 6)
    assert (label == 1).sum() >= 30                      # the car 34 m ahead
    assert frame.ignore.sum() > 500                      # the Misc box 9 m ahead and outside
    assert not (frame.ignore & (label > 0)).any()        # ignored pixels carry no class
    # columns at the view's edges fall outside the camera image: ignored
    valid = frame.scan.image[..., 4] > 0
    assert frame.ignore[:, :5][valid[:, :5]].all()


@pytest.mark.parametrize(("name", "text", "message"), [
    ("label.txt", "Car 0 0 0 1 2 3\n", "expected 15 fields"),
    ("label.txt", "Boat 0 0 0 1 2 3 4 1 1 1 0 0 0 0\n", "unknown object type 'Boat'"),
    ("calib.txt", "P2: 1 2 3\n", "key 'P2' with 12 numbers"),
])
def test_bad_files_name_themselves(tmp_path: Path, name: str, text: str, message: str) -> None:
    path = tmp_path / name
    path.write_text(text)
    reader = read_labels if name == "label.txt" else read_calib
    with pytest.raises(FalsifyError, match=message) as err:
        reader(path)
    assert str(path) in str(err.value)
