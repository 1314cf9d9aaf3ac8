"""KITTI 3D object frames as labelled range images with an ignore mask, for evaluation.

A frame's points are labelled from its 3D boxes: inside a `Car` box is car (and a `Pedestrian`
or `Cyclist` box its class); inside a `Van`, `Truck`, `Tram` or `Misc` box, or seen by the left
camera inside a `DontCare` rectangle (DontCare has no 3D box, only a 2D image region), a point
is ignored: it counts for no class. Points the left camera does not see (outside image_2) are
ignored too: KITTI labels only what is in that image. Reading the files and the box geometry
are falsify.data.kitti_object's.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from falsify.data.kitti_object import (
    TYPES,
    KittiObject,
    points_in_box,
    points_in_rect,
    read_calib,
    read_labels,
    read_velodyne,
)
from falsify.data.velodyne import kitti_rows
from falsify.errors import FalsifyError
from falsify.images.png import png_size
from falsify.sensor.calibration import KITTI_PIXEL_SHIFT, KittiCalib
from falsify.sensor.lidar import Sensor
from falsify.sensor.scan import Scan, image_from_points

# label_2 type -> our class id; every other type counts for no class.
LABELLED = {"Car": 1, "Pedestrian": 2, "Person_sitting": 2, "Cyclist": 3}
IGNORED = tuple(t for t in TYPES if t not in LABELLED)
# Marks an ignored point in the label channel until the image is split into labels and mask.
_IGNORE_ID = 255


@dataclass(frozen=True)
class ObjectFrame:
    """A labelled frame: the range image (label channel 0 where ignored), the ignore mask, and
    every point with its class from the boxes (for point-wise scoring)."""

    name: str
    scan: Scan
    ignore: np.ndarray        # (H, W) bool
    boxes: tuple[KittiObject, ...]
    xyz: np.ndarray | None = None          # (N, 3) float32 every point of the frame
    point_class: np.ndarray | None = None  # (N,) uint8 each point's class id (0 where ignored)
    point_ignore: np.ndarray | None = None  # (N,) bool points that count for no class


def label_points(points: np.ndarray, boxes: list[KittiObject], calib: KittiCalib,
                 image_size: tuple[int, int] | None = None) -> np.ndarray:
    """Class id per Velodyne point (0 outside every box); _IGNORE_ID where an ignored box holds
    it or, given the image's (width, height), where the left camera does not see the point.

    An ignored region wins over a labelled box, so a car point inside a DontCare rectangle
    counts for nothing rather than for car."""
    cls = np.zeros(len(points), np.uint8)
    if image_size is not None:
        whole = image_rect(image_size)
        cls[~points_in_rect(points, whole, calib)] = _IGNORE_ID
    for box in boxes:
        if box.type in LABELLED and box.has_3d:
            cls[points_in_box(points, box, calib)] = LABELLED[box.type]
    for box in boxes:
        if box.type in IGNORED:
            inside = (points_in_box(points, box, calib) if box.has_3d
                      else points_in_rect(points, box.box2d, calib))
            cls[inside] = _IGNORE_ID
    return cls


def image_rect(image_size: tuple[int, int]) -> tuple[float, float, float, float]:
    """The (left, top, right, bottom) a (width, height) image spans in KITTI's pixel coordinates:
    P2 puts pixel centres on integers, so pixel 0 spans [-0.5, 0.5] and the image
    [-0.5, width - 0.5], not [0, width] (half a pixel of points seen at each edge)."""
    w, h = image_size
    s = KITTI_PIXEL_SHIFT
    return (-s, -s, float(w) - s, float(h) - s)


def read_object_frame(root: Path, name: str, sensor: Sensor) -> ObjectFrame:
    """One frame of a KITTI object directory, projected with `sensor` and labelled from boxes."""
    bin_path = root / "velodyne" / f"{name}.bin"
    pts = read_velodyne(bin_path)
    if not len(pts):
        raise FalsifyError(f"{bin_path}: no points (expected N x 4 float32: x, y, z, "
                           "reflectance)")
    calib = read_calib(root / "calib" / f"{name}.txt")
    boxes = read_labels(root / "label_2" / f"{name}.txt")
    cls = label_points(pts[:, :3], boxes, calib, png_size(root / "image_2" / f"{name}.png"))
    scan = image_from_points(sensor, pts[:, :3], cls, np.zeros(len(pts), np.int32),
                             intensity=pts[:, 3], rows=kitti_rows(sensor, pts[:, :3]))
    image = scan.image
    image[..., 5], ignore = split_ignored(image[..., 5])
    point_class, point_ignore = split_ignored(cls)
    return ObjectFrame(name, Scan(image, scan.instance), ignore, tuple(boxes), pts[:, :3],
                       point_class, point_ignore)


def split_ignored(cls: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Class ids as `label_points` gives them, per point or per pixel -> (the ids, 0 where
    ignored; the ignore mask): one rule for the range image and point-wise scoring."""
    ignore = cls == _IGNORE_ID
    return np.where(ignore, 0, cls).astype(cls.dtype), ignore
