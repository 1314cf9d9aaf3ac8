"""The camera renderer: the Simulator's BVHs cast one ray per pixel centre.

The renderer reuses the Simulator's BVHs (the background in the world frame, each car model in
its own frame) and casts one ray per pixel centre: the nearest hit gives the class, instance and
depth images, and the shading gives the RGB image.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from falsify.sensor.calibration import (
    MIN_DEPTH,
)
from falsify.sensor.camera import Camera, CameraImage
from falsify.sensor.lidar import SensorPose
from falsify.sensor.look import Look, look_of
from falsify.sensor.scanner import PlacedCar
from falsify.sensor.shading import Hits, rain_streaks, shade, shadowed, slab, sun
from falsify.sensor.simulator import Simulator
from falsify.world.space import Sample


@dataclass(frozen=True)
class _Street:
    """What one (background, pose) gives every image: its hits and their labels and depth."""

    hits: Hits
    cls: np.ndarray
    inst: np.ndarray
    depth: np.ndarray


@dataclass(frozen=True)
class _Shaded:
    """The street shaded for one look with no car: RGB and which pixels the sun lights."""

    rgb: np.ndarray
    lit: np.ndarray
    points: np.ndarray  # hit points of the lit pixels (world), for the cars' shadow test


class CameraRenderer:
    """Renders samples with a Simulator's BVHs. The street without cars is cast once per
    (background, pose) and shaded once per look, like the LiDAR's cached background hits; an
    image then re-shades only the pixels a car covers or may shade."""

    def __init__(self, sim: Simulator, camera: Camera, max_cached: int = 4,
                 incremental: bool = True):
        """`incremental=False` shades every pixel of every image (the reference the incremental
        path is tested against)."""
        self.sim = sim
        self.camera = camera
        self.incremental = incremental
        self._rays_cam = camera.intrinsics.rays().reshape(-1, 3)
        self.streaks = rain_streaks(camera.shape).ravel()
        self._streets: OrderedDict[tuple, _Street] = OrderedDict()
        self._shaded: OrderedDict[tuple, _Shaded] = OrderedDict()
        self._max_cached = max_cached

    def pose_of(self, pose: SensorPose) -> tuple[np.ndarray, np.ndarray]:
        """Camera centre (world) and the rotation taking optical-frame vectors to the world."""
        s_rot = pose.rotation(self.sim.sensor)
        ext = self.camera.extrinsic
        return pose.origin(self.sim.sensor) + s_rot @ ext.centre, s_rot @ ext.rotation.T

    def _cached(self, cache: OrderedDict, key: tuple, make):
        if key in cache:
            cache.move_to_end(key)
            return cache[key]
        value = make()
        cache[key] = value
        while len(cache) > max(1, self._max_cached):
            cache.popitem(last=False)
        return value

    def _street(self, bg_id: int, pose: SensorPose) -> _Street:
        def make() -> _Street:
            caster, bg = self.sim.background(bg_id)
            origin, rot = self.pose_of(pose)
            t, prim, ng = caster.bvh.cast_with_normals(origin, self._rays_cam @ rot.T,
                                                       self.camera.max_depth)
            hit = prim >= 0
            cls = np.zeros(t.shape, np.uint8)
            inst = np.zeros(t.shape, np.int32)
            cls[hit] = bg.face_class[prim[hit]]
            inst[hit] = bg.face_instance[prim[hit]]
            depth = np.where(hit, t * self._rays_cam[:, 2], 0.0).astype(np.float32)
            street = _Street(Hits(t, np.full(t.shape, -1, np.int16), prim, ng), cls, inst,
                             depth)
            for a in (t, prim, ng, street.hits.owner, cls, inst, depth):
                a.setflags(write=False)
            return street
        return self._cached(self._streets, (bg_id, pose), make)

    def _shaded_street(self, bg_id: int, pose: SensorPose, look: Look) -> _Shaded:
        street = self._street(bg_id, pose)

        def make() -> _Shaded:
            h = street.hits
            everything = np.arange(len(h.t))
            rgb, lit, points = self._shade(bg_id, pose, [], [], h, everything, look)
            for a in (rgb, lit, points):
                a.setflags(write=False)
            return _Shaded(rgb, lit, points)
        return self._cached(self._shaded, (bg_id, pose, look), make)

    def window(self, car: PlacedCar, pose: SensorPose) -> np.ndarray:
        """Flat pixel indices whose rays can reach the car's bounding box."""
        _, corners = self.sim.car_caster(car.model)
        origin, rot = self.pose_of(pose)
        world = corners @ car.rotation().T + car.translation()
        pc = (world - origin) @ rot
        h, w = self.camera.shape
        if (pc[:, 2] <= MIN_DEPTH).all():
            return np.empty(0, np.int64)
        if (pc[:, 2] <= MIN_DEPTH).any():
            return np.arange(h * w)
        u, v, _ = self.camera.intrinsics.project(pc)
        c0, c1 = max(0, math.floor(u.min())), min(w - 1, math.floor(u.max()))
        r0, r1 = max(0, math.floor(v.min())), min(h - 1, math.floor(v.max()))
        if c0 > c1 or r0 > r1:
            return np.empty(0, np.int64)
        rows, cols = np.meshgrid(np.arange(r0, r1 + 1), np.arange(c0, c1 + 1), indexing="ij")
        return (rows * w + cols).ravel()

    def render(self, bg_id: int, placed: Sequence[PlacedCar], pose: SensorPose = SensorPose(),
               look: Look = Look(), paints: Sequence[tuple[float, float, float]] | None = None
               ) -> CameraImage:
        """The camera image of cars on a background; `paints` gives each car its own colour
        (default: every car in `look.colour`)."""
        street = self._street(bg_id, pose)
        base = street.hits
        hits = Hits(base.t.copy(), base.owner.copy(), base.prim.copy(), base.normal.copy())
        origin, rot = self.pose_of(pose)
        unoccluded = {}
        for k, car in enumerate(placed):
            idx = self.window(car, pose)
            if not len(idx):
                unoccluded[car.instance] = 0
                continue
            caster, _ = self.sim.car_caster(car.model)
            c_rot = car.rotation()
            dirs = self._rays_cam[idx] @ (c_rot.T @ rot).T
            t, prim, ng = caster.bvh.cast_with_normals((origin - car.translation()) @ c_rot, dirs,
                                                       self.camera.max_depth)
            unoccluded[car.instance] = int((prim >= 0).sum())
            nearer = (prim >= 0) & (t < hits.t[idx])
            sel = idx[nearer]
            hits.t[sel], hits.owner[sel], hits.prim[sel] = t[nearer], k, prim[nearer]
            hits.normal[sel] = ng[nearer]
        if paints is None:
            paints = [look.colour] * len(placed)
        on_car = np.flatnonzero(hits.owner >= 0)
        cls, inst, depth = street.cls.copy(), street.inst.copy(), street.depth.copy()
        owner = hits.owner[on_car]
        cls[on_car] = np.array([c.cls for c in placed], np.uint8)[owner]
        inst[on_car] = np.array([c.instance for c in placed], np.int32)[owner]
        depth[on_car] = hits.t[on_car] * self._rays_cam[on_car, 2]
        h, w = self.camera.shape
        if not self.incremental:
            rgb = self._shade(bg_id, pose, placed, paints, hits, np.arange(h * w), look)[0]
            return CameraImage(rgb.reshape(h, w, 3), cls.reshape(h, w), inst.reshape(h, w),
                               depth.reshape(h, w), unoccluded)
        shaded = self._shaded_street(bg_id, pose, look)
        redo = np.zeros(len(hits.t), bool)
        redo[on_car] = True
        if placed and len(shaded.points):
            sun_d = sun(look)[0]
            lit_px = np.flatnonzero(shaded.lit)
            for car in placed:  # street pixels whose sun ray passes a car's box
                _, corners = self.sim.car_caster(car.model)
                lo, hi = corners.min(axis=0), corners.max(axis=0)
                # First a cheap bound: the box's shadow reaches no further than its height
                # over the sun's slope beyond its footprint's circle.
                p = shaded.points
                reach = np.linalg.norm(hi[:2] - lo[:2]) / 2 + (hi[2] - lo[2] + 0.1) / max(
                    sun_d[2], 1e-3) * math.hypot(sun_d[0], sun_d[1])
                centre = car.translation()[:2] + car.rotation()[:2, :2] @ ((lo[:2] + hi[:2]) / 2)
                close = np.flatnonzero((p[:, 0] - centre[0]) ** 2 + (p[:, 1] - centre[1]) ** 2
                                       <= reach ** 2)
                c_rot = car.rotation()
                near = slab((p[close] - car.translation()) @ c_rot, sun_d @ c_rot, lo, hi)
                redo[lit_px[close[near]]] = True
        redo = np.flatnonzero(redo)
        rgb = shaded.rgb.copy()
        if len(redo):
            rgb[redo] = self._shade(bg_id, pose, placed, paints, hits, redo, look)[0]
        return CameraImage(rgb.reshape(h, w, 3), cls.reshape(h, w), inst.reshape(h, w),
                           depth.reshape(h, w), unoccluded)

    def render_sample(self, sample: Sample, pose: SensorPose = SensorPose()) -> CameraImage:
        """The camera image of a sample from the ego vehicle standing on the street, as its scan
        (InvalidSample for impossible scenes, as for scans)."""
        return self.render(sample.background, self.sim.placed_cars(sample),
                           self.sim.ego_pose(sample.background, pose), look_of(sample))

    def _shade(self, bg_id: int, pose: SensorPose, placed, paints, hits: Hits,
               idx: np.ndarray, look: Look) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """RGB (uint8) of pixels `idx`, which of them the sun lights, and those lit points."""
        caster, bg = self.sim.background(bg_id)
        origin, rot = self.pose_of(pose)
        sub = Hits(hits.t[idx], hits.owner[idx], hits.prim[idx], hits.normal[idx])

        def shadow_test(points: np.ndarray, sun_d: np.ndarray) -> np.ndarray:
            return shadowed(self, caster, placed, points, sun_d)
        return shade(self, bg, placed, paints, sub, self._rays_cam[idx] @ rot.T, origin,
                     rot[:, 2], look, self.streaks[idx], shadow_test)
