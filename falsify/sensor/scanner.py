"""What scoring needs of a scanner and what a scanner places: the `Scanner` protocol, a sample's
objects standing in the world (`PlacedCar`, from the space's `CarPose`), and `InvalidSample` for
scenes that cannot exist."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from falsify.classes import CAR
from falsify.rotations import rot_x, rot_y, rot_z
from falsify.sensor.lidar import Sensor, SensorPose
from falsify.sensor.scan import Scan
from falsify.world.space import CarPose, Sample

FIRST_CAR_INSTANCE = 1   # a sample's placed objects: 1, 2, ... (the street's start at 1000)


class InvalidSample(Exception):
    """The sample's objects would intersect each other, the ego car or the background."""


@dataclass(frozen=True)
class PlacedCar:
    """A car mesh at a world pose: the car frame's origin at (x, y) on the ground, turned by
    `heading_deg` counter-clockwise from the world's +x (forward) axis."""

    model: str
    x: float
    y: float
    heading_deg: float
    instance: int
    cls: int = CAR
    z: float = 0.0  # ground height, pitch and roll where it stands (Background.pose_on)
    pitch_deg: float = 0.0
    roll_deg: float = 0.0
    paint: int | None = None  # material id replacing the model's paint; None keeps it

    def rotation(self) -> np.ndarray:
        r = rot_z(self.heading_deg)
        if self.pitch_deg or self.roll_deg:
            r = r @ rot_y(self.pitch_deg) @ rot_x(self.roll_deg)
        return r

    def translation(self) -> np.ndarray:
        return np.array([self.x, self.y, self.z])

    def matrix(self) -> np.ndarray:
        """4x4 homogeneous car-to-world transform (rotation, then translation): the pose as a
        mesh library such as trimesh takes it, for the naive paths that merge posed meshes."""
        m = np.eye(4)
        m[:3, :3], m[:3, 3] = self.rotation(), self.translation()
        return m


def place(pose: CarPose, instance: int) -> PlacedCar:
    """Space coordinates (x to the right, y forward, yaw 0 = facing forward) to the world frame."""
    heading = math.remainder(pose.yaw, 360.0)  # -180, 180 and 540 are one pose
    return PlacedCar(pose.model, x=pose.y, y=-pose.x, heading_deg=heading, instance=instance)



class Scanner(Protocol):
    """What scores samples needs from a scanner: its sensor, the ego pose on a street, warm
    background hits, scans."""

    sensor: Sensor

    def ego_pose(self, bg_id: int, pose: SensorPose = ...) -> SensorPose: ...

    def background_hits(self, bg_id: int, pose: SensorPose) -> object: ...

    def scan(self, sample: Sample, pose: SensorPose = ...,
             rng: np.random.Generator | None = None) -> Scan: ...

    def placed_pixels(self, scan: Scan) -> np.ndarray:
        """The pixels of the objects the sample placed, apart from the background's own."""
        ...
