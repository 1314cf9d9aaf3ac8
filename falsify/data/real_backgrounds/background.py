"""A real scan read for insertion: its range image as `falsify predict` reads it, each pixel's
ray, and the whole cloud with its labels (SemanticKITTI's, or KITTI object boxes')."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from falsify.data.kitti_object import points_in_box, read_calib, read_labels
from falsify.data.real_backgrounds.ground import PointIndex, ground_points
from falsify.data.real_backgrounds.rays import pixel_directions
from falsify.data.velodyne import kitti_rows, read_bin, read_kitti
from falsify.errors import FalsifyError
from falsify.rotations import rot_z
from falsify.semantic import RAW_ID, kitti4, split_label
from falsify.sensor.lidar import Sensor
from falsify.sensor.scan import Scan, image_from_points
from falsify.world.space import RealScan

# KITTI object types -> the SemanticKITTI id their box's points carry (others: unlabeled).
OBJECT_TYPES = {"Car": RAW_ID["car"], "Van": RAW_ID["other-vehicle"], "Truck": RAW_ID["truck"],
                "Tram": RAW_ID["other-vehicle"], "Pedestrian": RAW_ID["person"],
                "Person_sitting": RAW_ID["person"], "Cyclist": RAW_ID["bicyclist"]}



@dataclass(frozen=True)
class RealBackground:
    """A real scan ready for insertion: its range image as read, each pixel's ray, and the whole
    cloud with its labels (for the ground and for collisions)."""

    scan: Scan                 # the real scan in the sensor's image, as `predict` reads it
    dist: np.ndarray           # (H, W) range of each pixel's point along its ray (at most the
    #                            sensor's range: an empty pixel's ray may meet a car that far)
    origin: np.ndarray         # (H, W, 3) where each pixel's ray starts (sensor frame)
    direction: np.ndarray      # (H, W, 3) unit direction of each pixel's ray
    cloud: PointIndex          # every finite point of the scan, with its label where known
    dense: bool                # every point labelled (SemanticKITTI), not only boxes' points
    ground: PointIndex         # the points a car may stand on
    row_elevation: np.ndarray  # (H, 2) lowest and highest elevation (rad) of each row's rays
    valid: np.ndarray          # (H, W) the pixels holding a real point
    origin_reach: float        # the farthest any ray starts from the sensor's origin


def read_background(real: RealScan, sensor: Sensor) -> RealBackground:
    """Read a real scan and its labels; FalsifyError names a file that cannot be read."""
    pts = read_bin(real.bin)
    finite = np.isfinite(pts).all(axis=1)
    xyz = np.ascontiguousarray(pts[finite, :3])
    if real.kind == "object" or real.yaw_deg:
        sem, inst = _labels(real, xyz, finite)
        rows = kitti_rows(sensor, xyz)   # from the stored order, before turning
        if real.yaw_deg:
            xyz = np.ascontiguousarray((xyz.astype(np.float64) @ rot_z(real.yaw_deg).T)
                                       .astype(np.float32))
        scan = image_from_points(sensor, xyz, kitti4(sem) if sem is not None else np.zeros(
            len(xyz), np.uint8), inst, intensity=pts[finite, 3], rows=rows, semantic=sem)
    else:
        scan = read_kitti(real.bin, real.label, sensor)
        sem = None
        if real.label is not None:
            sem = split_label(np.fromfile(real.label, np.uint32))[0][finite].astype(np.uint16)
    dense = real.kind == "semantickitti"
    origin = np.zeros((*sensor.shape, 3))
    if sensor.projection == "rings" and sensor.ray_origins is not None:
        origin += sensor.ray_origins
    valid = scan.valid
    p = scan.image[..., 0:3].astype(np.float64) - origin
    dist = np.where(valid, np.linalg.norm(p, axis=-1), np.inf)
    direction = pixel_directions(sensor)
    direction[valid] = p[valid] / dist[valid][:, None]
    ground = ground_points(xyz, sem if dense else None)
    for a in (dist, origin, direction):
        a.setflags(write=False)
    el = np.arcsin(np.clip(direction[..., 2], -1.0, 1.0))
    return RealBackground(scan, np.minimum(dist, sensor.max_range), origin, direction,
                          PointIndex.of(xyz, sem), dense,
                          PointIndex.of(ground.astype(np.float64)),
                          np.stack([el.min(axis=1), el.max(axis=1)], axis=1), valid,
                          float(np.abs(origin).max()))


def _labels(real: RealScan, xyz: np.ndarray, finite: np.ndarray
            ) -> tuple[np.ndarray | None, np.ndarray]:
    """Raw ids (None unlabelled) and instances of the finite points: from a KITTI object frame's
    boxes or a SemanticKITTI .label; FalsifyError names a .label of the wrong length."""
    if real.kind == "object":
        return _box_labels(real, xyz)
    if real.label is None:
        return None, np.zeros(len(xyz), np.int32)
    lab = np.fromfile(real.label, np.uint32)
    if len(lab) != len(finite):
        raise FalsifyError(f"{real.label}: {len(lab)} labels for {len(finite)} points in "
                           f"{real.bin.name}")
    sem, high = split_label(lab[finite])
    return sem.astype(np.uint16), high.astype(np.int32)


def _box_labels(real: RealScan, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Raw ids and instances of a KITTI object frame's points from its label_2 boxes."""
    calib = read_calib(real.bin.parent.parent / "calib" / f"{real.bin.stem}.txt")
    sem = np.zeros(len(xyz), np.uint16)
    inst = np.zeros(len(xyz), np.int32)
    for k, obj in enumerate(read_labels(real.label)):
        if obj.type in OBJECT_TYPES and obj.has_3d:
            inside = points_in_box(xyz, obj, calib)
            sem[inside] = OBJECT_TYPES[obj.type]
            inst[inside] = k + 1
    return sem, inst
