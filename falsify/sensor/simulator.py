"""Scenes from samples, cast into scans: background hits cached per pose, cars cast in a window.

The background never changes inside a run, so its BVH is built once and every sensor ray is cast
at it once per (background, sensor pose). A sampled car covers a small window of the range image:
only the rays inside the window of its bounding box are moved into the car's own frame and cast
at the car's BVH, and the nearer hit wins per pixel. That gives exactly the first returns of the
merged scene (tests compare against a full re-cast). A sample's weather and sensor faults
(falsify.sensor.weather) act on those first hits per ray, after casting, so the caches hold.
"""

from __future__ import annotations

import ctypes
import math
import zlib
from collections import OrderedDict
from collections.abc import Callable, Sequence
from dataclasses import replace

import numpy as np

import falsify.world.actors as actors
import falsify.world.cars as cars
import falsify.world.road_users as road_users
import falsify.world.streets as streets
from falsify.classes import CAR
from falsify.semantic import kitti4
from falsify.sensor.hits import Caster, HitLayer
from falsify.sensor.lidar import Sensor, SensorPose
from falsify.sensor.placement import (
    EGO_FOOTPRINT,
    EGO_X_BACKWARD,
    EGO_X_FORWARD,
    Obstacles,
    check_placement,
    check_surfaces,
    free_ego,
)
from falsify.sensor.raycast import cast_through
from falsify.sensor.returns import load_return_model, side_generator
from falsify.sensor.scan import Scan, project_scan
from falsify.sensor.scanner import FIRST_CAR_INSTANCE, InvalidSample, PlacedCar, Scanner, place
from falsify.sensor.weather import (
    NOMINAL_INTENSITY,
    Echoes,
    Effects,
    Weather,
    effect_seed,
    effects_of,
)
from falsify.world.materials import GLASS, PAINTS, mid
from falsify.world.space import Sample, UserCar
from falsify.world.street_layout import FIRST_STREET_INSTANCE
from falsify.world.terrain import Terrain

# The scanner's and placement's names callers import from here stay importable from here.
__all__ = [
    "EGO_X_BACKWARD", "EGO_X_FORWARD", "FIRST_CAR_INSTANCE", "InvalidSample", "Obstacles",
    "PAINT_IDS", "PlacedCar", "Scanner", "Simulator", "check_placement", "check_surfaces",
    "free_ego", "place", "porosity_seed", "release_free_heap",
]
PAINT_IDS = np.array(PAINTS, dtype=np.uint8)


def release_free_heap() -> None:
    """Hand the heap pages freed since the last call back to the OS (glibc's malloc_trim; a no-op
    elsewhere). Building a street leaves tens of MB of freed temporaries that glibc would keep
    in every worker for the rest of the run."""
    global _MALLOC_TRIM
    if _MALLOC_TRIM is None:
        try:
            _MALLOC_TRIM = ctypes.CDLL("libc.so.6").malloc_trim
        except (OSError, AttributeError):
            _MALLOC_TRIM = False
    if _MALLOC_TRIM:
        _MALLOC_TRIM(0)


_MALLOC_TRIM = None


def porosity_seed(bg_id: int) -> int:
    """The seed of a background's pass-through decisions (fixed per street, so cached hits and a
    full re-cast agree)."""
    return 0x5EED0000 + int(bg_id)



class Simulator:
    """Holds the expensive state (BVHs, background hits) warm across many samples.

    `background_source` builds a background from its id (default: the procedural streets);
    `max_bvh` backgrounds' BVHs and `max_hits` cached (background, pose) casts are kept;
    `surfaces` says per placed object where it must stand ("any", "road", "sidewalk")."""

    def __init__(self, sensor: Sensor, user_cars: dict[str, UserCar] | None = None,
                 lod: int = 2, max_bvh: int = 2, max_hits: int = 256,
                 background_source: Callable[[int], streets.Background] | None = None,
                 surfaces: tuple[str, ...] = ()):
        self.sensor = sensor
        self.surfaces = surfaces   # per placed object k, where it must stand (Space.surfaces)
        self.user_cars = dict(user_cars or {})
        self.lod = lod
        self._bvh: OrderedDict[int, tuple[Caster, object]] = OrderedDict()
        self._hits: OrderedDict[tuple, HitLayer] = OrderedDict()
        self._cars: dict[str, tuple[Caster, np.ndarray]] = {}
        self._obstacles: dict[int, Obstacles] = {}
        self._terrain: dict[int, Terrain | None] = {}
        self._ego_offset: dict[int, tuple[float, float, float]] = {}   # pitch, dz, dy
        self._kerbs_stop: dict[int, bool] = {}
        self._max_bvh, self._max_hits = max_bvh, max_hits
        self.background_source = background_source or streets.build_background
        self.returns = load_return_model(sensor.returns) if sensor.returns else None
        self._keep = (None if self.returns is None else
                      self.returns.keep_map(sensor.rows, sensor.azimuths_deg))
        self.weather = Weather(sensor, self.returns)

    # -- meshes ---------------------------------------------------------------------------
    def car_mesh(self, model: str):
        """A model as a trimesh mesh, for the naive paths and users (imports trimesh)."""
        if model in self.user_cars:
            u = self.user_cars[model]
            return cars.load_user_car(u.file, u.scale, u.forward, u.up, u.key)
        if model in road_users.OTHER_VEHICLES or model in actors.BUILTIN_ACTORS:
            import trimesh

            return trimesh.Trimesh(*self.car_arrays(model), process=False)
        return cars.car_mesh(model, lod=self.lod)

    def car_arrays(self, model: str) -> tuple[np.ndarray, np.ndarray]:
        """A model's vertices and faces in its own frame; built-in models without trimesh,
        so that a worker that casts only them never imports it."""
        if model in self.user_cars:
            mesh = self.car_mesh(model)
            return np.asarray(mesh.vertices), np.asarray(mesh.faces)
        if model in road_users.OTHER_VEHICLES:
            return road_users.vehicle_model(model)[:2]
        if model in actors.BUILTIN_ACTORS:
            return actors.actor_model(model)[:2]
        v, f, _ = cars.car_parts(model, self.lod)
        return v, f

    def car_materials(self, model: str) -> np.ndarray:
        """Per-face materials of a model (user meshes: mid paint everywhere)."""
        if model in self.user_cars:
            return np.full(len(self.car_arrays(model)[1]), mid("paint mid"), np.uint8)
        if model in road_users.OTHER_VEHICLES:
            return road_users.vehicle_model(model)[2]
        if model in actors.BUILTIN_ACTORS:
            return actors.actor_model(model)[2]
        return cars.car_parts(model, self.lod)[2]

    def car_semantic(self, car: PlacedCar) -> int:
        """The raw SemanticKITTI id a placed object's points carry (model_semantic)."""
        return self.model_semantic(car.model)

    def model_semantic(self, model: str) -> int:
        """The raw SemanticKITTI id of a model's points (actors.model_semantic)."""
        return actors.model_semantic(model, self.user_cars)

    def model_class(self, model: str) -> int:
        """A model's class in the four-class view: kitti4 of its id, but car for the other
        vehicles' model names (traffic and training scenes count what they place as car)."""
        if (model in road_users.OTHER_VEHICLES and model not in self.user_cars
                and model not in actors.BUILTIN_ACTORS):
            return CAR
        return int(kitti4(np.array([self.model_semantic(model)]))[0])

    def car_caster(self, model: str) -> tuple[Caster, np.ndarray]:
        """The car's BVH in its own frame and its bounding box corners (8×3)."""
        if model not in self._cars:
            v, f = self.car_arrays(model)
            used = v[np.unique(f)]     # trimesh's bounds: of the vertices faces reference
            lo, hi = used.min(axis=0), used.max(axis=0)
            corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                                for z in (lo[2], hi[2])])
            self._cars[model] = (Caster.of(v, f, self.car_materials(model),
                                            anchor=np.zeros(3)), corners)
        return self._cars[model]

    def background(self, bg_id: int):
        """The background and its BVH (a few kept, least recently used dropped)."""
        if bg_id in self._bvh:
            self._bvh.move_to_end(bg_id)
            return self._bvh[bg_id]
        bg = self.background_source(bg_id)
        entry = (Caster.of(bg.vertices, bg.faces, bg.materials()), bg)
        self._obstacles[bg_id] = Obstacles.of(bg.obstacles)
        self._terrain[bg_id] = bg.terrain
        self._ego_offset[bg_id] = (float(getattr(bg, "ego_pitch_deg", 0.0)),
                                   float(getattr(bg, "ego_dz", 0.0)),
                                   float(getattr(bg, "ego_dy", 0.0)))
        self._kerbs_stop[bg_id] = bool(getattr(bg, "kerbs_stop_cars", True))
        self._bvh[bg_id] = entry
        while len(self._bvh) > self._max_bvh:
            self._bvh.popitem(last=False)
        release_free_heap()
        return entry

    # -- casting --------------------------------------------------------------------------
    def background_hits(self, bg_id: int, pose: SensorPose) -> HitLayer:
        """Every sensor ray cast at the background once per (background, pose), then cached."""
        key = (bg_id, pose)
        if key in self._hits:
            self._hits.move_to_end(key)
            return self._hits[key]
        caster, bg = self.background(bg_id)
        rot = pose.rotation(self.sensor)
        dirs = self.sensor.directions.reshape(-1, 3) @ rot.T
        t, prim = cast_through(caster.bvh, self.ray_starts(pose, rot), dirs,
                               self.sensor.max_range, caster.face_pass,
                               np.arange(len(dirs)), porosity_seed(bg_id))
        hit = prim >= 0
        cls = np.zeros(t.shape, dtype=np.uint8)
        inst = np.zeros(t.shape, dtype=np.int32)
        mat = np.zeros(t.shape, dtype=np.uint8)
        cos = np.zeros(t.shape, dtype=np.float32)
        normal = np.zeros((len(t), 3), dtype=np.float32)
        sem = np.zeros(t.shape, dtype=np.uint16)
        cls[hit] = bg.face_class[prim[hit]]
        inst[hit] = bg.face_instance[prim[hit]]
        sem[hit] = bg.semantics()[prim[hit]]
        mat[hit] = caster.material[prim[hit]]
        facing = (caster.normals[prim[hit]] * dirs[hit]).sum(axis=1)
        cos[hit] = np.abs(facing)
        # World to sensor frame, turned towards the sensor.
        normal[hit] = (caster.normals[prim[hit]] @ rot) * np.where(facing > 0, -1.0, 1.0)[:, None]
        shape = self.sensor.shape
        layer = HitLayer(t.reshape(shape), cls.reshape(shape), inst.reshape(shape),
                       mat.reshape(shape), cos.reshape(shape), normal.reshape(*shape, 3),
                       sem.reshape(shape))
        for a in (layer.dist, layer.cls, layer.inst, layer.mat, layer.cos, layer.normal,
                  layer.semantic):
            a.setflags(write=False)
        self._hits[key] = layer
        while len(self._hits) > self._max_hits:
            self._hits.popitem(last=False)
        return layer

    def ray_starts(self, pose: SensorPose, rot: np.ndarray,
                   rows: np.ndarray | None = None) -> np.ndarray:
        """World start of each ray: the sensor origin (3,) when every ray starts there, else
        (n, 3) for the rays of `rows` (each ray's row; all rays, row-major, when None)."""
        origin = pose.origin(self.sensor)
        if self.sensor.ray_origins is None:
            return origin
        per_row = origin + self.sensor.ray_origins[:, 0, :] @ rot.T
        if rows is None:
            return np.repeat(per_row, self.sensor.columns, axis=0)
        return per_row[rows]

    def window(self, car: PlacedCar, pose: SensorPose) -> tuple[np.ndarray, np.ndarray]:
        """Rows and columns whose rays can reach the car's bounding box (may be empty). With
        per-row ray origins (offset along the sensor's z only, so azimuths do not change) the
        elevation bounds widen to hold from any of them."""
        _, corners = self.car_caster(car.model)
        s_rot = pose.rotation(self.sensor)
        world = corners @ car.rotation().T + car.translation()
        p = (world - pose.origin(self.sensor)) @ s_rot  # corners in the sensor frame
        # Distance from the sensor to the box, in the car frame where the box is axis-aligned.
        local = (pose.origin(self.sensor) - car.translation()) @ car.rotation()
        lo, hi = corners.min(axis=0), corners.max(axis=0)
        offsets = self.sensor.ring_offsets_m or (0.0,)
        reach = max(abs(v) for v in offsets)
        d_min = float(np.linalg.norm(local - np.clip(local, lo, hi))) - reach
        d_max = float(np.linalg.norm(p, axis=1).max()) + reach
        if d_min > self.sensor.max_range:
            return np.empty(0, np.int64), np.empty(0, np.int64)
        all_rows = np.arange(self.sensor.rows)
        all_cols = np.arange(self.sensor.columns)
        if d_min <= 1e-9:
            return all_rows, all_cols
        z_lo, z_hi = p[:, 2].min() - max(offsets), p[:, 2].max() - min(offsets)
        el_hi = math.asin(min(1.0, z_hi / d_min)) if z_hi > 0 else math.asin(z_hi / d_max)
        el_lo = math.asin(max(-1.0, z_lo / d_min)) if z_lo < 0 else math.asin(z_lo / d_max)
        el = np.radians(np.asarray(self.sensor.elevations_deg))
        eps = 1e-9
        rows = all_rows[(el >= el_lo - eps) & (el <= el_hi + eps)]
        # Azimuth: the arc the corners span is the complement of the largest gap between them.
        az = np.sort(np.degrees(np.arctan2(p[:, 1], p[:, 0])))
        gaps = np.diff(np.concatenate([az, [az[0] + 360.0]]))
        k = int(np.argmax(gaps))
        if gaps[k] <= 180.0:  # the sensor is inside the box's outline: every column
            return rows, all_cols
        start = az[(k + 1) % len(az)]  # arc runs counter-clockwise from start by span
        span = 360.0 - gaps[k]
        rel = (self.sensor.azimuths_deg - start) % 360.0
        cols = all_cols[(rel <= span + eps) | (rel >= 360.0 - eps)]
        return rows, cols

    def cast_car(self, layer: HitLayer, car: PlacedCar, pose: SensorPose) -> int:
        """Cast the car's window rays at its BVH and keep the nearer hits; returns rays cast."""
        rows, cols = self.window(car, pose)
        if len(rows) == 0 or len(cols) == 0:
            return 0
        caster, _ = self.car_caster(car.model)
        r_idx, c_idx = np.meshgrid(rows, cols, indexing="ij")
        r_idx, c_idx = r_idx.ravel(), c_idx.ravel()
        s_rot = pose.rotation(self.sensor)
        c_rot = car.rotation()
        to_car = c_rot.T @ s_rot   # sensor frame to the car's
        dirs = self.sensor.directions[r_idx, c_idx] @ to_car.T
        origin = (self.ray_starts(pose, s_rot, r_idx) - car.translation()) @ c_rot
        current = layer.dist[r_idx, c_idx]
        ray_ids = r_idx * self.sensor.columns + c_idx
        t, prim = cast_through(caster.bvh, origin, dirs, np.minimum(current, self.sensor.max_range),
                               caster.face_pass, ray_ids, 0)
        nearer = (prim >= 0) & (t < current)
        rn, cn, pn = r_idx[nearer], c_idx[nearer], prim[nearer]
        layer.dist[rn, cn] = t[nearer]
        layer.cls[rn, cn] = car.cls
        layer.inst[rn, cn] = car.instance
        layer.semantic[rn, cn] = self.car_semantic(car)
        mat = caster.material[pn]
        if car.paint is not None:
            mat = np.where(np.isin(mat, PAINT_IDS), car.paint, mat)
        layer.mat[rn, cn] = mat
        facing = (caster.normals[pn] * dirs[nearer]).sum(axis=1)
        layer.cos[rn, cn] = np.abs(facing)
        if layer.normal is not None:   # car to sensor frame, turned towards the sensor
            layer.normal[rn, cn] = (caster.normals[pn] @ to_car) * np.where(facing > 0, -1.0,
                                                                             1.0)[:, None]
        return len(t)

    def render(self, bg_id: int, placed: Sequence[PlacedCar], pose: SensorPose = SensorPose(),
               rng: np.random.Generator | None = None, effects: Effects | None = None,
               seed: int = 0) -> Scan:
        """Compose the cached background with the cars and turn first returns into a Scan, with
        `effects` (weather, faults) drawn from `rng`'s state (from `seed` without one)."""
        normals = effects is not None and not effects.clear and bool(effects.ego_speed
                                                                     or effects.medium)
        layer = self.background_hits(bg_id, pose).copy(normals)
        for car in placed:
            self.cast_car(layer, car, pose)
        return self.to_scan(layer, rng, effects, seed)

    def to_scan(self, layer: HitLayer, rng: np.random.Generator | None,
                effects: Effects | None = None, seed: int = 0) -> Scan:
        """Apply range limits, weather and sensor effects, then build the H×W×6 image. Clear
        effects take exactly today's path; others read their seed from `rng` without drawing
        from it, so the scan's own draws are those of a clear scan."""
        s = self.sensor
        fx = None if effects is None or effects.clear else effects
        fx_seed = 0 if fx is None else effect_seed(rng, seed)
        r = layer.dist
        if fx is not None and fx.ego_speed:
            r = self.weather.moving_ranges(r, layer.normal, layer.cos, fx.ego_speed)
        if rng is not None and s.range_noise > 0:
            r = r + rng.normal(0.0, s.range_noise, r.shape)
        valid = np.isfinite(r) & (r >= s.min_range) & (r <= s.max_range)
        if rng is not None and s.ray_drop > 0:
            valid &= rng.random(r.shape) >= s.ray_drop
        intensity = None
        cls, inst, sem = layer.cls, layer.inst, layer.semantic
        if self.returns is not None:
            valid &= ~GLASS[layer.mat]
            intensity = np.zeros(r.shape, np.float32)
            intensity[valid] = self.returns.intensity(
                layer.mat[valid], layer.cos[valid], r[valid], sem[valid], inst[valid],
                None if rng is None or self.returns.classes is None else side_generator(rng))
        if fx is not None and fx.medium:
            clear_i = (valid * np.float32(NOMINAL_INTENSITY) if intensity is None
                       else intensity)
            e = self.weather.medium(fx, fx_seed, Echoes(r, valid, intensity, cls, inst, sem),
                                    clear_i, layer.mat, layer.cos, layer.normal,
                                    self._material_power(layer, r, valid))
            r, valid, intensity, cls, inst, sem = (e.r, e.valid, e.intensity, e.cls, e.inst,
                                                   e.semantic)
        if self.returns is not None and rng is not None:
            u = rng.random(r.shape)[valid]
            p = self.returns.return_probability(intensity[valid], sem[valid]) * self._keep[valid]
            valid[valid] = u < p
        if fx is not None and (fx.crosstalk or fx.beam_loss or fx.beams):
            e = self.weather.faults(fx, fx_seed, Echoes(r, valid, intensity, cls, inst, sem))
            r, valid, intensity, cls, inst, sem = (e.r, e.valid, e.intensity, e.cls, e.inst,
                                                   e.semantic)
        image = np.zeros((*s.shape, 6), dtype=np.float32)
        rv = np.where(valid, r, 0.0)
        if s.ray_origins is None:
            image[..., 0:3] = s.directions * rv[..., None]
            image[..., 4] = rv
        else:  # points from their rows' origins; range from the sensor origin, as KITTI's
            xyz = np.where(valid[..., None], s.points(rv), 0.0)
            image[..., 0:3] = xyz
            image[..., 4] = np.linalg.norm(xyz, axis=-1)
        if intensity is not None:
            image[..., 3] = np.where(valid, intensity, 0.0)
        image[..., 5] = np.where(valid, cls, 0)
        return project_scan(s, Scan(image, np.where(valid, inst, 0).astype(np.int32),
                                   np.where(valid, sem, 0).astype(np.uint16)))

    def _material_power(self, layer: HitLayer, r: np.ndarray, valid: np.ndarray
                        ) -> np.ndarray | None:
        """Where the return model shades by class: each hit's intensity by its material, what
        the weather decides detection on (a class's stored remission may be darker than any
        material's, as a real scan's may; its echo still reached the floor)."""
        if self.returns is None or self.returns.classes is None:
            return None
        out = np.zeros(r.shape, np.float32)
        out[valid] = self.returns.intensity(layer.mat[valid], layer.cos[valid], r[valid])
        return out

    # -- samples --------------------------------------------------------------------------
    def placed_cars(self, sample: Sample) -> list[PlacedCar]:
        """The sample's cars in the world, or InvalidSample naming what they would intersect."""
        dy = self.ego_dy(sample.background)   # the sample's positions are the sensor's
        placed = [replace(place(c, FIRST_CAR_INSTANCE + i), cls=self.model_class(c.model))
                  for i, c in enumerate(sample.cars)]
        placed = [replace(c, y=c.y + dy) for c in placed] if dy else placed
        obstacles = self.obstacles(sample.background)
        crosses = (self.crosses_kerbs(placed) if self._kerbs_stop[sample.background]
                   else [True] * len(placed))
        check_placement(placed, [self.footprint(c) for c in placed], obstacles, crosses,
                        EGO_FOOTPRINT + [0.0, dy])
        check_surfaces(placed, self.surfaces,
                       lambda x, y: self.surface(sample.background, x, y))
        return [self.settle(sample.background, c) for c in placed]

    def crosses_kerbs(self, placed: Sequence[PlacedCar]) -> list[bool]:
        """Per placed object, whether it may stand beyond the kerb (people and bicycles)."""
        return [int(self.model_semantic(p.model)) in actors.KERB_CROSSING_IDS for p in placed]

    def surface(self, bg_id: int, x: float, y: float) -> str:
        """What the ground at world (x, y) is: "road", "sidewalk" or "terrain" (the street's
        kerb and sidewalk lines; a background without terrain is all road)."""
        if bg_id not in self._terrain:
            self.background(bg_id)
        t = self._terrain[bg_id]
        return "road" if t is None else t.surface(x, y)

    def settle(self, bg_id: int, car: PlacedCar) -> PlacedCar:
        """The car standing on the background's ground (z, pitch, roll from its wheelbase)."""
        _, corners = self.car_caster(car.model)
        lo, hi = corners.min(axis=0), corners.max(axis=0)
        z, pitch, roll = self.pose_on(
            bg_id, car.x, car.y, car.heading_deg, max((hi[0] - lo[0]) / 2 - 0.6, 0.3),
            max((hi[1] - lo[1]) / 2 - 0.15, 0.3))
        return replace(car, z=z, pitch_deg=pitch, roll_deg=roll)

    def ego_pose(self, bg_id: int, pose: SensorPose = SensorPose()) -> SensorPose:
        """The ego vehicle standing on the background's ground at the pose's x, heading and y
        across from where the street's ego stands (ego_dy), pitched and raised by the street's
        own ego offsets (a street fitted to a real place)."""
        dy = self.ego_dy(bg_id)
        z, pitch, roll = self.pose_on(bg_id, pose.x, pose.y + dy, pose.heading_deg)
        dpitch, dz, _ = self._ego_offset[bg_id]
        return replace(pose, y=pose.y + dy, z=z + dz, pitch_deg=pitch + dpitch, roll_deg=roll)

    def ego_dy(self, bg_id: int) -> float:
        """Where across the road (m, +left of the crown) the background's ego stands."""
        if bg_id not in self._ego_offset:
            self.background(bg_id)
        return self._ego_offset[bg_id][2]

    def pose_on(self, bg_id: int, x: float, y: float, heading_deg: float,
                half_length: float = 1.4, half_width: float = 0.8) -> tuple[float, float, float]:
        """(z, pitch, roll) of a vehicle on the background's terrain (kept after its BVH is
        dropped; a background without terrain is the plane z = 0)."""
        if bg_id not in self._terrain:
            self.background(bg_id)
        t = self._terrain[bg_id]
        if t is None:
            return 0.0, 0.0, 0.0
        return t.pose_on(x, y, heading_deg, half_length, half_width)

    def obstacles(self, bg_id: int) -> Obstacles:
        """The background's obstacle outlines, kept after its BVH is dropped."""
        if bg_id not in self._obstacles:
            self.background(bg_id)
        return self._obstacles[bg_id]

    def footprint(self, car: PlacedCar) -> np.ndarray:
        """The car's outline on the ground (4×2, counter-clockwise) in the world frame."""
        _, corners = self.car_caster(car.model)
        lo, hi = corners.min(axis=0), corners.max(axis=0)
        box = np.array([[lo[0], lo[1]], [hi[0], lo[1]], [hi[0], hi[1]], [lo[0], hi[1]]])
        return box @ car.rotation()[:2, :2].T + [car.x, car.y]

    def placed_pixels(self, scan: Scan) -> np.ndarray:
        """The pixels of the sample's placed objects (instances 1, 2, ...), not the street's
        parked cars and other objects (instances from FIRST_STREET_INSTANCE)."""
        return (scan.instance >= FIRST_CAR_INSTANCE) & (scan.instance < FIRST_STREET_INSTANCE)

    def scan(self, sample: Sample, pose: SensorPose = SensorPose(),
             rng: np.random.Generator | None = None) -> Scan:
        """The labelled scan of a sample, with its weather and faults (effect dims); raises
        InvalidSample for impossible scenes."""
        effects = effects_of(sample)
        seed = 0 if effects.clear else zlib.crc32(repr(sample.lidar_values).encode())
        return self.render(sample.background, self.placed_cars(sample),
                           self.ego_pose(sample.background, pose), rng, effects, seed)
