"""Where placed objects may stand: their outlines against each other, the ego vehicle and the
background's obstacles, the surface each must stand on, and a training scene's free ego pose."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from falsify.classes import CAR
from falsify.rotations import rot_z
from falsify.sensor.lidar import SensorPose
from falsify.sensor.scanner import InvalidSample, PlacedCar
from falsify.world.street_layout import KERB_OBSTACLE

# The ego vehicle's footprint around the sensor (KITTI's Passat, sensor behind the front axle);
# a sampled car that overlaps it cannot exist. It is not drawn: real scans filter the ego car.
EGO_FOOTPRINT = np.array([[-2.8, -0.95], [1.9, -0.95], [1.9, 0.95], [-2.8, 0.95]])
EGO_TRIES = 50  # draws of a training scene's ego pose before a street counts as full
# Where training scenes stand the ego along the road (x), heading +x and heading -x: beyond the
# test site too, so narrowing streets are seen from inside their narrow stretches.
EGO_X_FORWARD: tuple[float, float] = (-90.0, 90.0)
EGO_X_BACKWARD: tuple[float, float] = (-50.0, 130.0)


@dataclass(frozen=True)
class Obstacles:
    """A background's obstacle outlines with their bounding boxes, for a quick first test."""

    items: tuple
    lo: np.ndarray  # (N, 2)
    hi: np.ndarray  # (N, 2)

    @classmethod
    def of(cls, items: Sequence) -> Obstacles:
        items = tuple(items)
        lo = np.array([o.polygon.min(axis=0) for o in items]).reshape(-1, 2)
        hi = np.array([o.polygon.max(axis=0) for o in items]).reshape(-1, 2)
        return cls(items, lo, hi)


def placed_label(obj: PlacedCar, number: int) -> str:
    """How a reason names a placed object: "car 2 (sedan)", or "actor 1 (pedestrian-walking)"
    for what is not a car, as the report names them."""
    return f"{'car' if obj.cls == CAR else 'actor'} {number} ({obj.model})"


def check_placement(placed: Sequence[PlacedCar], outlines: Sequence[np.ndarray],
                    obstacles: Obstacles, crosses_kerbs: Sequence[bool] | None = None,
                    ego: np.ndarray = EGO_FOOTPRINT) -> None:
    """Raise InvalidSample if car outlines overlap each other, the ego car or an obstacle (the
    kerbs' outlines left out for the objects in `crosses_kerbs`: people and bicycles)."""
    for i, (car, poly) in enumerate(zip(placed, outlines, strict=True)):
        if polygons_overlap(poly, ego):
            raise InvalidSample(f"{placed_label(car, i + 1)} intersects the ego vehicle")
        for j in range(i):
            if polygons_overlap(poly, outlines[j]):
                raise InvalidSample(f"{placed_label(car, i + 1)} intersects "
                                    f"{placed_label(placed[j], j + 1)}")
        kerbless = crosses_kerbs is not None and crosses_kerbs[i]
        obstacle = first_overlap(poly, obstacles, skip_kerbs=kerbless)
        if obstacle is not None:
            raise InvalidSample(f"{placed_label(car, i + 1)} intersects the background's "
                                f"{obstacle.label}")


class Grounds(Protocol):
    """What free_ego reads of a simulator: a background's obstacles, and the ego standing on
    its ground."""

    def obstacles(self, bg_id: int) -> Obstacles: ...

    def ego_pose(self, bg_id: int, pose: SensorPose = ...) -> SensorPose: ...


def free_ego(sim: Grounds, bg_id: int, draw: Callable[[], SensorPose],
             what: str) -> tuple[SensorPose, np.ndarray]:
    """The first pose from `draw()`, stood on the terrain, whose ego outline keeps off the
    background's obstacles, and that outline (a training scene's ego once stood in parked
    buses); InvalidSample naming `what` after EGO_TRIES draws."""
    obstacles = sim.obstacles(bg_id)
    for _ in range(EGO_TRIES):
        pose = sim.ego_pose(bg_id, draw())
        ego = ego_outline(pose)
        if first_overlap(ego, obstacles) is None:
            return pose, ego
    raise InvalidSample(f"{what}: no free ego pose on background {bg_id} in {EGO_TRIES} draws")


def first_overlap(poly: np.ndarray, obstacles: Obstacles, skip_kerbs: bool = False):
    """The first of the background's obstacles that the outline `poly` overlaps, or None;
    `skip_kerbs` leaves out the kerbs' outlines (what stops a vehicle, not a person)."""
    lo, hi = poly.min(axis=0), poly.max(axis=0)
    near = np.flatnonzero(~((obstacles.lo > hi).any(axis=1) | (obstacles.hi < lo).any(axis=1)))
    for k in near:
        if skip_kerbs and obstacles.items[k].label.startswith(KERB_OBSTACLE):
            continue
        if polygons_overlap(poly, obstacles.items[k].polygon):
            return obstacles.items[k]
    return None


def check_surfaces(placed: Sequence[PlacedCar], surfaces: Sequence[str],
                   surface_at: Callable[[float, float], str]) -> None:
    """InvalidSample naming the first object that stands on another surface than its own
    (`surfaces[k]`, "any" where absent), by `surface_at(x, y)` of the background."""
    for i, car in enumerate(placed):
        on = surfaces[i] if i < len(surfaces) else "any"
        if on == "any":
            continue
        found = surface_at(car.x, car.y)
        if found != on:
            raise InvalidSample(f"{placed_label(car, i + 1)} stands on {found}, "
                                f"not on the {on}")


def ego_outline(pose: SensorPose) -> np.ndarray:
    """The ego vehicle's outline on the ground for a sensor pose."""
    return EGO_FOOTPRINT @ rot_z(pose.heading_deg)[:2, :2].T + [pose.x, pose.y]


def polygons_overlap(a: np.ndarray, b: np.ndarray) -> bool:
    """Separating-axis test for two convex polygons (touching counts as overlap)."""
    for poly in (a, b):
        edges = np.roll(poly, -1, axis=0) - poly
        normals = np.stack([-edges[:, 1], edges[:, 0]], axis=1)
        pa, pb = a @ normals.T, b @ normals.T
        if np.any((pa.max(axis=0) < pb.min(axis=0)) | (pb.max(axis=0) < pa.min(axis=0))):
            return False
    return True
