"""The camera sensor: a pinhole beside the LiDAR that renders the same scene with Embree.

The renderer reuses the Simulator's BVHs (the background in the world frame, each car model in
its own frame) and casts one ray per pixel centre: the nearest hit gives the class, instance and
depth images, and a simple shading of its normal gives the RGB image. Only the RGB image reads
the image-only dims (colour, weather, time_of_day); the LiDAR scan never does.
"""

from __future__ import annotations

import hashlib
import math
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from falsify.calibration import (
    MIN_DEPTH,
    Extrinsic,
    KittiCalib,
    Pinhole,
    pixel_index,
    project_points,
)
from falsify.errors import ConfigError
from falsify.scene import PlacedCar, Simulator
from falsify.sensor import SensorPose
from falsify.space import IMAGE_ONLY, Sample, Space

# KITTI's left colour camera (P2 of the 2011_09_26 drives): 1242 x 375 pixels, focal 721.5377 px.
KITTI_WIDTH, KITTI_HEIGHT = 1242, 375
KITTI_FOCAL = 721.5377
# KITTI's published 2011_09_26 rig calibration (calib_cam_to_cam.txt, calib_velo_to_cam.txt).
KITTI_P2 = np.array([[721.5377, 0.0, 609.5593, 44.85728],
                     [0.0, 721.5377, 172.854, 0.2163791],
                     [0.0, 0.0, 1.0, 0.002745884]])
KITTI_R0_RECT = np.array([[0.9999239, 0.00983776, -0.007445048],
                          [-0.009869795, 0.9999421, -0.004278459],
                          [0.007402527, 0.004351614, 0.9999631]])
KITTI_TR_VELO_TO_CAM = np.array([[0.007533745, -0.9999714, -0.000616602, -0.004069766],
                                 [0.01480249, 0.0007280733, -0.9998902, -0.07631618],
                                 [0.9998621, 0.00752379, 0.01480755, -0.2717806]])
CAMERA_PRESETS = ("kitti-centre", "kitti-rig")
DEFAULT_CAMERA = "kitti-centre"


@dataclass(frozen=True, eq=False)
class Camera:
    """Intrinsics plus the transform from the LiDAR's frame to the camera's optical frame."""

    name: str
    intrinsics: Pinhole
    extrinsic: Extrinsic
    max_depth: float = 400.0

    @property
    def shape(self) -> tuple[int, int]:
        return (self.intrinsics.height, self.intrinsics.width)

    def scaled(self, factor: float) -> Camera:
        """The same field of view at `factor` times the resolution (tests use small images)."""
        i = self.intrinsics
        w, h = max(1, round(i.width * factor)), max(1, round(i.height * factor))
        sx, sy = w / i.width, h / i.height
        return replace(self, name=f"{self.name}@{w}x{h}",
                       intrinsics=Pinhole(w, h, i.fx * sx, i.fy * sy, i.cx * sx, i.cy * sy))

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """LiDAR-frame points to (col, row, inside)."""
        u, v, _ = project_points(points, self.intrinsics, self.extrinsic)
        return pixel_index(u, v, self.intrinsics)

    def kitti_calib(self) -> KittiCalib:
        return KittiCalib.for_camera(self.intrinsics, self.extrinsic)


def camera_preset(name: str) -> Camera:
    """`kitti-centre`: KITTI's image size and focal length at the LiDAR's centre, looking along its
    x axis (the paper's set-up); `kitti-rig`: KITTI's real camera 2 with its offset and
    rectification."""
    if name == "kitti-centre":
        intr = Pinhole(KITTI_WIDTH, KITTI_HEIGHT, KITTI_FOCAL, KITTI_FOCAL, KITTI_WIDTH / 2,
                       KITTI_HEIGHT / 2)
        return Camera(name, intr, Extrinsic.shared_centre())
    if name == "kitti-rig":
        calib = KittiCalib((KITTI_P2,) * 4, KITTI_R0_RECT, KITTI_TR_VELO_TO_CAM)
        intr, ext = calib.camera2(KITTI_WIDTH, KITTI_HEIGHT)
        return Camera(name, intr, ext)
    raise ConfigError(f"--camera: unknown camera {name!r}; allowed: {', '.join(CAMERA_PRESETS)}")


# -- the image-only dims ----------------------------------------------------------------------
COLOURS = {
    "red": (0.55, 0.03, 0.03), "white": (0.80, 0.80, 0.78), "black": (0.025, 0.025, 0.03),
    "silver": (0.50, 0.52, 0.55), "grey": (0.22, 0.23, 0.24), "gray": (0.22, 0.23, 0.24),
    "blue": (0.03, 0.10, 0.45), "green": (0.04, 0.28, 0.08), "yellow": (0.75, 0.55, 0.02),
    "orange": (0.80, 0.25, 0.02), "brown": (0.20, 0.09, 0.04),
}
WEATHERS = ("clear", "sun", "cloudy", "rain", "fog")
TIMES = {"dawn": 6.5, "morning": 9.0, "noon": 12.0, "afternoon": 15.0, "dusk": 17.5,
         "night": 22.0}
# Extinction per metre (fog and rain attenuate with depth) and direct sun kept through clouds.
_EXTINCTION = {"clear": 1 / 3000, "cloudy": 1 / 1500, "rain": 1 / 180, "fog": 1 / 28}
_SUN_KEPT = {"clear": 1.0, "cloudy": 0.2, "rain": 0.08, "fog": 0.25}


@dataclass(frozen=True)
class Look:
    """What the image-only dims set: car paint (linear RGB), weather and the hour (0..24)."""

    colour: tuple[float, float, float] = COLOURS["silver"]
    weather: str = "clear"
    hour: float = 12.0


def parse_look(values: dict[str, object]) -> Look:
    """Look from {colour, weather, time_of_day}; a bad value names its dim and what is allowed."""
    look = Look()
    if "colour" in values:
        c = str(values["colour"]).lower()
        if c in COLOURS:
            rgb = COLOURS[c]
        elif len(c) == 7 and c[0] == "#" and all(ch in "0123456789abcdef" for ch in c[1:]):
            rgb = tuple((int(c[k:k + 2], 16) / 255.0) ** 2.2 for k in (1, 3, 5))
        else:
            raise ConfigError(f"dims.colour: {values['colour']!r} is not a colour; allowed: "
                              f"{', '.join(COLOURS)} or #rrggbb")
        look = replace(look, colour=tuple(float(v) for v in rgb))
    if "weather" in values:
        w = str(values["weather"]).lower()
        if w not in WEATHERS:
            raise ConfigError(f"dims.weather: {values['weather']!r} is not a weather; allowed: "
                              f"{', '.join(WEATHERS)}")
        look = replace(look, weather="clear" if w == "sun" else w)
    if "time_of_day" in values:
        t = str(values["time_of_day"]).lower()
        if t in TIMES:
            hour = TIMES[t]
        else:
            try:
                hh, mm = t.split(":")
                hour = int(hh) + int(mm) / 60
                ok = len(mm) == 2 and 0 <= int(mm) < 60 and 0 <= hour <= 24
            except ValueError:
                ok = False
            if not ok:
                raise ConfigError(f"dims.time_of_day: {values['time_of_day']!r} is not a time; "
                                  f"allowed: {', '.join(TIMES)} or HH:MM (00:00..24:00)")
        look = replace(look, hour=float(hour))
    return look


def look_of(sample: Sample) -> Look:
    return parse_look({d: sample[d] for d in IMAGE_ONLY if sample.get(d) is not None})


def check_looks(space: Space) -> None:
    """Fail before anything is written if an image-only dim holds a value we cannot render."""
    for name in IMAGE_ONLY:
        if name in space.dims:
            for v in space.dims[name].grid():
                parse_look({name: v})


# -- rendering --------------------------------------------------------------------------------
@dataclass(frozen=True)
class CameraImage:
    """One camera frame: RGB, per-pixel class and instance, depth along the optical axis (m,
    0 where nothing is hit), and the pixels each car would cover with nothing in front of it."""

    rgb: np.ndarray       # (H, W, 3) uint8
    cls: np.ndarray       # (H, W) uint8
    instance: np.ndarray  # (H, W) int32
    depth: np.ndarray     # (H, W) float32
    unoccluded: dict[int, int]


@dataclass
class Hits:
    """Nearest hit per pixel (flat): distance, owner (-1 background, k = car k), primitive,
    unnormalised normal in the owner's frame."""

    t: np.ndarray
    owner: np.ndarray
    prim: np.ndarray
    normal: np.ndarray


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
        self.streaks = _rain_streaks(camera.shape).ravel()
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
            sun_d = _sun(look)[0]
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
                near = _slab((p[close] - car.translation()) @ c_rot, sun_d @ c_rot, lo, hi)
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
            return _shadowed(self, caster, placed, points, sun_d)
        return shade(self, bg, placed, paints, sub, self._rays_cam[idx] @ rot.T, origin,
                     rot[:, 2], look, self.streaks[idx], shadow_test)


# Linear light to 8-bit sRGB-like values (gamma 2.2) through a table: 16 linear steps per code.
_GAMMA = (np.linspace(0.0, 1.0, 4096) ** (1 / 2.2) * 255 + 0.5).astype(np.uint8)
# Fog and rain take the sky's colour 10 degrees above the horizon.
_HAZE_RAY = np.array([[math.cos(math.radians(10)), 0.0, math.sin(math.radians(10))]])


def _sun(look: Look) -> tuple[np.ndarray, float, np.ndarray]:
    """Unit direction to the sun (world), its strength after clouds, and its colour."""
    el = math.radians(62.0 * math.sin(math.pi * (look.hour - 6.0) / 12.0))
    az = math.radians(100.0 - 200.0 * (look.hour - 6.0) / 12.0)
    d = np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
    strength = float(np.clip(math.sin(el) * 4.0, 0.0, 1.0)) * _SUN_KEPT[look.weather]
    warm = float(np.clip(math.sin(el) * 2.5, 0.0, 1.0))
    colour = np.array([1.0, 0.55 + 0.42 * warm, 0.30 + 0.60 * warm])
    return d, strength, colour


def _sky(look: Look, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sky colour per ray and the ambient light level (linear RGB)."""
    sun_el = math.sin(math.radians(62.0 * math.sin(math.pi * (look.hour - 6.0) / 12.0)))
    day = float(np.clip(sun_el * 3.0 + 0.25, 0.0, 1.0))
    up = np.clip(dirs[:, 2], 0.0, 1.0)[:, None]
    if look.weather == "clear":
        zenith, horizon = np.array([0.10, 0.25, 0.65]), np.array([0.55, 0.68, 0.85])
    else:
        zenith, horizon = np.array([0.42, 0.44, 0.47]), np.array([0.60, 0.62, 0.64])
    dusk = float(np.clip(1.0 - abs(sun_el) * 5.0, 0.0, 1.0))
    horizon = horizon * (1 - 0.5 * dusk) + 0.5 * dusk * np.array([0.95, 0.50, 0.30])
    night = np.array([0.004, 0.006, 0.02])
    sky = (horizon + (zenith - horizon) * np.sqrt(up)) * day + night * (1 - day)
    ambient = horizon * (0.35 * day) + np.array([0.01, 0.012, 0.025])
    return sky, ambient


def _palette(keys: np.ndarray, colours: np.ndarray) -> np.ndarray:
    """A fixed colour per integer key (deterministic hash)."""
    h = (keys.astype(np.uint64) * np.uint64(2654435761)) % np.uint64(len(colours))
    return colours[h.astype(np.int64)]


_BUILDING = np.array([[0.40, 0.33, 0.25], [0.30, 0.27, 0.24], [0.45, 0.42, 0.36],
                      [0.28, 0.14, 0.10], [0.38, 0.38, 0.38], [0.50, 0.45, 0.32]])
_CLOTHES = np.array([[0.05, 0.05, 0.10], [0.40, 0.05, 0.05], [0.08, 0.20, 0.40],
                     [0.35, 0.30, 0.20], [0.10, 0.10, 0.10], [0.50, 0.45, 0.40]])
_PARKED = np.array([list(COLOURS[c]) for c in ("red", "white", "black", "silver", "grey",
                                                "blue", "green")])


_ROAD = (0.075, 0.075, 0.08)
_DASH = (0.70, 0.70, 0.66)
_PAVE = (0.30, 0.29, 0.27)
_GRASS = (0.07, 0.14, 0.04)


def ground_colours(bg, x: np.ndarray, y: np.ndarray, z: np.ndarray, up: np.ndarray,
                   col: np.ndarray) -> None:
    """Colour the background's upward-facing points in `col`: road (within 5 cm of the road's
    crown height at x, so a street that climbs stays road), its centre dashes, pavement within
    6.5 m beyond the kerb, grass beyond."""
    if bg.terrain is not None:
        kerb, crown = bg.terrain.kerb(x), bg.terrain.road_z(x)
    else:
        kerb, crown = bg.road_half_width, 0.0
    road = up & (z < crown + 0.05) & (np.abs(y) < kerb)
    col[road] = _ROAD
    col[road & (np.abs(y) < 0.08) & (np.mod(x, 9.0) < 3.0)] = _DASH
    pave = up & ~road & (np.abs(y) < kerb + 6.5)
    col[pave] = _PAVE
    col[up & ~road & ~pave] = _GRASS


def shade(r: CameraRenderer, bg, placed, paints, hits: Hits, dirs, origin, axis: np.ndarray,
          look: Look, streaks: np.ndarray, shadow_test
          ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Lambert plus a sun highlight on paint, cast shadows, sky light, headlights at night,
    and weather as attenuation with depth and darkening, for the rays `dirs` and their hits
    (`shadow_test(points, sun_dir)` says which points the sun cannot see); returns RGB (N, 3)
    uint8, which pixels the sun lights, and the lit hit points."""
    n = len(hits.t)
    hit = np.isfinite(hits.t)
    pos = origin + dirs * np.where(hit, hits.t, 0.0)[:, None]
    normal = hits.normal.astype(np.float64)
    albedo = np.zeros((n, 3))
    spec = np.zeros(n)
    # Background surfaces, by class and shape.
    b = np.flatnonzero(hit & (hits.owner < 0))
    cls, inst = bg.face_class[hits.prim[b]], bg.face_instance[hits.prim[b]]
    nb = normal[b]
    up = np.abs(nb[:, 2]) > 0.9 * np.sqrt(np.einsum("ij,ij->i", nb, nb))
    z, y, x = pos[b, 2], pos[b, 1], pos[b, 0]
    col = _palette(hits.prim[b] // 12, _BUILDING)
    ground_colours(bg, x, y, z, up, col)
    things = np.flatnonzero((cls == 0) & (inst > 0))
    tx, ty, tz = x[things], y[things], z[things]
    above = tz - (bg.terrain.height(tx, ty) if bg.terrain is not None else 0.0)
    col[things] = np.where((above > 2.0)[:, None], (0.05, 0.14, 0.04), (0.16, 0.12, 0.08))
    col[cls == 1] = _palette(inst[cls == 1], _PARKED)
    people = (cls == 2) | (cls == 3)
    col[people] = _palette(inst[people], _CLOTHES)
    albedo[b] = col
    # Sampled cars: paint, dark glass above the belt line, dark tyres and sills low down.
    for k, car in enumerate(placed):
        mine = np.flatnonzero(hits.owner == k)
        if not len(mine):
            continue
        _, corners = r.sim.car_caster(car.model)
        height = float(corners[:, 2].max() - corners[:, 2].min())
        local = (pos[mine] - car.translation()) @ car.rotation()
        n_loc = normal[mine] / np.maximum(np.linalg.norm(normal[mine], axis=1,
                                                         keepdims=True), 1e-12)
        paint = np.tile(np.asarray(paints[k], np.float64), (len(mine), 1))
        glass = (local[:, 2] > 0.62 * height) & (local[:, 2] < 0.96 * height) \
            & (np.abs(n_loc[:, 2]) < 0.8)
        paint[glass] = (0.02, 0.025, 0.03)
        low = local[:, 2] < 0.27 * height
        paint[low] = (0.03, 0.03, 0.03)
        albedo[mine] = paint
        spec[mine] = np.where(low, 0.05, np.where(glass, 0.9, 0.5))
        normal[mine] = normal[mine] @ car.rotation().T
    # Light.
    nrm = normal / np.maximum(np.sqrt(np.einsum("ij,ij->i", normal, normal)), 1e-12)[:, None]
    nrm *= np.where(np.einsum("ij,ij->i", nrm, dirs) > 0, -1.0, 1.0)[:, None]
    sun_d, sun_k, sun_c = _sun(look)
    sky, ambient = _sky(look, dirs)
    facing = np.flatnonzero(hit & (nrm @ sun_d > 0) & (sun_k > 0))
    points = pos[facing] + nrm[facing] * 0.02
    free = ~shadow_test(points, sun_d)
    lit = np.zeros(n, bool)
    lit[facing[free]] = True
    lambert = np.where(lit, nrm @ sun_d, 0.0)
    sky_light = 0.6 + 0.4 * np.clip(nrm[:, 2], 0.0, 1.0)
    light = ambient[None, :] * sky_light[:, None] + sun_k * lambert[:, None] * sun_c
    if sun_d[2] < 0.05:  # headlights: the ego car lights the road ahead at night
        cos_axis = np.clip(dirs @ axis, 0.0, 1.0)
        dist = np.where(hit, hits.t, np.inf)
        beam = np.clip((cos_axis - 0.9) * 10.0, 0.0, 1.0) * 40.0 / (dist ** 2 + 25.0)
        light = light + (beam * np.clip(-np.einsum("ij,ij->i", nrm, dirs), 0, 1))[:, None] \
            * np.array([1.0, 0.95, 0.85])
    out = albedo * light
    shiny = np.flatnonzero(spec > 0)  # paint and glass: a sun highlight and the sky reflected
    if len(shiny):
        d, nr, sp = dirs[shiny], nrm[shiny], spec[shiny]
        half = sun_d[None, :] - d
        half /= np.sqrt(np.einsum("ij,ij->i", half, half))[:, None]
        cos_h = np.clip(np.einsum("ij,ij->i", nr, half), 0, 1)
        highlight = sp * np.where(lit[shiny], cos_h ** 60, 0.0)
        reflect = sp * 0.25 * (1 - np.clip(-np.einsum("ij,ij->i", nr, d), 0, 1)) ** 2
        out[shiny] += highlight[:, None] * sun_k * sun_c + reflect[:, None] * sky[shiny]
    if look.weather == "rain":
        out *= 0.8  # wet, dull surfaces
    out = np.where(hit[:, None], out, sky)
    # Weather: attenuation towards the horizon's colour with distance.
    dist = np.where(hit, hits.t, r.camera.max_depth * 4)
    keep = np.exp(-dist * _EXTINCTION[look.weather])[:, None]
    haze = _sky(look, _HAZE_RAY)[0] if look.weather in ("fog", "rain") else sky
    out = out * keep + haze * (1 - keep)
    if look.weather == "rain":
        out = out + 0.08 * streaks[:, None] * haze
    rgb = _GAMMA[(np.clip(out, 0.0, 1.0) * (len(_GAMMA) - 1) + 0.5).astype(np.int64)]
    return rgb, lit, points[free]


def _shadowed(r: CameraRenderer, bg_caster, placed, points: np.ndarray,
              sun_d: np.ndarray) -> np.ndarray:
    """Whether each point's ray to the sun is blocked by the background or a car."""
    blocked = np.zeros(len(points), bool)
    if len(points) == 0:
        return blocked
    t, _ = bg_caster.bvh.cast(points, np.broadcast_to(sun_d, points.shape), 1000.0)
    blocked |= np.isfinite(t)
    for car in placed:
        caster, corners = r.sim.car_caster(car.model)
        c_rot = car.rotation()
        o = (points - car.translation()) @ c_rot
        d = sun_d @ c_rot
        near = _slab(o, d, corners.min(axis=0), corners.max(axis=0)) & ~blocked
        if near.any():
            t, _ = caster.bvh.cast(o[near], np.broadcast_to(d, (int(near.sum()), 3)), 1000.0)
            blocked[np.flatnonzero(near)[np.isfinite(t)]] = True
    return blocked


def _slab(o: np.ndarray, d: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Which rays o + s d (s > 0, one direction d for all) cross the box [lo, hi]."""
    tmin = np.zeros(len(o))
    tmax = np.full(len(o), np.inf)
    for k in range(3):
        if abs(d[k]) < 1e-12:  # parallel to this slab: inside it or never
            outside = (o[:, k] < lo[k]) | (o[:, k] > hi[k])
            tmax[outside] = -1.0
            continue
        t1, t2 = (lo[k] - o[:, k]) / d[k], (hi[k] - o[:, k]) / d[k]
        if d[k] < 0:
            t1, t2 = t2, t1
        np.maximum(tmin, t1, out=tmin)
        np.minimum(tmax, t2, out=tmax)
    return tmax >= tmin


def _rain_streaks(shape: tuple[int, int]) -> np.ndarray:
    """A fixed pattern of short slanted streaks (deterministic: no per-run randomness)."""
    h, w = shape
    seed = int.from_bytes(hashlib.sha256(f"rain{h}x{w}".encode()).digest()[:4], "little")
    rng = np.random.default_rng(seed)
    out = np.zeros((h, w))
    n = max(1, h * w // 900)
    r0, c0 = rng.integers(0, h, n), rng.integers(0, w, n)
    length = max(2, h // 25)
    for k in range(length):
        rr, cc = r0 + k, c0 + k // 4
        ok = (rr < h) & (cc < w)
        out[rr[ok], cc[ok]] = 1.0
    return out


def class_picture(image: CameraImage) -> np.ndarray:
    """(H, W, 3) uint8 class image: classes in the preview colours, unknown shaded by depth,
    sky dark."""
    from falsify.preview import CLASS_RGB, EMPTY_RGB
    rgb = CLASS_RGB[np.clip(image.cls, 0, 3)].astype(np.float32)
    unknown = image.cls == 0
    rgb[unknown] *= (1.0 - np.clip(image.depth[unknown] / 80.0, 0.0, 0.75))[:, None]
    rgb[image.depth <= 0] = EMPTY_RGB
    return rgb.astype(np.uint8)


def overlay_picture(image: CameraImage, camera: Camera, points: np.ndarray) -> np.ndarray:
    """The paper's figure 1b: LiDAR points (sensor frame) drawn on the RGB image, far first,
    coloured by depth."""
    from falsify.overlay import depth_colours, draw_points
    u, v, depth = project_points(points, camera.intrinsics, camera.extrinsic)
    col, row, inside = pixel_index(u, v, camera.intrinsics)
    order = np.flatnonzero(inside)
    order = order[np.argsort(-depth[order], kind="stable")]
    return draw_points(image.rgb.copy(), col[order], row[order], depth_colours(depth[order]),
                       size=2)


def camera_files(image: CameraImage, prefix: str = "") -> dict[str, bytes]:
    """The files that hold one camera frame: RGB and class PNGs, class, instance and depth."""
    import io

    from falsify.preview import encode_png

    def npy(a: np.ndarray) -> bytes:
        buf = io.BytesIO()
        np.save(buf, a, allow_pickle=False)
        return buf.getvalue()
    return {f"{prefix}image.png": encode_png(image.rgb),
            f"{prefix}class.png": encode_png(class_picture(image)),
            f"{prefix}class.npy": npy(image.cls), f"{prefix}instance.npy": npy(image.instance),
            f"{prefix}depth.npy": npy(image.depth)}
