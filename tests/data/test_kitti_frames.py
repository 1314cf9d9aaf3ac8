"""KITTI object frames as labelled range images: boxes label Velodyne points, ignored regions and
what the left camera does not see count for nothing (reading and box geometry:
test_kitti_object.py)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from falsify.data.kitti_frames import _IGNORE_ID, label_points, read_object_frame
from falsify.data.kitti_object import KittiObject
from falsify.sensor.lidar import load_sensor
from tests.data.test_kitti_object import AXES


def test_ignored_regions_win_and_unseen_points_are_ignored() -> None:
    # a car 10 m ahead, a DontCare rectangle over its left half, and a point behind the camera
    car = KittiObject("Car", 0, 0, 0, (0, 0, 0, 0), (1.5, 2.0, 4.0), (0.0, 1.7, 10.0), 0.0)
    dontcare = KittiObject("DontCare", -1, -1, -10, (0.0, 0.0, 590.0, 375.0), (-1, -1, -1),
                           (-1000, -1000, -1000), -10)
    pts = np.array([[10.0, 0.5, -1.0], [10.0, -0.5, -1.0], [-10.0, 0.0, 0.0], [30.0, 0, -1.0]])
    assert label_points(pts, [car], AXES).tolist() == [1, 1, 0, 0]
    assert label_points(pts, [car], AXES, (1242, 375)).tolist() == [1, 1, _IGNORE_ID, 0]
    assert label_points(pts, [car, dontcare], AXES, (1242, 375)).tolist() == [
        _IGNORE_ID, 1, _IGNORE_ID, 0]


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
