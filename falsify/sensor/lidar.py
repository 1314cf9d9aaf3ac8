"""The virtual LiDAR: beam elevations, azimuth grid, mounting, range limits and sensor effects.

A sensor is a fixed fan of rays in its own frame (x forward, y left, z up, origin at the optical
centre). Each row's rays start at the origin, or `ring_offsets_m[r]` above it: a real HDL-64E's
lasers sit 0.1-0.2 m above its frame's origin, which moves a ring's elevation seen from the origin
by `dz / range`. Row r, column c of the range image is the ray at elevation `elevations[r]` and
azimuth `az_left - (c + 0.5) * az_step`, so a point at azimuth `a` falls in column
`floor((az_left - a) / az_step)`: SqueezeSeg's layout (column 0 is the left edge).

A sensor with `projection = "spherical"` still casts those rays but stores its scans in RangeNet++'s
range image (Milioto et al., IROS 2019), the input of networks trained on SemanticKITTI: rows by
pitch evenly from `fov_up_deg` (row 0) down to `fov_down_deg`, columns by azimuth over 360° with
straight ahead (+x) at column W/2, the nearest point winning a pixel (`Sensor.pixel_of`);
the image keeps the ray grid's H x W.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from functools import cached_property
from pathlib import Path

import numpy as np

from falsify.errors import ConfigError
from falsify.fileio import parse_toml, read_bytes
from falsify.paths import RETURN_MODELS, SENSOR_PRESETS, sensor_digest
from falsify.rotations import rot_x, rot_y, rot_z

PRESET_DIR = SENSOR_PRESETS
SENSOR_KEYS = {
    "name", "description", "elevations_deg", "vertical", "h_fov_deg", "columns", "pitch_deg",
    "mount_height", "max_range", "min_range", "rotation_hz", "ray_drop", "range_noise",
    "returns", "kitti_rings", "ring_offsets_m", "projection", "fov_up_deg", "fov_down_deg",
}
PROJECTIONS = ("rings", "spherical")
MAX_RING_OFFSET_M = 1.0
# Farthest max_range: ten times any automotive LiDAR's, where float32 ranges still hold a
# millimetre; far beyond it the detection floor (1 / max_range^2) and the float32 scan overflow.
MAX_RANGE_M = 10_000.0
# Spin rates a sweep may take: spinning LiDARs turn at 5-20 Hz; at 1e-300 Hz a moving ego's sweep
# never ends and every ray is lost.
MIN_ROTATION_HZ, MAX_ROTATION_HZ = 0.1, 1000.0
# The grid's size: columns up to 16384 (0.022 deg over 360), rows up to 2048 (real sensors have
# at most 128 lasers, scanning solid-state ones a few hundred lines), and at most 2^22 rays a
# scan, so a typo (beams = 100000000) is refused instead of allocating hundreds of GB.
MAX_COLUMNS, MAX_ROWS, MAX_RAYS = 16384, 2048, 1 << 22


@dataclass(frozen=True)
class Sensor:
    """A LiDAR's geometry and effects; `elevations_deg` runs from the top row down."""

    name: str
    elevations_deg: tuple[float, ...]
    az_left_deg: float
    az_right_deg: float
    columns: int
    pitch_deg: float = 0.0
    mount_height: float = 1.73
    max_range: float = 120.0
    min_range: float = 0.0
    rotation_hz: float = 10.0
    ray_drop: float = 0.0
    range_noise: float = 0.0
    description: str = ""
    returns: str = ""  # a fitted return model in configs/returns/ ("" = every hit returns)
    # Rows are the HDL-64E's laser rings: KITTI .bin scans are read by ring (falsify.data.velodyne).
    kitti_rings: bool = False
    # Per row, how far above the origin (sensor-frame z, metres) its rays start; () = all at it.
    ring_offsets_m: tuple[float, ...] = ()
    # The scan image's layout: "rings" (row = ray row, column = azimuth bin) or "spherical"
    # (RangeNet++'s projection between fov_up_deg and fov_down_deg; see pixel_of).
    projection: str = "rings"
    fov_up_deg: float = 3.0
    fov_down_deg: float = -25.0
    # sha256 of a user's sensor file and the return model file it names ("" for a preset): a
    # dataset made with it records this, so one extended after the file changed is refused
    file_sha256: str = field(default="", compare=False)

    @property
    def rows(self) -> int:
        return len(self.elevations_deg)

    @property
    def shape(self) -> tuple[int, int]:
        return (self.rows, self.columns)

    @property
    def az_step_deg(self) -> float:
        return (self.az_left_deg - self.az_right_deg) / self.columns

    @property
    def full_circle(self) -> bool:
        return abs(self.az_left_deg - self.az_right_deg - 360.0) < 1e-9

    @cached_property
    def azimuths_deg(self) -> np.ndarray:
        """Azimuth of each column's ray (the centre of its bin), degrees, left to right."""
        return self.az_left_deg - (np.arange(self.columns) + 0.5) * self.az_step_deg

    @cached_property
    def directions(self) -> np.ndarray:
        """(H, W, 3) float64 unit ray directions in the sensor frame."""
        el = np.radians(np.asarray(self.elevations_deg))[:, None]
        az = np.radians(self.azimuths_deg)[None, :]
        d = np.stack(np.broadcast_arrays(np.cos(el) * np.cos(az), np.cos(el) * np.sin(az),
                                         np.sin(el)), axis=-1)
        d.setflags(write=False)
        return d

    @cached_property
    def ray_origins(self) -> np.ndarray | None:
        """(H, 1, 3) start of each row's rays in the sensor frame, or None when every ray starts
        at the origin (the single-origin path, kept so such sensors give the same bytes)."""
        if not any(self.ring_offsets_m):
            return None
        o = np.zeros((self.rows, 1, 3))
        o[:, 0, 2] = self.ring_offsets_m
        o.setflags(write=False)
        return o

    def points(self, ranges: np.ndarray) -> np.ndarray:
        """(H, W, 3) sensor-frame points of (H, W) laser ranges (each from its row's origin)."""
        p = self.directions * ranges[..., None]
        return p if self.ray_origins is None else p + self.ray_origins

    @cached_property
    def row_edges_deg(self) -> np.ndarray:
        """Elevation boundaries between rows (midpoints), descending, length H + 1."""
        el = np.asarray(self.elevations_deg, dtype=np.float64)
        if len(el) == 1:
            return np.array([el[0] + 1.0, el[0] - 1.0])
        mid = (el[:-1] + el[1:]) / 2
        return np.concatenate([[el[0] + (el[0] - mid[0])], mid, [el[-1] - (mid[-1] - el[-1])]])

    def pixel_of(self, points: np.ndarray, rows: np.ndarray | None = None
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Project sensor-frame points to (row, col, inside) with this sensor's layout; `rows`,
        when given, is each point's row (a laser ring) in place of its elevation's (ignored by
        a spherical sensor)."""
        p = np.asarray(points, dtype=np.float64)
        r = np.linalg.norm(p, axis=1)
        if self.projection == "spherical":
            return self._spherical_pixel(p, r)
        az = np.degrees(np.arctan2(p[:, 1], p[:, 0]))
        # Degrees clockwise from the left edge, in [0, 360): a field of view across +-180 deg
        # (e.g. [270, 90], looking back) holds azimuths that atan2 reports a turn away.
        col = np.floor(np.mod(self.az_left_deg - az, 360.0) / self.az_step_deg).astype(np.int64)
        if self.full_circle:
            col %= self.columns
        if rows is not None:
            row = np.asarray(rows, dtype=np.int64)
        else:
            el = np.degrees(np.arcsin(np.divide(p[:, 2], r, out=np.zeros_like(r), where=r > 0)))
            row = np.searchsorted(-self.row_edges_deg, -el, side="right") - 1
        inside = (col >= 0) & (col < self.columns) & (row >= 0) & (row < self.rows) & (r > 0)
        return row, col, inside

    def _spherical_pixel(self, p: np.ndarray, r: np.ndarray
                         ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """RangeNet++'s spherical projection (Milioto et al., IROS 2019): yaw = -atan2(y, x),
        pitch = asin(z / |p|); col = floor((yaw / pi + 1) W / 2), row = floor((1 - (pitch +
        |fov_down|) / fov) H), fov = |fov_up| + |fov_down|. Both are clamped into the image, so
        points above fov_up or below fov_down land in the top or bottom row, as in the images
        the SemanticKITTI networks were trained on; every point with |p| > 0 is inside."""
        h, w = self.shape
        down = math.radians(self.fov_down_deg)
        fov = abs(down) + abs(math.radians(self.fov_up_deg))
        yaw = -np.arctan2(p[:, 1], p[:, 0])
        sin = np.divide(p[:, 2], r, out=np.zeros_like(r), where=r > 0)
        pitch = np.arcsin(np.clip(sin, -1.0, 1.0))
        col = np.clip(np.floor(0.5 * (yaw / np.pi + 1.0) * w), 0, w - 1).astype(np.int64)
        row = np.clip(np.floor((1.0 - (pitch + abs(down)) / fov) * h), 0, h - 1).astype(np.int64)
        return row, col, r > 0

    def with_resolution(self, rows: int, columns: int) -> Sensor:
        """The same sensor resampled to another grid over the same fields of view."""
        el = np.asarray(self.elevations_deg)
        src = np.linspace(0.0, 1.0, len(el))
        at = np.linspace(0.0, 1.0, rows)
        offsets = (tuple(float(v) for v in np.interp(at, src, self.ring_offsets_m))
                   if self.ring_offsets_m else ())
        return replace(self, name=f"{self.name}@{rows}x{columns}",
                       elevations_deg=tuple(float(v) for v in np.interp(at, src, el)),
                       columns=columns, ring_offsets_m=offsets)


@dataclass(frozen=True)
class SensorPose:
    """Where the sensor's ground point stands in the world and which way it looks; z, pitch
    and roll are the ego vehicle's on uneven ground (falsify.world.terrain.Terrain.pose_on)."""

    x: float = 0.0
    y: float = 0.0
    """The ground point in the world frame, metres."""
    heading_deg: float = 0.0
    """Counter-clockwise from the world's +x."""
    z: float = 0.0
    pitch_deg: float = 0.0
    roll_deg: float = 0.0
    """The ground's height under the ego and its tilt there (0 on flat streets)."""

    def rotation(self, sensor: Sensor) -> np.ndarray:
        """3×3 rotation taking sensor-frame vectors to world-frame vectors (vehicle yaw, pitch,
        roll, then the sensor's own mounting pitch)."""
        r = rot_z(self.heading_deg)
        if self.pitch_deg or self.roll_deg:
            r = r @ rot_y(self.pitch_deg) @ rot_x(self.roll_deg)
        return r @ rot_y(sensor.pitch_deg)

    def origin(self, sensor: Sensor) -> np.ndarray:
        return np.array([self.x, self.y, self.z + sensor.mount_height], dtype=np.float64)


def preset_names() -> list[str]:
    return sorted(p.stem for p in PRESET_DIR.glob("*.toml"))


def load_sensor(name_or_path: str | Path, **overrides) -> Sensor:
    """Load a preset by name (configs/sensors/NAME.toml) or a TOML file path."""
    path = Path(name_or_path)
    if path.suffix != ".toml":
        path = PRESET_DIR / f"{name_or_path}.toml"
        if not path.exists():
            raise ConfigError(f"sensor: unknown preset {str(name_or_path)!r}; allowed: "
                              f"{', '.join(preset_names())} or a path to a .toml file")
    raw = parse_toml(read_bytes(path, "sensor", ConfigError), path, "sensor TOML", ConfigError)
    raw.update(overrides)
    sensor = parse_sensor(raw, source=str(path))
    if path.resolve().parent == PRESET_DIR.resolve():   # bundled: its bytes ship with the version
        return sensor
    return replace(sensor, file_sha256=sensor_digest(path, ConfigError))


def parse_sensor(raw: dict, source: str = "<sensor>") -> Sensor:
    """Validate a sensor table; each error names the key and what is allowed."""
    where = f"{source}: "
    extra = sorted(set(raw) - SENSOR_KEYS)
    if extra:
        raise ConfigError(f"{where}unknown key {extra[0]!r}; allowed: "
                          f"{', '.join(sorted(SENSOR_KEYS))}")

    def num(key: str, default: float | None = None, lo: float | None = None,
            hi: float | None = None, lo_open: bool = False) -> float:
        if key not in raw:
            if default is None:
                raise ConfigError(f"{where}missing key {key!r}")
            return default
        v = raw[key]
        if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
            raise ConfigError(f"{where}{key}: expected a finite number, got {v!r}")
        if lo is not None and (v < lo or (lo_open and v == lo)):
            raise ConfigError(f"{where}{key}: {v} must be {'>' if lo_open else '>='} {lo}")
        if hi is not None and v > hi:
            raise ConfigError(f"{where}{key}: {v} must be <= {hi}")
        return float(v)

    elevations = _elevations(raw, where)

    fov = raw.get("h_fov_deg")
    if not isinstance(fov, list) or len(fov) != 2 or not all(_finite(a) for a in fov):
        raise ConfigError(f"{where}h_fov_deg: expected [left_deg, right_deg], two finite "
                          "numbers of degrees counter-clockwise from forward (left positive), "
                          "e.g. [45, -45]")
    left, right = float(fov[0]), float(fov[1])
    if not 0 < left - right <= 360.0:
        raise ConfigError(f"{where}h_fov_deg: left {left:g} minus right {right:g} must be in "
                          "(0, 360] degrees")
    cols = raw.get("columns")
    if isinstance(cols, bool) or not isinstance(cols, int) or not 1 <= cols <= MAX_COLUMNS:
        raise ConfigError(f"{where}columns: {cols!r} must be an integer in 1..{MAX_COLUMNS}")
    if len(elevations) * cols > MAX_RAYS:
        raise ConfigError(f"{where}columns: {len(elevations)} rows x {cols} columns = "
                          f"{len(elevations) * cols:,} rays a scan; allowed: at most "
                          f"{MAX_RAYS:,} (e.g. 128 x 16384 or 2048 x 2048)")
    max_range = num("max_range", 120.0, lo=0.0, hi=MAX_RANGE_M, lo_open=True)
    min_range = num("min_range", 0.0, lo=0.0)
    if min_range >= max_range:
        raise ConfigError(f"{where}min_range {min_range} must be below max_range {max_range}")
    return Sensor(
        name=str(raw.get("name", Path(source).stem)),
        description=str(raw.get("description", "")),
        elevations_deg=tuple(elevations),
        az_left_deg=left,
        az_right_deg=right,
        columns=cols,
        pitch_deg=num("pitch_deg", 0.0, lo=-45.0, hi=45.0),
        mount_height=num("mount_height", 1.73, lo=0.0, hi=100.0),
        max_range=max_range,
        min_range=min_range,
        rotation_hz=num("rotation_hz", 10.0, lo=MIN_ROTATION_HZ, hi=MAX_ROTATION_HZ),
        ray_drop=num("ray_drop", 0.0, lo=0.0, hi=1.0),
        range_noise=num("range_noise", 0.0, lo=0.0, hi=1.0),
        returns=_returns_name(raw.get("returns", ""), where, Path(source).parent),
        kitti_rings=_flag(raw, "kitti_rings", where),
        ring_offsets_m=_ring_offsets(raw, len(elevations), where),
        **_projection(raw, where, full_circle=abs(left - right - 360.0) < 1e-9),
    )


def _elevations(raw: dict, where: str) -> list[float]:
    """The rows' elevations, from the top row down: `elevations_deg` (a per-beam table) or
    `vertical` (beams evenly from up_deg to down_deg), strictly inside (-90, 90)."""
    if ("elevations_deg" in raw) == ("vertical" in raw):
        raise ConfigError(f"{where}give exactly one of elevations_deg (a per-beam table) or "
                          "vertical = {{ up_deg, down_deg, beams }}")
    if "elevations_deg" in raw:
        el = raw["elevations_deg"]
        if not isinstance(el, list) or not el:
            raise ConfigError(f"{where}elevations_deg: expected a non-empty list of degrees, "
                              "one per row, top row first")
        bad = next((i for i, v in enumerate(el) if not _finite(v)), None)
        if bad is not None:
            raise ConfigError(f"{where}elevations_deg: row {bad} is {el[bad]!r}; allowed: "
                              "finite numbers of degrees")
        if len(el) > MAX_ROWS:
            raise ConfigError(f"{where}elevations_deg: {len(el)} rows; allowed: 1..{MAX_ROWS}")
        elevations = [float(v) for v in el]
        for i, (a, b) in enumerate(zip(elevations, elevations[1:], strict=False)):
            if b >= a:
                raise ConfigError(
                    f"{where}elevations_deg: row {i + 1} ({b:g}) is not below row {i} ({a:g}); "
                    "they must decrease strictly from the top row, no repeats (sort a "
                    "datasheet's laser-id table by elevation, highest first)")
    else:
        v = raw["vertical"]
        if not isinstance(v, dict) or set(v) != {"up_deg", "down_deg", "beams"}:
            raise ConfigError(f"{where}vertical: expected {{ up_deg, down_deg, beams }}")
        up, down, beams = v["up_deg"], v["down_deg"], v["beams"]
        if isinstance(beams, bool) or not isinstance(beams, int) or not 1 <= beams <= MAX_ROWS:
            raise ConfigError(f"{where}vertical.beams: {beams!r} must be an integer in "
                              f"1..{MAX_ROWS}")
        if not (_finite(up) and _finite(down)) or up <= down:
            raise ConfigError(f"{where}vertical: up_deg {up!r}, down_deg {down!r}; allowed: "
                              "finite numbers of degrees, up_deg above down_deg")
        elevations = list(np.linspace(float(up), float(down), beams)) if beams > 1 else [float(up)]
    if elevations[0] >= 90.0 or elevations[-1] <= -90.0:
        raise ConfigError(f"{where}vertical field of view {elevations[-1]:g}..{elevations[0]:g} "
                          "deg: elevations must lie strictly inside (-90, 90) (FOV < 180 deg); "
                          "the range-image projection cannot hold at the poles")
    return elevations


def _projection(raw: dict, where: str, full_circle: bool) -> dict:
    """`projection` ("rings", the default, or "spherical") and, for spherical only, its
    vertical field of view `fov_up_deg` in [0, 90) and `fov_down_deg` in (-90, 0]."""
    kind = raw.get("projection", "rings")
    if kind not in PROJECTIONS:
        raise ConfigError(f"{where}projection: {kind!r} is not allowed; allowed: "
                          f"{', '.join(repr(k) for k in PROJECTIONS)}")
    if kind == "rings":
        for key in ("fov_up_deg", "fov_down_deg"):
            if key in raw:
                raise ConfigError(f"{where}{key}: only for projection = \"spherical\" (the "
                                  "ring layout's rows are the sensor's own)")
        return {}
    if not full_circle:
        raise ConfigError(f"{where}h_fov_deg: projection = \"spherical\" spans 360 deg; "
                          "allowed: a left minus right of 360, e.g. [180, -180]")
    if raw.get("kitti_rings", False):
        raise ConfigError(f"{where}kitti_rings: must be false with projection = \"spherical\" "
                          "(its rows are pitch bins, not laser rings)")
    out = {}
    for key, lo, hi in (("fov_up_deg", 0.0, 90.0), ("fov_down_deg", -90.0, 0.0)):
        if key not in raw:
            raise ConfigError(f"{where}missing key {key!r} (projection = \"spherical\" needs "
                              "fov_up_deg and fov_down_deg, e.g. 3 and -25)")
        v = raw[key]
        if (isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v)
                or not lo <= v <= hi or abs(v) == 90.0):
            span = "[0, 90)" if lo == 0.0 else "(-90, 0]"
            raise ConfigError(f"{where}{key}: {v!r} is not allowed with projection = "
                              f"\"spherical\"; allowed: a number of degrees in {span}")
        out[key] = float(v)
    if out["fov_up_deg"] == out["fov_down_deg"]:
        raise ConfigError(f"{where}fov_up_deg, fov_down_deg: both 0; allowed: fov_up_deg above "
                          "fov_down_deg")
    return {"projection": kind, **out}


def _ring_offsets(raw: dict, rows: int, where: str) -> tuple[float, ...]:
    """`ring_offsets_m`: one finite number per row, each within MAX_RING_OFFSET_M (or absent)."""
    if "ring_offsets_m" not in raw:
        return ()
    v = raw["ring_offsets_m"]
    if not isinstance(v, list) or len(v) != rows or not all(
            isinstance(a, int | float) and not isinstance(a, bool) and math.isfinite(a)
            and abs(a) <= MAX_RING_OFFSET_M for a in v):
        raise ConfigError(f"{where}ring_offsets_m: expected a list of {rows} numbers (one per "
                          f"row, metres above the sensor origin), each within "
                          f"±{MAX_RING_OFFSET_M:g}")
    return tuple(float(a) for a in v)


def _finite(v: object) -> bool:
    """A finite int or float, not a bool (TOML's true would pass for 1)."""
    return isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)


def _flag(raw: dict, key: str, where: str) -> bool:
    v = raw.get(key, False)
    if not isinstance(v, bool):
        raise ConfigError(f"{where}{key}: expected true or false, got {v!r}")
    return v


def _returns_name(value, where: str, folder: Path) -> str:
    """A return model: the name of one in configs/returns/, a .json file (relative to the
    sensor's TOML) that `falsify fit-returns` wrote, or "" for none."""
    if value == "":
        return ""
    allowed = sorted(p.stem for p in RETURN_MODELS.glob("*.json"))
    if isinstance(value, str) and value.endswith(".json"):
        from falsify.sensor.returns import load_return_model

        path = (folder / value).resolve()
        try:
            load_return_model(str(path))
        except ConfigError as exc:
            raise ConfigError(f"{where}{exc}") from None
        return str(path)
    if not isinstance(value, str) or value not in allowed:
        raise ConfigError(f"{where}returns: {value!r} is not a fitted return model; allowed: "
                          f"{', '.join(allowed) or 'none'} (configs/returns/), a .json file "
                          "that `falsify fit-returns` wrote, or \"\"")
    return value
