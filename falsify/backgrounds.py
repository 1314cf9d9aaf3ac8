"""Procedural street backgrounds: one straight road along world x, fully determined by an id.

World frame: metres, origin on the road below the sensor, +x forward, +y left, +z up; the road
surface is z = 0. Every background keeps the free zone (x in [0, 25], y in [-8.5, 7.5]) flat,
empty road so sampled cars can go anywhere in it, and nothing but road lies within 3 m of the
sensor. Curbs stand at y = ±road_half_width (always ≥ 9 m); sidewalks, buildings, trees, poles,
fences, parked cars, pedestrians and cyclists lie beyond them or outside the free zone.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from falsify import shapes
from falsify.cars import BUILTIN_MODELS, car_mesh
from falsify.classes import CAR, CYCLIST, PEDESTRIAN, UNKNOWN
from falsify.errors import ConfigError

MAX_BACKGROUND_ID: int = 999_999
ROAD_X: tuple[float, float] = (-170.0, 230.0)  # road, sidewalks and terrain span this x range
FREE_ZONE: tuple[tuple[float, float], tuple[float, float]] = ((0.0, 25.0), (-8.5, 7.5))
SENSOR_CLEARANCE: float = 3.0  # metres around (0, 0) holding nothing but road
TERRAIN_HALF_WIDTH: float = 300.0  # flat ground beyond the curbs out to |y| = this

_FIRST_INSTANCE = 1000


@dataclass(frozen=True)
class Footprint:
    """A convex ground polygon (world x, y, counter-clockwise) that a sampled car must avoid."""

    label: str
    polygon: np.ndarray  # (K, 2) float64


@dataclass(frozen=True)
class Background:
    """The static street around the sensor: one triangle soup with per-face class and instance.

    ``road_half_width``: the curbs stand at y = ±road_half_width; the drivable road is
    |y| < road_half_width for x in ``road_x``. Arrays are read-only (the object is cached).
    """

    bg_id: int
    vertices: np.ndarray  # (N, 3) float64
    faces: np.ndarray  # (M, 3) int32
    face_class: np.ndarray  # (M,) uint8, 0 unknown, 1 car, 2 pedestrian, 3 cyclist
    face_instance: np.ndarray  # (M,) int32, 0 for stuff, >= 1000 per object instance
    obstacles: tuple[Footprint, ...]
    road_half_width: float
    curb_height: float = 0.15
    road_x: tuple[float, float] = ROAD_X


def _rect(x0: float, x1: float, y0: float, y1: float) -> np.ndarray:
    """Counter-clockwise axis-aligned rectangle polygon."""
    return np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]], dtype=np.float64)


def _quad(p0, p1, p2, p3) -> shapes.Mesh:
    """One planar quad; corners in counter-clockwise order seen from the front side."""
    v = np.array([p0, p1, p2, p3], dtype=np.float64)
    return v, np.array([[0, 1, 2], [0, 2, 3]], dtype=np.int64)


class _Street:
    """Accumulates meshes with labels, and the footprints used for placement and obstacles."""

    def __init__(self) -> None:
        self.meshes: list[shapes.Mesh] = []
        self.cls: list[int] = []
        self.inst: list[int] = []
        self.obstacles: list[Footprint] = []
        self.boxes: list[np.ndarray] = []  # (4,) x0, x1, y0, y1 of placed objects
        self.next_id = _FIRST_INSTANCE

    def add(self, mesh: shapes.Mesh, cls: int = UNKNOWN, instance: int = 0) -> None:
        self.meshes.append(mesh)
        self.cls.append(cls)
        self.inst.append(instance)

    def new_instance(self) -> int:
        self.next_id += 1
        return self.next_id - 1

    def fits(self, poly: np.ndarray, margin: float = 0.3) -> bool:
        """True when a footprint keeps off the free zone, the sensor and every placed object."""
        x0, y0 = poly.min(axis=0) - margin
        x1, y1 = poly.max(axis=0) + margin
        (fx0, fx1), (fy0, fy1) = FREE_ZONE
        if x1 > fx0 and x0 < fx1 and y1 > fy0 and y0 < fy1:
            return False
        dx = max(x0, 0.0, -x1)
        dy = max(y0, 0.0, -y1)
        if dx * dx + dy * dy < SENSOR_CLEARANCE**2:
            return False
        if self.boxes:
            b = np.asarray(self.boxes)
            hit = (x1 > b[:, 0]) & (x0 < b[:, 1]) & (y1 > b[:, 2]) & (y0 < b[:, 3])
            if hit.any():
                return False
        return True

    def occupy(self, label: str, poly: np.ndarray) -> None:
        self.obstacles.append(Footprint(label, poly))
        lo, hi = poly.min(axis=0), poly.max(axis=0)
        self.boxes.append(np.array([lo[0], hi[0], lo[1], hi[1]]))


@dataclass(frozen=True)
class _Layout:
    """The cross-section of one street, drawn from the background's random streams."""

    half_width: float
    curb_h: float
    sidewalk: tuple[float, float]  # sidewalk width on the left (+y) and right (-y) side
    parking: bool


def _rng(bg_id: int, stream: int) -> np.random.Generator:
    """Independent generator per aspect, so changing trees never moves the parked cars."""
    return np.random.default_rng([bg_id, stream])


def _layout(bg_id: int) -> _Layout:
    rng = _rng(bg_id, 0)
    lanes = int(rng.integers(4, 7))
    lane_w = rng.uniform(3.0, 3.7)
    parking = bool(rng.random() < 0.6)
    half = lanes * lane_w / 2 + (rng.uniform(2.2, 2.6) if parking else rng.uniform(0.0, 0.8))
    return _Layout(
        half_width=float(np.clip(half, 9.0, 15.0)),
        curb_h=float(rng.uniform(0.12, 0.18)),
        sidewalk=(float(rng.uniform(2.5, 6.0)), float(rng.uniform(2.5, 6.0))),
        parking=parking,
    )


def _ground(st: _Street, lay: _Layout) -> None:
    """Road at z = 0, vertical curb faces, and raised sidewalk/terrain out to the far field."""
    x0, x1 = ROAD_X
    hw, ch, far = lay.half_width, lay.curb_h, TERRAIN_HALF_WIDTH
    st.add(_quad([x0, -hw, 0], [x1, -hw, 0], [x1, hw, 0], [x0, hw, 0]))
    st.add(_quad([x0, hw, 0], [x1, hw, 0], [x1, hw, ch], [x0, hw, ch]))  # faces -y
    st.add(_quad([x1, -hw, 0], [x0, -hw, 0], [x0, -hw, ch], [x1, -hw, ch]))  # faces +y
    st.add(_quad([x0, hw, ch], [x1, hw, ch], [x1, far, ch], [x0, far, ch]))
    st.add(_quad([x0, -far, ch], [x1, -far, ch], [x1, -hw, ch], [x0, -hw, ch]))
    st.obstacles.append(Footprint("curb left", _rect(x0, x1, hw, far)))
    st.obstacles.append(Footprint("curb right", _rect(x0, x1, -far, -hw)))


def _buildings(st: _Street, lay: _Layout, bg_id: int) -> None:
    """Facade boxes with window frames, set back 2–15 m behind both sidewalks, gaps between."""
    rng = _rng(bg_id, 1)
    mean_h = rng.uniform(6.0, 22.0)
    gap_p = rng.uniform(0.1, 0.7)
    n_built = 0
    for side, sw in ((1, lay.sidewalk[0]), (-1, lay.sidewalk[1])):
        base_setback = rng.uniform(2.0, 15.0)
        x = ROAD_X[0] - rng.uniform(0.0, 20.0)
        while x < ROAD_X[1]:
            width = rng.uniform(8.0, 35.0)
            if rng.random() < gap_p:
                x += rng.uniform(2.0, 15.0)
            xa, xb = x, min(x + width, ROAD_X[1] + 10.0)
            x = xb
            if xb - xa < 4.0:
                continue
            setback = float(np.clip(base_setback + rng.normal(0.0, 2.0), 2.0, 15.0))
            depth = rng.uniform(8.0, 20.0)
            height = float(np.clip(rng.normal(mean_h, 0.35 * mean_h), 4.0, 30.0))
            near = lay.half_width + sw + setback
            ya, yb = (near, near + depth) if side > 0 else (-near - depth, -near)
            st.add(shapes.boxes([xa, ya, 0.0], [xb, yb, height]))
            st.occupy(f"building {n_built}", _rect(xa, xb, ya, yb))
            n_built += 1
            _facade(st, rng, xa, xb, side * near, side, height)


def _facade(st: _Street, rng: np.random.Generator, xa: float, xb: float, y_front: float,
            side: int, height: float) -> None:
    """Window frames and floor ledges standing out of the road-facing wall."""
    floor_h = rng.uniform(2.8, 3.6)
    floors = int((height - 1.0) // floor_h)
    pitch = rng.uniform(2.2, 3.6)
    n_win = int((xb - xa - 1.0) // pitch)
    if floors < 1 or n_win < 1:
        return
    win_w, win_h = min(1.4, pitch - 0.6), min(1.6, floor_h - 1.0)
    out = rng.uniform(0.06, 0.25)
    xc = xa + (xb - xa - (n_win - 1) * pitch) / 2 + pitch * np.arange(n_win)
    zc = 1.0 + floor_h * (np.arange(floors) + 0.5)
    gx, gz = np.meshgrid(xc, zc)
    gx, gz = gx.ravel(), gz.ravel()
    y0, y1 = sorted((y_front + 0.02 * side, y_front - out * side))
    lo = np.stack([gx - win_w / 2, np.full_like(gx, y0), gz - win_h / 2], axis=1)
    hi = np.stack([gx + win_w / 2, np.full_like(gx, y1), gz + win_h / 2], axis=1)
    # Sills under every window, standing out a little further than the frames.
    ys0, ys1 = sorted((y_front, y_front - (out + 0.12) * side))
    lo_s = np.stack([gx - win_w / 2 - 0.1, np.full_like(gx, ys0), gz - win_h / 2 - 0.1], axis=1)
    hi_s = np.stack([gx + win_w / 2 + 0.1, np.full_like(gx, ys1), gz - win_h / 2], axis=1)
    lo, hi = np.concatenate([lo, lo_s]), np.concatenate([hi, hi_s])
    # Floor ledges between storeys.
    lz = 1.0 + floor_h * np.arange(1, floors + 1) - 0.1
    lo2 = np.stack([np.full_like(lz, xa), np.full_like(lz, y0), lz], axis=1)
    hi2 = np.stack([np.full_like(lz, xb), np.full_like(lz, y1), lz + 0.2], axis=1)
    st.add(shapes.boxes(np.concatenate([lo, lo2]), np.concatenate([hi, hi2])))


def _fences(st: _Street, lay: _Layout, bg_id: int) -> None:
    """Walls, fences or hedges along the back of the sidewalk in some backgrounds."""
    rng = _rng(bg_id, 2)
    for side, sw in ((1, lay.sidewalk[0]), (-1, lay.sidewalk[1])):
        kind = rng.choice(["none", "wall", "fence", "hedge"], p=[0.4, 0.2, 0.2, 0.2])
        if kind == "none":
            continue
        y_in = side * (lay.half_width + sw + 0.1)
        x = ROAD_X[0] + rng.uniform(0.0, 10.0)
        n = 0
        while x < ROAD_X[1] - 5.0:
            length = rng.uniform(8.0, 40.0)
            xa, xb = x, min(x + length, ROAD_X[1])
            x = xb + rng.uniform(1.5, 12.0)
            thick = 0.2 if kind != "hedge" else rng.uniform(0.6, 1.2)
            ya, yb = sorted((y_in, y_in + side * thick))
            if kind == "wall":
                st.add(shapes.boxes([xa, ya, 0.0], [xb, yb, rng.uniform(0.6, 2.2)]))
            elif kind == "hedge":
                st.add(shapes.boxes([xa, ya, 0.0], [xb, yb, rng.uniform(0.8, 1.8)]))
            else:
                h = rng.uniform(1.0, 1.8)
                px = np.arange(xa, xb, 2.5)
                lo = np.stack([px, np.full_like(px, ya), np.zeros_like(px)], axis=1)
                hi = np.stack([px + 0.08, np.full_like(px, yb), np.full_like(px, h)], axis=1)
                rails = np.array([[xa, ya + 0.05, 0.35 * h], [xa, ya + 0.05, 0.9 * h]])
                rails_hi = np.array([[xb, yb - 0.05, 0.35 * h + 0.06], [xb, yb - 0.05, 0.9 * h]])
                rails_hi[1, 2] += 0.06
                st.add(shapes.boxes(np.concatenate([lo, rails]), np.concatenate([hi, rails_hi])))
            st.obstacles.append(Footprint(f"{kind} {n}", _rect(xa, xb, ya, yb)))
            n += 1


def _trees(st: _Street, lay: _Layout, bg_id: int) -> None:
    """Street trees on the sidewalks and in the front yards: trunk plus a round or conical crown."""
    rng = _rng(bg_id, 3)
    density = rng.uniform(0.0, 1.0)
    conifer_p = rng.uniform(0.0, 0.5)
    n = 0
    for side, sw in ((1, lay.sidewalk[0]), (-1, lay.sidewalk[1])):
        for zone in ("sidewalk", "yard"):
            if rng.random() > density:
                continue
            x = ROAD_X[0] + rng.uniform(0.0, 10.0)
            while x < ROAD_X[1]:
                x += rng.uniform(6.0, 16.0)
                if zone == "sidewalk":
                    if sw < 3.0:
                        break
                    off = lay.half_width + rng.uniform(1.5, sw - 0.8)
                else:
                    off = lay.half_width + sw + rng.uniform(0.8, 2.0)
                y = side * off
                trunk_r = rng.uniform(0.1, 0.25)
                poly = _rect(x - trunk_r, x + trunk_r, y - trunk_r, y + trunk_r)
                if not st.fits(poly, margin=0.2):
                    continue
                # Crowns overhang the road but stop 0.4 m short of the free zone (jitter ≤ 12 %).
                crown = min(rng.uniform(1.2, 3.2), (off - 8.9) / 1.12)
                if crown < 0.8:
                    continue
                trunk_h = rng.uniform(1.8, 3.5)
                iid = st.new_instance()
                ground = lay.curb_h
                st.add(shapes.cylinder([x, y, ground - 0.05], [x, y, ground + trunk_h + crown],
                                       trunk_r, 8, 0.6 * trunk_r), UNKNOWN, iid)
                if rng.random() < conifer_p:
                    top = ground + trunk_h + rng.uniform(2.5, 3.5) * crown
                    st.add(shapes.cylinder([x, y, ground + trunk_h], [x, y, top], crown, 10,
                                           0.0), UNKNOWN, iid)
                else:
                    v, f = shapes.icosphere([0, 0, 0], [crown, crown, crown * 0.9], 2)
                    v = v * rng.uniform(0.88, 1.12, size=(len(v), 1))
                    v += [x, y, ground + trunk_h + 0.8 * crown]
                    st.add((v, f), UNKNOWN, iid)
                st.occupy(f"tree {n}", poly)
                n += 1


def _poles(st: _Street, lay: _Layout, bg_id: int) -> None:
    """Street lights with arms over the road, and sign posts, along both curbs."""
    rng = _rng(bg_id, 4)
    spacing = rng.uniform(18.0, 45.0)
    n = 0
    for side in (1, -1):
        x = ROAD_X[0] + rng.uniform(0.0, spacing)
        while x < ROAD_X[1]:
            off = lay.half_width + rng.uniform(0.35, 0.7)
            y = side * off
            poly = _rect(x - 0.15, x + 0.15, y - 0.15, y + 0.15)
            if st.fits(poly, margin=0.1):
                iid = st.new_instance()
                base = lay.curb_h
                if rng.random() < 0.75:
                    h = rng.uniform(6.0, 10.0)
                    arm_end = max(off - rng.uniform(1.0, 2.5), 8.8)
                    st.add(shapes.cylinder([x, y, base], [x, y, base + h], 0.1, 8, 0.07),
                           UNKNOWN, iid)
                    st.add(shapes.boxes([x - 0.05, min(y, side * arm_end), base + h - 0.3],
                                        [x + 0.05, max(y, side * arm_end), base + h - 0.2]),
                           UNKNOWN, iid)
                    ye = side * arm_end
                    st.add(shapes.boxes([x - 0.3, ye - 0.15, base + h - 0.45],
                                        [x + 0.3, ye + 0.15, base + h - 0.25]), UNKNOWN, iid)
                else:
                    h = rng.uniform(2.2, 3.2)
                    st.add(shapes.cylinder([x, y, base], [x, y, base + h], 0.04, 6), UNKNOWN,
                           iid)
                    st.add(shapes.boxes([x - 0.02, y - 0.35, base + h - 0.7],
                                        [x + 0.02, y + 0.35, base + h]), UNKNOWN, iid)
                st.occupy(f"pole {n}", poly)
                n += 1
            x += spacing * rng.uniform(0.7, 1.3)


def _place_mesh(st: _Street, v: np.ndarray, f: np.ndarray, x: float, y: float, z: float,
                yaw: float, cls: int, label: str) -> None:
    """Add one labelled object instance turned by ``yaw`` and record its footprint."""
    v = shapes.rotate_z(v, yaw) + [x, y, z]
    iid = st.new_instance()
    st.add((v, f), cls, iid)
    st.occupy(label, _footprint(v))


def _footprint(v: np.ndarray) -> np.ndarray:
    """Oriented bounding rectangle of an object's (x, y) points, counter-clockwise."""
    xy = v[:, :2]
    c = xy.mean(axis=0)
    d = xy - c
    # Principal axis of the footprint gives the heading for car-like objects.
    cov = d.T @ d
    _, vec = np.linalg.eigh(cov)
    ax = vec[:, 1]
    perp = np.array([-ax[1], ax[0]])
    a, b = d @ ax, d @ perp
    corners = np.array([[a.min(), b.min()], [a.max(), b.min()], [a.max(), b.max()],
                        [a.min(), b.max()]])
    return c + corners[:, :1] * ax + corners[:, 1:] * perp


def _candidate_footprint(length: float, width: float, x: float, y: float,
                         yaw: float) -> np.ndarray:
    """Rectangle of a car-like object about to be placed, for the fits() check."""
    c, s = np.cos(yaw), np.sin(yaw)
    loc = np.array([[-length, -width], [length, -width], [length, width], [-length, width]]) / 2
    return loc @ np.array([[c, s], [-s, c]]) + [x, y]


def _parked_cars(st: _Street, lay: _Layout, bg_id: int) -> None:
    """Cars parked along both curbs, at least one 30–60 m ahead; lod 1 within x in
    (-100, 140), lod 0 beyond (those are seen by few rays and cost BVH build time)."""
    rng = _rng(bg_id, 5)
    occupancy = rng.uniform(0.3, 0.7)
    forced_side = int(rng.choice([1, -1]))
    n = 0
    for side in (1, -1):
        forced = side == forced_side
        x = -120.0 + rng.uniform(0.0, 6.0)
        while x < 175.0:
            name = str(rng.choice(BUILTIN_MODELS))
            lod = 1 if -100.0 < x < 140.0 else 0
            mesh = car_mesh(name, lod)
            length, width = float(mesh.extents[0]), float(mesh.extents[1])
            cx = x + length / 2
            x += length + rng.uniform(0.8, 6.0)
            want = rng.random() < occupancy
            if forced and 30.0 < cx < 60.0:
                want, forced = True, False
            # Right-hand traffic: most cars on the left curb face -x.
            heading = 0.0 if (side < 0) != (rng.random() < 0.15) else np.pi
            yaw = heading + rng.normal(0.0, 0.03)
            cy = side * (lay.half_width - 0.25 - width / 2 - rng.uniform(0.0, 0.3))
            if not want or not st.fits(_candidate_footprint(length, width, cx, cy, yaw), 0.2):
                continue
            _place_mesh(st, np.asarray(mesh.vertices), np.asarray(mesh.faces), cx, cy, 0.0,
                        yaw, CAR, f"parked car {n}")
            n += 1


def _people(st: _Street, lay: _Layout, bg_id: int) -> None:
    """Pedestrians on the sidewalks (a few crossing far ahead) and cyclists at the road edge."""
    rng = _rng(bg_id, 6)
    n_ped = int(rng.integers(2, 15))
    placed = 0
    for i in range(n_ped * 4):
        if placed == n_ped:
            break
        side = 1 if rng.random() < 0.5 else -1
        sw = lay.sidewalk[0] if side > 0 else lay.sidewalk[1]
        crossing = i > 0 and rng.random() < 0.12
        if crossing:
            x, y, z = rng.uniform(32.0, 90.0), rng.uniform(-lay.half_width + 1,
                                                          lay.half_width - 1), 0.0
        else:
            x = rng.uniform(8.0, 45.0) if placed == 0 else rng.uniform(-60.0, 120.0)
            y, z = side * (lay.half_width + rng.uniform(0.5, sw - 0.5)), lay.curb_h
        poly = _rect(x - 0.4, x + 0.4, y - 0.4, y + 0.4)
        if not st.fits(poly, 0.2):
            continue
        v, f = shapes.person(rng.uniform(1.5, 1.95), rng.uniform(0.0, 0.55), rng.uniform(0, 0.3))
        yaw = rng.uniform(-np.pi, np.pi)
        _place_mesh(st, v, f, x, y, z, yaw, PEDESTRIAN, f"pedestrian {placed}")
        placed += 1

    n_cyc = int(rng.integers(1, 5))
    placed = 0
    for i in range(n_cyc * 6):
        if placed == n_cyc:
            break
        side = 1 if rng.random() < 0.5 else -1
        sw = lay.sidewalk[0] if side > 0 else lay.sidewalk[1]
        if i < 6 and placed == 0:
            x = rng.uniform(28.0, 55.0)
        else:
            x = rng.uniform(-60.0, -6.0) if rng.random() < 0.3 else rng.uniform(28.0, 120.0)
        if rng.random() < 0.7 or sw < 3.0:
            y, z = side * (lay.half_width - rng.uniform(0.6, 1.3)), 0.0
        else:
            y, z = side * (lay.half_width + rng.uniform(1.0, sw - 1.0)), lay.curb_h
        heading = (0.0 if side < 0 else np.pi) + rng.normal(0.0, 0.08)
        if not st.fits(_candidate_footprint(1.8, 0.7, x, y, heading), 0.3):
            continue
        v, f = shapes.cyclist(rng.uniform(1.6, 1.9))
        _place_mesh(st, v, f, x, y, z, heading, CYCLIST, f"cyclist {placed}")
        placed += 1


def _assemble(bg_id: int, st: _Street, lay: _Layout) -> Background:
    """Merge the pieces into one float64/int32 triangle soup and freeze the arrays."""
    counts = np.array([len(f) for _, f in st.meshes])
    offsets = np.cumsum([0] + [len(m[0]) for m in st.meshes[:-1]])
    v = np.concatenate([m[0] for m in st.meshes]).astype(np.float64)
    f = np.concatenate([m[1] + o for m, o in zip(st.meshes, offsets, strict=True)])
    keep = shapes.drop_degenerate(v, f)  # lofts and lathes leave collapsed triangles
    cls = np.repeat(np.array(st.cls, dtype=np.uint8), counts)[keep]
    inst = np.repeat(np.array(st.inst, dtype=np.int32), counts)[keep]
    f = f[keep]
    faces = f.astype(np.int32)
    for arr in (v, faces, cls, inst):
        arr.setflags(write=False)
    return Background(bg_id=bg_id, vertices=v, faces=faces, face_class=cls,
                      face_instance=inst, obstacles=tuple(st.obstacles),
                      road_half_width=lay.half_width, curb_height=lay.curb_h)


def build_background(bg_id: int) -> Background:
    """The street for ``bg_id`` in [0, MAX_BACKGROUND_ID]; the same id always gives the same
    bytes. Cached: the returned object and its arrays are shared and read-only."""
    if isinstance(bg_id, bool) or not isinstance(bg_id, int | np.integer):
        raise ConfigError(f"background: {bg_id!r} is not an integer id; "
                          f"allowed: 0..{MAX_BACKGROUND_ID}")
    if not 0 <= int(bg_id) <= MAX_BACKGROUND_ID:
        raise ConfigError(f"background: id {bg_id} is out of range; "
                          f"allowed: 0..{MAX_BACKGROUND_ID}")
    return _build(int(bg_id))


@functools.lru_cache(maxsize=16)
def _build(bg_id: int) -> Background:
    lay = _layout(bg_id)
    st = _Street()
    _ground(st, lay)
    # Dynamic objects first (they are guaranteed their slots), then street furniture.
    _parked_cars(st, lay, bg_id)
    _people(st, lay, bg_id)
    _poles(st, lay, bg_id)
    _trees(st, lay, bg_id)
    _fences(st, lay, bg_id)
    _buildings(st, lay, bg_id)
    return _assemble(bg_id, st, lay)
