"""Synthetic cars inserted into real scans: the user's own streets as backgrounds.

A real scan (KITTI .bin, with SemanticKITTI labels or KITTI object boxes where present) is read
into the sensor's range image as `falsify predict` reads it. Every pixel of that image is a ray
from the scan's origin: along its real point when it holds one, else along the pixel's own
direction. A car stands on the scan's ground (a plane fitted to the ground points around it) and
the rays of the columns it spans are cast at its mesh by Embree. A ray that meets the car before
its real return takes the car's return (its label; its shade and dropout from the sensor's return
model, by the car's class where the model has classes, as the world's own cars), which hides the
real point behind it; a real point inside the car's body is removed; every other pixel keeps the
real scan's bytes, so a car beyond the range or outside the field of view leaves the scan as it
was. A car that would stand in a real object (a real car, a wall, a tree: at least
COLLISION_POINTS points of it inside the car's body) makes the sample invalid, never merged.

Weather and sensor faults (the effect dims) then act on every return of the scan, real or
inserted, per ray as falsify.sensor.weather acts on a cast scan: a return of range R (along its
ray) and stored intensity I (KITTI's remission, taken as range-compensated: received power
I / R^2, the module's units) is attenuated two-way, competes with the fog's soft echo and the
particles on its ray, and is kept where it reaches the detection floor; a recorded return was
detected, so its clear power is taken as at least the floor (and a stored remission of 0, below
KITTI's first step, as half that step: ZERO_REMISSION). A kept return keeps its point and
label and reports I attenuated; a spurious echo is a point on the same ray (label 0). The water
film darkens road, parking and sidewalk returns (SemanticKITTI ids; unlabelled scans: the points
near their cell's lowest, as for the ground) at their incidence on the scan's fitted ground
plane. Lasers out are the image's rows (laser rings), crosstalk its pixels. Ego motion is
refused on real scans (space.py), as is any effect on a spherical image, whose bins are not
the sensor's rays.
"""

from __future__ import annotations

import math
import zlib
from collections import OrderedDict
from dataclasses import replace
from typing import NamedTuple

import numpy as np

from falsify.data.real_backgrounds.background import RealBackground, read_background
from falsify.data.real_backgrounds.ground import (
    GROUND_IDS,
    IGNORED_IDS,
    fit_ground,
    lowest_band,
)
from falsify.data.real_backgrounds.normals import estimated_normals
from falsify.data.real_backgrounds.rays import column_azimuths, meets_box
from falsify.errors import ConfigError, FalsifyError
from falsify.semantic import RAW_NAMES, kitti4
from falsify.sensor.lidar import Sensor, SensorPose
from falsify.sensor.placement import placed_label
from falsify.sensor.raycast import cast_through
from falsify.sensor.returns import side_generator
from falsify.sensor.scan import Scan
from falsify.sensor.simulator import (
    FIRST_CAR_INSTANCE,
    InvalidSample,
    Obstacles,
    PlacedCar,
    Simulator,
    check_placement,
    check_surfaces,
    place,
)
from falsify.sensor.weather import (
    _RECORDED,
    NOMINAL_INTENSITY,
    Echoes,
    Effects,
    check_beams,
    effect_seed,
    effects_of,
    stream,
)
from falsify.world.materials import GLASS
from falsify.world.space import EFFECT_DIMS, RealScan, Sample, Space, UserCar

CLEARANCE_M = 0.25       # real points this far above the ground under a car are in its body
COLLISION_POINTS = 5     # obstacle points in a car's body that make the sample invalid
SURFACE_REACH_M = 0.75   # the ground points within this of an actor decide what it stands on
# What the ground an actor stands on counts as, by SemanticKITTI ids (`[dims.actor] on`).
SURFACE_IDS = {"road": np.array([40, 44, 60]), "sidewalk": np.array([48]),
               "terrain": np.array([49, 72])}
INSERTED_INSTANCE = 1 << 16   # instance ids of inserted cars: above SemanticKITTI's 16 bits
WET_IDS = np.array([40, 44, 48])   # road, parking, sidewalk: what a water film lies on
# KITTI stores remission in steps of 0.01, and some 12 % of a scan's points (a third of some
# real cars') at 0: the sensor saw them, below its first step. Deciding what fog leaves, such a
# return is taken as half a step (its intensity reported stays 0).
ZERO_REMISSION = 0.005
PLANE_REACH_M = 30.0     # the scan's ground plane (incidence on a wet road) is fitted this far


class CarHits(NamedTuple):
    """The cars' nearest hit per flat pixel of the image (`RealScanner._cast_cars`)."""

    t: np.ndarray       # range along the pixel's ray (inf: no car)
    car: np.ndarray     # index of the placed car hit (-1: none)
    material: np.ndarray
    cos: np.ndarray     # |cosine| of the ray to the hit face's normal
    px: np.ndarray      # the pixels hit, sorted


class RealScanner:
    """Scans of samples whose backgrounds are real scans: the Scanner a space with
    `[dims.background] real = [...]` runs on. Car meshes and the return model come from a
    Simulator of the same sensor; `max_backgrounds` read scans are kept."""

    def __init__(self, sensor: Sensor, backgrounds: tuple[RealScan, ...],
                 user_cars: dict[str, UserCar] | None = None, lod: int = 2,
                 max_backgrounds: int = 16, surfaces: tuple[str, ...] = ()):
        self.sensor = sensor
        self.real = backgrounds
        self.sim = Simulator(sensor, user_cars, lod=lod)
        self.surfaces = surfaces   # per placed object, where it must stand (Space.surfaces)
        self._bg: OrderedDict[int, RealBackground] = OrderedDict()
        self._boxes: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray, float]] = {}
        # (background, car) of the last placed_cars whose body holds no point of the cloud
        self._empty_bodies: set[tuple[int, PlacedCar]] = set()
        self._max = max_backgrounds
        self._columns = column_azimuths(sensor)
        self._keep = (self.sim.returns.keep_map(sensor.rows, sensor.azimuths_deg)
                      if self.sim.returns is not None and sensor.projection == "rings" else None)

    def background(self, bg_id: int) -> RealBackground:
        """The real scan of background `bg_id`, read once and kept (least recently used go)."""
        if bg_id in self._bg:
            self._bg.move_to_end(bg_id)
            return self._bg[bg_id]
        if not 0 <= bg_id < len(self.real):
            raise FalsifyError(f"background {bg_id}: the space has {len(self.real)} real scans")
        bg = read_background(self.real[bg_id], self.sensor)
        self._bg[bg_id] = bg
        while len(self._bg) > self._max:
            self._bg.popitem(last=False)
        return bg

    def ego_pose(self, bg_id: int, pose: SensorPose = SensorPose()) -> SensorPose:
        """A real scan is seen from where it was recorded: the sensor frame is the world's."""
        return SensorPose()

    def background_hits(self, bg_id: int, pose: SensorPose = SensorPose()) -> RealBackground:
        return self.background(bg_id)

    # -- cars ------------------------------------------------------------------------------
    def placed_cars(self, sample: Sample) -> list[PlacedCar]:
        """The sample's cars standing on the real ground, or InvalidSample naming what a car
        would intersect: the ego car, another car, or a real object of the scan."""
        bg = self.background(sample.background)
        placed = [replace(place(c, FIRST_CAR_INSTANCE + i), cls=self.sim.model_class(c.model))
                  for i, c in enumerate(sample.cars)]
        check_placement(placed, [self.sim.footprint(c) for c in placed], Obstacles.of(()))
        check_surfaces(placed, self.surfaces, lambda x, y: self.surface(bg, x, y))
        settled = [self.settle(bg, c) for c in placed]
        self._empty_bodies = set()
        for i, car in enumerate(settled):
            if self.check_collision(bg, car, i + 1) == 0:
                self._empty_bodies.add((id(bg), car))
        return settled

    def surface(self, bg: RealBackground, x: float, y: float) -> str:
        """What the scan's labels say the ground at (x, y) is: the most common of road (road,
        parking, lane marking), sidewalk and other ground among the ground points within
        SURFACE_REACH_M; "unlabelled ground" where none lies there."""
        rows = bg.cloud.near(x, y, SURFACE_REACH_M)
        if bg.cloud.semantic is None or not len(rows):
            return "unlabelled ground"
        p = bg.cloud.points[rows]
        sem = bg.cloud.semantic[rows][np.hypot(p[:, 0] - x, p[:, 1] - y) <= SURFACE_REACH_M]
        votes = {name: int(np.isin(sem, ids).sum()) for name, ids in SURFACE_IDS.items()}
        best = max(votes, key=lambda k: votes[k])
        return best if votes[best] else "unlabelled ground"

    def _box(self, car: PlacedCar) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
        """The car model's bounding box in its own frame: lowest and highest corner, the eight
        corners, and how far the farthest is from the car's origin."""
        if car.model not in self._boxes:
            _, corners = self.sim.car_caster(car.model)
            lo, hi = corners.min(axis=0), corners.max(axis=0)
            self._boxes[car.model] = (lo, hi, corners,
                                      float(np.linalg.norm(np.maximum(np.abs(lo), np.abs(hi)))))
        return self._boxes[car.model]

    def settle(self, bg: RealBackground, car: PlacedCar) -> PlacedCar:
        """The car on the scan's ground plane under it: height, pitch and roll (as
        falsify.world.terrain.Terrain.pose_on: positive pitch tilts the nose down, positive
        roll lifts the left side)."""
        lo, hi, _, _ = self._box(car)
        reach = float(np.hypot(*np.maximum(np.abs(lo[:2]), np.abs(hi[:2]))))
        z, gx, gy = fit_ground(bg.ground, car.x, car.y, reach, -self.sensor.mount_height)
        h = math.radians(car.heading_deg)
        fx, fy = math.cos(h), math.sin(h)
        pitch = math.degrees(math.atan(-(gx * fx + gy * fy)))
        roll = math.degrees(math.atan(-gx * fy + gy * fx))
        return replace(car, z=z, pitch_deg=pitch, roll_deg=roll)

    def reach(self, car: PlacedCar) -> float:
        """How far from its origin any part of the car's bounding box is, at most."""
        return self._box(car)[3]

    def body_points(self, xyz: np.ndarray, car: PlacedCar) -> np.ndarray:
        """Bool per point: inside the car's bounding box and at least CLEARANCE_M above the
        ground it stands on."""
        lo, hi, _, _ = self._box(car)
        reach = self.reach(car)
        near = ((np.abs(xyz[:, 0] - car.x) <= reach) & (np.abs(xyz[:, 1] - car.y) <= reach))
        out = np.zeros(len(xyz), bool)
        idx = np.flatnonzero(near)
        local = (xyz[idx].astype(np.float64) - car.translation()) @ car.rotation()
        out[idx] = ((local[:, 0] >= lo[0]) & (local[:, 0] <= hi[0]) & (local[:, 1] >= lo[1])
                    & (local[:, 1] <= hi[1]) & (local[:, 2] >= CLEARANCE_M)
                    & (local[:, 2] <= hi[2]))
        return out

    def check_collision(self, bg: RealBackground, car: PlacedCar, number: int) -> int:
        """InvalidSample if COLLISION_POINTS or more obstacle points of the scan (any point but
        ground, unlabeled and outliers where every point is labelled; any point otherwise) lie in
        the car's body; else how many points of any kind lie there."""
        rows = bg.cloud.near(car.x, car.y, self.reach(car))
        inside = self.body_points(bg.cloud.points[rows], car)
        in_body = int(inside.sum())
        sem = None if bg.cloud.semantic is None else bg.cloud.semantic[rows][inside]
        if bg.dense:
            sem = sem[~np.isin(sem, np.concatenate([GROUND_IDS, IGNORED_IDS]))]
        n = in_body if sem is None else len(sem)
        if n < COLLISION_POINTS:
            return in_body
        what = "points"
        named = sem if sem is not None else np.empty(0, np.uint16)
        named = named[named > 1]
        if len(named):
            ids, counts = np.unique(named, return_counts=True)
            what = RAW_NAMES.get(int(ids[np.argmax(counts)]), "object")
        raise InvalidSample(f"{placed_label(car, number)} intersects the real scan's {what} "
                            f"({n} points in its body)")

    # -- casting ---------------------------------------------------------------------------
    def columns(self, car: PlacedCar) -> np.ndarray:
        """The image columns whose rays can reach the car's bounding box (one column of margin
        either side: a real point's azimuth strays within its column)."""
        world = self._box(car)[2] @ car.rotation().T + car.translation()
        az = np.sort(np.degrees(np.arctan2(world[:, 1], world[:, 0])))
        gaps = np.diff(np.concatenate([az, [az[0] + 360.0]]))
        k = int(np.argmax(gaps))
        if gaps[k] <= 180.0:   # the origin is inside the box's outline
            return np.arange(self.sensor.columns)
        start, span = az[(k + 1) % len(az)], 360.0 - gaps[k]
        step = 360.0 / self.sensor.columns if self.sensor.projection == "spherical" else abs(
            self.sensor.az_step_deg)
        rel = (self._columns - start + step) % 360.0
        return np.flatnonzero(rel <= span + 2 * step)

    def rows(self, bg: RealBackground, car: PlacedCar) -> np.ndarray:
        """The image rows holding a ray whose elevation can reach the car's bounding box, from
        the box's nearest and farthest distance and its height (with every ray's origin)."""
        lo, hi, corners, _ = self._box(car)
        p = corners @ car.rotation().T + car.translation()
        local = -car.translation() @ car.rotation()   # the sensor origin in the car's frame
        start = bg.origin_reach
        d_min = float(np.linalg.norm(local - np.clip(local, lo, hi))) - start
        d_max = float(np.linalg.norm(p, axis=1).max()) + start
        all_rows = np.arange(self.sensor.rows)
        if d_min <= 1e-9:
            return all_rows
        z_lo, z_hi = p[:, 2].min() - start, p[:, 2].max() + start
        el_hi = math.asin(min(1.0, z_hi / d_min)) if z_hi > 0 else math.asin(z_hi / d_max)
        el_lo = math.asin(max(-1.0, z_lo / d_min)) if z_lo < 0 else math.asin(z_lo / d_max)
        eps = 1e-9
        return all_rows[(bg.row_elevation[:, 1] >= el_lo - eps)
                        & (bg.row_elevation[:, 0] <= el_hi + eps)]

    def placed_pixels(self, scan: Scan) -> np.ndarray:
        """The pixels of the inserted objects, not the scan's own."""
        return scan.instance >= INSERTED_INSTANCE

    def scan(self, sample: Sample, pose: SensorPose = SensorPose(),
             rng: np.random.Generator | None = None) -> Scan:
        """The real scan with the sample's cars inserted; InvalidSample for impossible ones."""
        bg = self.background(sample.background)
        placed = self.placed_cars(sample)
        effects = effects_of(sample)
        if effects.clear:
            return self.insert(bg, placed, rng)
        refuse_effects(self.sensor, [n for n, _ in sample.effects])
        # As Simulator.scan: the effects' seed fixed by the sample and the generator's state,
        # read before the scan's own draws without drawing.
        seed = effect_seed(rng, zlib.crc32(repr(sample.lidar_values).encode()))
        return self.weather(bg, self.insert(bg, placed, rng), effects, seed, rng is not None)

    def weather(self, bg: RealBackground, scan: Scan, fx: Effects, seed: int,
                dropouts: bool = True) -> Scan:
        """The scan (cars inserted) with weather and faults on each of its returns, per ray as
        Weather acts on a cast scan (the module's docstring). Where `dropouts` and the sensor has
        a return model, an echo the weather weakened is kept with the ratio of the model's return
        probabilities, weathered to clear (the recorded echo was seen once: the same draw decides
        again), and a spurious echo with the model's probability; draws from the effects' seed."""
        w = self.sim.weather
        img = scan.image
        valid = scan.valid
        r = np.full(valid.shape, np.inf)
        r[valid] = np.linalg.norm(img[valid, 0:3].astype(np.float64) - bg.origin[valid], axis=-1)
        clear_i = np.where(valid, img[..., 3], np.float32(0.0))
        e = Echoes(r, valid, clear_i, img[..., 5], scan.instance, scan.semantic)
        if fx.ego_speed:   # as on our streets, the surface from the scan's own neighbours
            normal, cos = estimated_normals(img[..., 0:3], valid, bg.origin, bg.direction)
            e = replace(e, r=np.where(valid, w.moving_ranges(r, normal, cos, fx.ego_speed), r))
        if fx.medium:
            ground = cos = None
            if fx.wet_road > 0:
                ground, cos = self.wet_ground(bg, scan)
            # What decides detection: at least the floor (the return was recorded; a hair
            # above, so that rounding never drops a return nothing weakened), and a stored
            # remission of 0 (below KITTI's first step) taken as half a step.
            at_floor = w.floor * (1.0 + 1e-9) * np.where(valid, r, 0.0) ** 2
            least = np.where(valid, np.maximum(at_floor,
                                               np.where(clear_i > 0, 0.0, ZERO_REMISSION)), 0.0)
            e, spurious = w.through(fx, seed, e, clear_i, ground, cos, least)
            returns = self.sim.returns
            if dropouts and returns is not None:
                now = returns.p_return(e.intensity)
                keep = np.where(spurious, now, now / returns.p_return(clear_i))
                if self._keep is not None:
                    keep = np.where(spurious, keep * self._keep, keep)
                e.valid = e.valid & (stream(seed, _RECORDED).random(r.shape) < keep)
        if fx.crosstalk or fx.beam_loss or fx.beams:
            e = w.faults(fx, seed, e)
        ok = e.valid
        moved = ok & (~valid | (e.r != r))   # an echo at another range: a new point on the ray
        image = np.where(ok[..., None], img, np.float32(0.0))
        image[..., 3] = np.where(ok, e.intensity, np.float32(0.0))
        image[..., 5] = np.where(ok, e.cls, 0)
        xyz = (bg.origin[moved] + bg.direction[moved] * e.r[moved][:, None]).astype(np.float32)
        image[moved, 0:3] = xyz
        image[moved, 4] = np.linalg.norm(xyz.astype(np.float64), axis=1)
        inst = np.where(ok, e.inst, 0).astype(np.int32)
        sem = None if e.semantic is None else np.where(ok, e.semantic, 0).astype(np.uint16)
        return Scan(image, inst, sem)

    def wet_ground(self, bg: RealBackground, scan: Scan) -> tuple[np.ndarray, np.ndarray]:
        """(wet pixels, incidence cosine per pixel): the real returns from road, parking or
        sidewalk (SemanticKITTI ids; without them: points within LOWEST_BAND_M of their cell's
        lowest point, not in a labelled object, below the sensor by more than half its height),
        and each ray's cosine to the normal of the ground plane fitted around the sensor."""
        real = scan.valid & (scan.instance < INSERTED_INSTANCE)
        if bg.dense and scan.semantic is not None:
            ground = real & np.isin(scan.semantic, WET_IDS)
        else:
            xyz = scan.image[..., 0:3]
            ground = real & lowest_band(bg.cloud.points, xyz.reshape(-1, 3)).reshape(real.shape)
            ground &= xyz[..., 2] < -0.5 * self.sensor.mount_height
            if scan.semantic is not None:
                ground &= scan.semantic == 0
        _, gx, gy = fit_ground(bg.ground, 0.0, 0.0, PLANE_REACH_M, -self.sensor.mount_height)
        normal = np.array([-gx, -gy, 1.0]) / math.sqrt(gx * gx + gy * gy + 1.0)
        return ground, np.abs(bg.direction @ normal)

    def insert(self, bg: RealBackground, placed: list[PlacedCar],
               rng: np.random.Generator | None = None) -> Scan:
        """Cast each car at the rays of its columns; the nearest car hit per pixel replaces the
        real return behind it; then the sensor's return model decides each car hit (glass
        never returns) and real points left inside a car's body go."""
        s = self.sensor
        w = s.shape[1]
        spans = [(self.rows(bg, car), self.columns(car)) for car in placed]
        hit_t, hit_car, hit_mat, hit_cos, px = self._cast_cars(bg, placed, spans)
        emptied = []
        for car, (rows, cols) in zip(placed, spans, strict=True):   # real points in its body
            if (id(bg), car) in self._empty_bodies:   # placed_cars found none in the cloud
                continue
            window = (rows[:, None] * w + cols[None, :]).ravel()
            window = window[bg.valid.ravel()[window] & (hit_car[window] < 0)]
            inside = self.body_points(bg.scan.image.reshape(-1, 6)[window, 0:3], car)
            emptied.append(window[inside])
        t = hit_t[px]
        mat = hit_mat[px]
        if rng is not None and s.range_noise > 0:
            t = t + rng.normal(0.0, s.range_noise, t.shape)
        car_sem = np.array([self.sim.car_semantic(c) for c in placed], np.uint16)[hit_car[px]]
        model = self.sim.returns
        returns = ~GLASS[mat] if model is not None else np.ones(len(t), bool)
        intensity = np.full(len(t), NOMINAL_INTENSITY, np.float32)
        if model is not None:   # shaded and dropped as the world's own cars are
            draws = None if rng is None or model.classes is None else side_generator(rng)
            intensity = model.intensity(mat, hit_cos[px], t, car_sem,
                                        INSERTED_INSTANCE + hit_car[px], draws)
            if rng is not None:
                p = model.return_probability(intensity, car_sem)
                if self._keep is not None:
                    p = p * self._keep.ravel()[px]
                returns &= rng.random(len(t)) < p
        emptied.append(px[~returns])
        px, t, intensity, car_sem = px[returns], t[returns], intensity[returns], car_sem[returns]
        image = bg.scan.image.copy()
        inst = bg.scan.instance.copy()
        sem = None if bg.scan.semantic is None else bg.scan.semantic.copy()
        gone = np.concatenate(emptied)
        image.reshape(-1, 6)[gone] = 0.0
        inst.ravel()[gone] = 0
        if sem is not None:
            sem.ravel()[gone] = 0
        xyz = (bg.origin.reshape(-1, 3)[px] + bg.direction.reshape(-1, 3)[px] * t[:, None]
               ).astype(np.float32)
        flat = image.reshape(-1, 6)
        flat[px, 0:3] = xyz
        flat[px, 3] = intensity
        flat[px, 4] = np.linalg.norm(xyz.astype(np.float64), axis=1)
        flat[px, 5] = kitti4(car_sem)
        inst.ravel()[px] = INSERTED_INSTANCE + hit_car[px]
        if sem is not None:
            sem.ravel()[px] = car_sem
        return Scan(image, inst, sem)

    def _cast_cars(self, bg: RealBackground, placed: list[PlacedCar],
                   spans: list[tuple[np.ndarray, np.ndarray]]) -> CarHits:
        """Each car cast at the rays of its (rows, columns) span, nearer than the real return
        and any car cast before: per flat pixel the nearest hit's range, car, material and
        incidence cosine, and the pixels hit (sorted)."""
        s = self.sensor
        h, w = s.shape
        hit_t = np.full(h * w, np.inf)   # flat pixel index -> nearest car hit so far
        hit_car = np.full(h * w, -1, np.int64)
        hit_mat = np.zeros(h * w, np.uint8)
        hit_cos = np.zeros(h * w, np.float32)
        hit_px: list[np.ndarray] = []
        for k, car in enumerate(placed):
            rows, cols = spans[k]
            if len(cols) == 0 or len(rows) == 0:
                continue
            px = (rows[:, None] * w + cols[None, :]).ravel()
            caster, _ = self.sim.car_caster(car.model)
            rot = car.rotation()
            start = bg.origin.reshape(-1, 3)[px] if bg.origin_reach else np.zeros((1, 3))
            o = np.broadcast_to((start - car.translation()) @ rot, (len(px), 3))
            d = bg.direction.reshape(-1, 3)[px] @ rot
            limit = np.minimum(bg.dist.ravel()[px], hit_t[px])
            near = meets_box(o, d, limit, *self._box(car)[:2])
            if not near.any():
                continue
            px, o, d, limit = px[near], o[near], d[near], limit[near]
            t, prim = cast_through(caster.bvh, o, d, limit, caster.face_pass, px, 0)
            ok = (prim >= 0) & (t < limit) & (t >= s.min_range)
            pn = prim[ok]
            px = px[ok]
            hit_t[px] = t[ok]
            hit_car[px] = k
            hit_mat[px] = caster.material[pn]
            hit_cos[px] = np.abs((caster.normals[pn] * d[ok]).sum(axis=1))
            hit_px.append(px)
        # One car's pixels are in row-major order already; several cars' may overlap.
        px = (hit_px[0] if len(hit_px) == 1 else np.unique(np.concatenate(hit_px)) if hit_px
              else np.empty(0, np.int64))
        return CarHits(hit_t, hit_car, hit_mat, hit_cos, px)



def refuse_effects(sensor: Sensor, names) -> None:
    """ConfigError naming the first effect dim of `names` when the sensor stores its scans in a
    spherical image: its bins are not the sensor's rays (an empty bin may be no ray at all, and a
    row is no laser), so the effects have no ray to act on."""
    names = list(names)
    if names and sensor.projection == "spherical":
        raise ConfigError(f"dims.{names[0]}: weather and sensor faults on a real background act "
                          f"on the sensor's rays; {sensor.name} stores scans in a spherical "
                          "image whose bins are not its rays (use a sensor with the rings "
                          "layout, e.g. kitti-hdl64e-front, or drop the dim)")



def scanner_for(space: Space, sensor: Sensor | None = None, lod: int = 2):
    """The scanner a space's samples are cast with: a RealScanner over its real backgrounds,
    else a Simulator of its streets."""
    from falsify.sensor.lidar import load_sensor
    sensor = sensor or load_sensor(space.sensor)
    check_beams(space, sensor)
    if space.real_backgrounds:
        try:
            refuse_effects(sensor, [n for n in EFFECT_DIMS if n in space.dims])
        except ConfigError as exc:
            raise ConfigError(f"{space.source}: {exc}") from None
        return RealScanner(sensor, space.real_backgrounds, space.user_cars, lod=lod,
                           surfaces=space.surfaces)
    return Simulator(sensor, space.user_cars, lod=lod, surfaces=space.surfaces,
                     background_source=space.background_source())
