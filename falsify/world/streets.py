"""Procedural street backgrounds: one straight road along world x, fully determined by an id.

World frame: metres, origin on the road's crown below the sensor, +x forward, +y left, +z up.
The ground is a seeded `falsify.world.terrain.Terrain`: the road has a grade, long crests and a
crowned camber; kerbs, sidewalks, then per side a roadside (grass verge, ditch, embankment up
or down, rising fields) with height noise. Every background keeps the free zone (x in [0, 25],
y in [-8.5, 7.5]) empty road so sampled cars can go anywhere in it (they stand on the terrain),
and nothing but road lies within 3 m of the sensor. Kerbs stand at y = ±road_half_width (always
≥ 9 m along the free zone; half the streets (NARROW_P) narrow beyond it, kerbs 3.5-6.5 m from
the centre); sidewalks, buildings, walls, fences, railings, guard rails, hedges, bushes, trees (and
the far band of trees), poles, signs, parked cars, vans, trucks, buses, trailers, bicycles,
pedestrians and cyclists lie beyond them or outside the free zone. Every triangle carries a
class, a material (falsify.world.materials) and a raw SemanticKITTI id (falsify.semantic).
Which mix a street gets is drawn from its id, so the 15 backgrounds of configs/paper.toml are
different places. About one street in four (TOWN_P) is a town street, enclosed like the KITTI
frames' residential streets: flat roadsides, the narrowest road the free zone allows, narrow
sidewalks and blocks on both sides close behind them.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from falsify.classes import CAR, CYCLIST, PEDESTRIAN, UNKNOWN
from falsify.errors import ConfigError
from falsify.rotations import rot_x, rot_y, rot_z
from falsify.semantic import RAW_ID
from falsify.world import buildings, shapes, vegetation
from falsify.world.cars import BUILTIN_MODELS, car_parts
from falsify.world.materials import PAINTS, mid
from falsify.world.road_users import (
    BICYCLE_SEMANTIC,
    OTHER_VEHICLE_SEMANTIC,
    OTHER_VEHICLES,
    bicycle_parts,
    merge_parts,
    pedestrian_parts,
    vehicle_parts,
)
from falsify.world.terrain import Terrain, draw_terrain, terrain_meshes

MAX_BACKGROUND_ID: int = 999_999
KERB_OBSTACLE: str = "curb"   # the label the kerbs' obstacle outlines start with
ROAD_X: tuple[float, float] = (-170.0, 230.0)  # road, sidewalks and terrain span this x range
FREE_ZONE: tuple[tuple[float, float], tuple[float, float]] = ((0.0, 25.0), (-8.5, 7.5))
SENSOR_CLEARANCE: float = 3.0  # metres around (0, 0) holding nothing but road
TERRAIN_HALF_WIDTH: float = 300.0  # the ground reaches out to |y| = this

_FIRST_INSTANCE = 1000
_DEFAULT_MAT = mid("concrete")
# Our classes (unknown, car, pedestrian, cyclist) as raw SemanticKITTI ids, for pieces that name
# no id of their own: unknown stays 0 "unlabeled".
SEMANTIC_OF_CLASS = np.array([0, RAW_ID["car"], RAW_ID["person"], RAW_ID["bicyclist"]],
                             np.uint16)


@dataclass(frozen=True)
class Footprint:
    """A convex ground polygon (world x, y, counter-clockwise) that a sampled car must avoid."""

    label: str
    polygon: np.ndarray  # (K, 2) float64
    instance: int = 0    # the object's face_instance; 0 for stuff (kerbs)


@dataclass(frozen=True)
class Background:
    """The static street around the sensor: one triangle soup with per-face class, instance,
    material and raw SemanticKITTI id, and the terrain it stands on.

    ``road_half_width``: the kerbs stand at y = ±road_half_width; the drivable road is
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
    face_material: np.ndarray | None = None  # (M,) uint8 material ids; None: concrete
    terrain: Terrain | None = None  # None: the flat plane z = 0
    face_semantic: np.ndarray | None = None  # (M,) uint16 raw SemanticKITTI ids; None: by class

    def materials(self) -> np.ndarray:
        """Per-face material ids (concrete everywhere for a background built without them)."""
        if self.face_material is not None:
            return self.face_material
        return np.full(len(self.faces), _DEFAULT_MAT, np.uint8)

    def semantics(self) -> np.ndarray:
        """Per-face raw SemanticKITTI ids; derived from the classes (car 10, pedestrian 30,
        cyclist 31, else 0) when there are none or they do not match the faces (a background
        whose faces were replaced without them)."""
        if self.face_semantic is not None and len(self.face_semantic) == len(self.faces):
            return self.face_semantic
        return SEMANTIC_OF_CLASS[self.face_class]


def _rect(x0: float, x1: float, y0: float, y1: float) -> np.ndarray:
    """Counter-clockwise axis-aligned rectangle polygon."""
    return np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]], dtype=np.float64)


class _Street:
    """Accumulates meshes with labels and materials, and the footprints used for placement."""

    def __init__(self) -> None:
        self.meshes: list[shapes.Mesh] = []
        self.cls: list[int] = []
        self.inst: list[int] = []
        self.mat: list[np.ndarray] = []
        self.sem: list[np.ndarray] = []  # raw SemanticKITTI ids per face
        self.obstacles: list[Footprint] = []
        self.boxes: list[np.ndarray] = []  # (4,) x0, x1, y0, y1 of placed objects
        self.next_id = _FIRST_INSTANCE

    def add(self, mesh: shapes.Mesh, cls: int = UNKNOWN, instance: int = 0,
            mat: int | np.ndarray = _DEFAULT_MAT, sem: int | np.ndarray | None = None) -> None:
        """Add a mesh; `mat` is one material id or one per face, `sem` one raw SemanticKITTI id
        or one per face (None: the class's, SEMANTIC_OF_CLASS)."""
        self.meshes.append(mesh)
        self.cls.append(cls)
        self.inst.append(instance)
        self.mat.append(np.broadcast_to(np.asarray(mat, np.uint8), (len(mesh[1]),)))
        if sem is None:
            sem = SEMANTIC_OF_CLASS[cls]
        self.sem.append(np.broadcast_to(np.asarray(sem, np.uint16), (len(mesh[1]),)))

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

    def occupy(self, label: str, poly: np.ndarray, instance: int = 0) -> None:
        self.obstacles.append(Footprint(label, poly, instance))
        lo, hi = poly.min(axis=0), poly.max(axis=0)
        self.boxes.append(np.array([lo[0], hi[0], lo[1], hi[1]]))


@dataclass(frozen=True)
class _Layout:
    """The cross-section of one street, drawn from the background's random streams."""

    half_width: float
    curb_h: float
    sidewalk: tuple[float, float]  # sidewalk width on the left (+y) and right (-y) side
    parking: bool
    terrain: Terrain
    town: bool = False  # a town street: flat roadsides, blocks close behind narrow sidewalks


# Town streets (fitted on the KITTI object frames' geometry only; README, realism): the
# road as narrow as the free zone allows, narrow sidewalks, blocks on both sides close behind
# them, as in the residential streets the KITTI frames were driven through.
TOWN_P: float = 0.25
TOWN_HALF_WIDTH: tuple[float, float] = (9.0, 10.0)
TOWN_SIDEWALK: tuple[float, float] = (1.5, 3.5)
TOWN_SETBACK: tuple[float, float] = (1.5, 5.0)  # blocks behind the sidewalk (front gardens)


# Narrowing streets: the road keeps the paper's width along the test site (the free zone's x
# and a margin each way) and narrows to a residential street beyond it, where about a third of
# training scenes stand (their ego stands anywhere in x -90..90: scene.EGO_X_FORWARD).
NARROW_P: float = 0.5
NARROW_KERB: tuple[float, float] = (3.5, 6.5)         # |y| of the kerbs where narrow
NARROW_WIDE_BEHIND: tuple[float, float] = (5.0, 20.0)  # wide stretch starts this far behind x=0
NARROW_WIDE_AHEAD: tuple[float, float] = (12.0, 30.0)  # and ends this far beyond the free zone
NARROW_TAPER: tuple[float, float] = (6.0, 15.0)       # metres over which the kerbs move in
NEAR_ZONE: float = 5.0  # objects this close to the free zone's x range keep off its y range


def _near_zone(x: float) -> bool:
    (x0, x1), _ = FREE_ZONE
    return x0 - NEAR_ZONE < x < x1 + NEAR_ZONE


def _rng(bg_id: int, stream: int) -> np.random.Generator:
    """Independent generator per aspect, so changing trees never moves the parked cars."""
    return np.random.default_rng([bg_id, stream])


def _layout(bg_id: int) -> _Layout:
    rng = _rng(bg_id, 0)
    lanes = int(rng.integers(4, 7))
    lane_w = rng.uniform(3.0, 3.7)
    parking = bool(rng.random() < 0.6)
    half = lanes * lane_w / 2 + (rng.uniform(2.2, 2.6) if parking else rng.uniform(0.0, 0.8))
    half = float(np.clip(half, 9.0, 15.0))
    curb_h = float(rng.uniform(0.1, 0.18))
    sidewalk = (float(rng.uniform(1.5, 6.0)), float(rng.uniform(1.5, 6.0)))
    town_rng = _rng(bg_id, 9)  # its own stream: other streets keep every draw they had
    town = bool(town_rng.random() < TOWN_P)
    if town:
        half = float(town_rng.uniform(*TOWN_HALF_WIDTH))
        sidewalk = (float(town_rng.uniform(*TOWN_SIDEWALK)),
                    float(town_rng.uniform(*TOWN_SIDEWALK)))
    narrow_rng = _rng(bg_id, 10)  # its own stream, as for town streets
    narrowing = None
    if narrow_rng.random() < NARROW_P:
        kerb = float(narrow_rng.uniform(*NARROW_KERB))
        wide_x = (FREE_ZONE[0][0] - float(narrow_rng.uniform(*NARROW_WIDE_BEHIND)),
                  FREE_ZONE[0][1] + float(narrow_rng.uniform(*NARROW_WIDE_AHEAD)))
        narrowing = (max(half - kerb, 0.0), wide_x, float(narrow_rng.uniform(*NARROW_TAPER)))
    terrain = draw_terrain(_rng(bg_id, 7), half, curb_h, sidewalk, flat_sides=town,
                           narrowing=narrowing)
    return _Layout(half_width=half, curb_h=curb_h, sidewalk=sidewalk, parking=parking,
                   terrain=terrain, town=town)


def _side_kind(lay: _Layout, side: int) -> str:
    return lay.terrain.sides[0 if side > 0 else 1].kind


# The ground's pieces by material (terrain_meshes): the road surface is road (one mesh from kerb
# to kerb, so there is no separate parking lane), kerb faces and sidewalks sidewalk (SemanticKITTI
# counts kerbs as sidewalk), verges, ditches, embankments and fields terrain.
_GROUND_SEMANTIC: dict[int, int] = {mid("asphalt"): RAW_ID["road"],
                                    mid("concrete"): RAW_ID["sidewalk"],
                                    mid("grass"): RAW_ID["terrain"], mid("soil"): RAW_ID["terrain"]}


def _ground(st: _Street, lay: _Layout) -> None:
    """Road, kerb faces, sidewalks and the roadsides out to the far field."""
    x0, x1 = ROAD_X
    for mesh, mat in terrain_meshes(lay.terrain, ROAD_X, TERRAIN_HALF_WIDTH):
        st.add(mesh, UNKNOWN, 0, mat, _GROUND_SEMANTIC[mat])
    t, far = lay.terrain, TERRAIN_HALF_WIDTH
    br = t.kerb_breaks(x0, x1)
    for k, (u, v) in enumerate(zip(br[:-1], br[1:], strict=False)):
        ku, kv = float(t.kerb(u)), float(t.kerb(v))
        tag = "" if k == 0 else f" {k}"
        st.obstacles.append(Footprint(f"{KERB_OBSTACLE} left{tag}", np.array(
            [[u, ku], [v, kv], [v, far], [u, far]], dtype=np.float64)))
        st.obstacles.append(Footprint(f"{KERB_OBSTACLE} right{tag}", np.array(
            [[u, -far], [v, -far], [v, -kv], [u, -ku]], dtype=np.float64)))


def _slope_top(lay: _Layout, side: int) -> float:
    """u (beyond the sidewalk) where an embankment's slope ends; 0 for level roadsides."""
    s = lay.terrain.sides[0 if side > 0 else 1]
    if s.kind == "embankment up":
        return float(s.knots[3][0])
    return 0.0


def _buildings(st: _Street, lay: _Layout, bg_id: int) -> None:
    """Blocks with recessed glass windows behind level sidewalks or on top of embankments."""
    rng = _rng(bg_id, 1)
    mean_h = rng.uniform(6.0, 22.0)
    gap_p = rng.uniform(0.1, 0.7)
    if lay.town:
        gap_p *= 0.3
    n_built = 0
    for side, sw in ((1, lay.sidewalk[0]), (-1, lay.sidewalk[1])):
        kind = _side_kind(lay, side)
        build_p = {"flat": 0.9, "ditch": 0.35, "embankment up": 0.3, "hill": 0.25}.get(kind, 0.0)
        if rng.random() >= build_p and not lay.town:
            continue
        base_setback = rng.uniform(2.0, 15.0) + _slope_top(lay, side)
        if lay.town:  # the same draw mapped into TOWN_SETBACK, so the stream keeps its order
            base_setback = TOWN_SETBACK[0] + (base_setback - 2.0) / 13.0 * (
                TOWN_SETBACK[1] - TOWN_SETBACK[0])
        x = ROAD_X[0] - rng.uniform(0.0, 20.0)
        while x < ROAD_X[1]:
            width = rng.uniform(8.0, 35.0)
            if rng.random() < gap_p:
                x += rng.uniform(2.0, 15.0)
            xa, xb = x, min(x + width, ROAD_X[1] + 10.0)
            x = xb
            if xb - xa < 4.0:
                continue
            setback = float(np.clip(base_setback + rng.normal(0.0, 2.0), 2.0, 40.0))
            depth = rng.uniform(8.0, 20.0)
            height = float(np.clip(rng.normal(mean_h, 0.35 * mean_h), 4.0, 30.0))
            near = lay.terrain.widest_kerb(xa, xb) + sw + setback
            ya, yb = (near, near + depth) if side > 0 else (-near - depth, -near)
            if not st.fits(_rect(xa, xb, ya, yb), margin=0.0):
                continue
            buildings.building(st, lay.terrain, rng, xa, xb, near, depth, height, side,
                                f"building {n_built}")
            n_built += 1


def _guard_rails(st: _Street, lay: _Layout, bg_id: int) -> None:
    """A guard rail at the road edge where the ground falls away. Placed before the poles and
    signs, which stand on the same line: placed after them, 88 of 92 rail stretches over 60
    streets found a pole or sign in the way and were dropped."""
    rng = _rng(bg_id, 11)
    n = 0
    for side, sw in ((1, lay.sidewalk[0]), (-1, lay.sidewalk[1])):
        if _side_kind(lay, side) not in ("embankment down", "ditch") or rng.random() >= 0.7:
            continue
        x = ROAD_X[0] + rng.uniform(0.0, 20.0)
        while x < ROAD_X[1] - 5.0:
            xa, xb = x, min(x + rng.uniform(30.0, 120.0), ROAD_X[1])
            for pa, pb in lay.terrain.straight_kerb(xa, xb):  # none along a taper
                y = side * (float(lay.terrain.kerb(pa)) + min(0.6, sw / 2))
                if pb - pa > 6.0 and st.fits(_rect(pa, pb, y - 0.3, y + 0.3), 0.0):
                    buildings.guard_rail(st, lay.terrain, rng, pa, pb, y, side,
                                          f"guard rail {n}")
                    n += 1
            x = xb + rng.uniform(3.0, 40.0)


def _boundaries(st: _Street, lay: _Layout, bg_id: int) -> None:
    """Along the back of each sidewalk: walls, chain-link fences, railings or hedges."""
    rng = _rng(bg_id, 2)
    for side, sw in ((1, lay.sidewalk[0]), (-1, lay.sidewalk[1])):
        what = str(rng.choice(["none", "wall", "fence", "railing", "hedge"],
                              p=[0.25, 0.2, 0.2, 0.15, 0.2]))
        if what == "none":
            continue
        x = ROAD_X[0] + rng.uniform(0.0, 10.0)
        n = 0
        while x < ROAD_X[1] - 5.0:
            xa, xb = x, min(x + rng.uniform(8.0, 40.0), ROAD_X[1])
            x = xb + rng.uniform(1.5, 12.0)
            for pa, pb in lay.terrain.straight_kerb(xa, xb):  # none along a taper
                y_in = side * (float(lay.terrain.kerb(pa)) + sw + 0.1)
                lo, hi = sorted((y_in, y_in + side * 1.3))
                if not st.fits(_rect(pa, pb, lo, hi), 0.0):
                    continue
                build = {"wall": buildings.wall, "fence": buildings.fence,
                         "railing": buildings.railing, "hedge": vegetation.hedge}[what]
                build(st, lay.terrain, rng, pa, pb, y_in, side, f"{what} {n}")
                n += 1


def _plants(st: _Street, lay: _Layout, bg_id: int) -> None:
    """Street trees on sidewalks and verges, bushes on the roadsides (thick on embankments),
    and the far band of trees toward the horizon."""
    rng = _rng(bg_id, 3)
    density = rng.uniform(0.0, 1.0)
    conifer_p = rng.uniform(0.0, 0.5)
    t = lay.terrain
    n = 0
    for side, sw in ((1, lay.sidewalk[0]), (-1, lay.sidewalk[1])):
        for zone in ("sidewalk", "verge"):
            if rng.random() > density:
                continue
            x = ROAD_X[0] + rng.uniform(0.0, 10.0)
            while x < ROAD_X[1]:
                x += rng.uniform(6.0, 16.0)
                kerb = float(t.kerb(x))
                if zone == "sidewalk":
                    if sw < 3.0:
                        break
                    off = kerb + rng.uniform(1.5, sw - 0.8)
                else:
                    off = kerb + sw + rng.uniform(0.8, 4.0)
                # Crowns overhang the road but stop short of the free zone (jitter <= 15 %);
                # away from it, up to 2 m over a narrowed road.
                edge = 8.9 if t.narrow == 0.0 or _near_zone(x) else kerb - 2.0
                crown = min(rng.uniform(1.2, 3.5), (off - edge) / 1.2)
                if crown < 0.8:
                    continue
                if vegetation.tree(st, t, rng, x, side * off, crown, rng.random() < conifer_p,
                                   f"tree {n}"):
                    n += 1
        kind = _side_kind(lay, side)
        bush_density = {"flat": 0.01, "ditch": 0.03, "embankment up": 0.08,
                        "embankment down": 0.05, "hill": 0.04}[kind] * rng.uniform(0.3, 1.5)
        vegetation.bushes(st, t, rng, side, (0.5, 35.0), (-60.0, 130.0), bush_density)
        if rng.random() < 0.8:
            near = rng.uniform(12.0, 40.0) + _slope_top(lay, side)
            vegetation.tree_band(st, t, rng, side, near, (-90.0, 160.0),
                                 rng.uniform(6.0, 30.0), rng.uniform(4.0, 9.0))


def _poles(st: _Street, lay: _Layout, bg_id: int) -> None:
    """Street lights with arms over the road, and signs with retro-reflective plates."""
    rng = _rng(bg_id, 4)
    spacing = rng.uniform(18.0, 45.0)
    t = lay.terrain
    n = 0
    for side in (1, -1):
        x = ROAD_X[0] + rng.uniform(0.0, spacing)
        while x < ROAD_X[1]:
            kerb = float(t.kerb(x))
            off = kerb + rng.uniform(0.35, 0.7)
            y = side * off
            poly = _rect(x - 0.15, x + 0.15, y - 0.15, y + 0.15)
            if rng.random() < 0.7:
                if st.fits(poly, margin=0.1):
                    iid = st.new_instance()
                    base = float(t.height(np.array([x]), np.array([y]))[0])
                    h = rng.uniform(6.0, 10.0)
                    edge = 8.8 if t.narrow == 0.0 or _near_zone(x) else kerb - 2.5
                    arm_end = max(off - rng.uniform(1.0, 2.5), edge)
                    # A street light is pole throughout (SemanticKITTI: lamp posts), its arm
                    # and lamp head too.
                    st.add(shapes.cylinder([x, y, base - 0.1], [x, y, base + h], 0.1, 8, 0.07),
                           UNKNOWN, iid, mid("metal"), RAW_ID["pole"])
                    st.add(shapes.boxes([x - 0.05, min(y, side * arm_end), base + h - 0.3],
                                        [x + 0.05, max(y, side * arm_end), base + h - 0.2]),
                           UNKNOWN, iid, mid("metal"), RAW_ID["pole"])
                    ye = side * arm_end
                    st.add(shapes.boxes([x - 0.3, ye - 0.15, base + h - 0.45],
                                        [x + 0.3, ye + 0.15, base + h - 0.25]), UNKNOWN, iid,
                           mid("metal"), RAW_ID["pole"])
                    st.occupy(f"pole {n}", poly)
                    n += 1
            elif buildings.sign(st, t, rng, x, y, side, f"sign {n}"):
                n += 1
            x += spacing * rng.uniform(0.7, 1.3)


def _place(st: _Street, t: Terrain, v: np.ndarray, f: np.ndarray, mat: np.ndarray | int,
           x: float, y: float, yaw: float, cls: int, label: str, sem: int | None = None) -> None:
    """Add one labelled object instance turned by ``yaw`` (radians), standing on the ground;
    ``sem``: its raw SemanticKITTI id (None: its class's)."""
    lo, hi = v.min(axis=0), v.max(axis=0)
    hl, hw = max((hi[0] - lo[0]) / 2 - 0.3, 0.2), max((hi[1] - lo[1]) / 2 - 0.1, 0.2)
    z, pitch, roll = t.pose_on(x, y, math.degrees(yaw), hl, hw)
    rot = rot_z(math.degrees(yaw)) @ rot_y(pitch) @ rot_x(roll)
    v = v @ rot.T + [x, y, z]
    iid = st.new_instance()
    st.add((v, f), cls, iid, mat, sem)
    st.occupy(label, _footprint(v), iid)


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


def _parked_vehicles(st: _Street, lay: _Layout, bg_id: int) -> None:
    """Cars (and vans, trucks, buses, trailers: class 0) parked along both kerbs, at least one
    car 30-60 m ahead; lod 1 within x in (-100, 140), lod 0 beyond (seen by few rays)."""
    rng = _rng(bg_id, 5)
    occupancy = rng.uniform(0.3, 0.7)
    other_p = rng.uniform(0.05, 0.3)
    forced_side = int(rng.choice([1, -1]))
    n = 0
    for side in (1, -1):
        forced = side == forced_side
        x = -120.0 + rng.uniform(0.0, 6.0)
        while x < 175.0:
            lod = 1 if -100.0 < x < 140.0 else 0
            if rng.random() < other_p and not (forced and x > 20.0):
                kind = str(rng.choice(OTHER_VEHICLES))
                v, f, mat = merge_parts(vehicle_parts(kind, rng))
                cls, label, sem = UNKNOWN, f"parked {kind} {n}", OTHER_VEHICLE_SEMANTIC[kind]
            else:
                name = str(rng.choice(BUILTIN_MODELS))
                v, f, mat = car_parts(name, lod)
                mat = np.where(mat == mid("paint mid"), PAINTS[int(rng.integers(3))], mat)
                cls, label, sem = CAR, f"parked car {n}", RAW_ID["car"]
            length, width = float(np.ptp(v[:, 0])), float(np.ptp(v[:, 1]))
            cx = x + length / 2
            x += length + rng.uniform(0.8, 6.0)
            want = rng.random() < occupancy
            if forced and cls == CAR and 30.0 < cx < 60.0:
                want, forced = True, False
            # Right-hand traffic: most vehicles on the left kerb face -x.
            heading = 0.0 if (side < 0) != (rng.random() < 0.15) else np.pi
            yaw = heading + rng.normal(0.0, 0.03)
            kerb = lay.terrain.narrowest_kerb(cx - length / 2, cx + length / 2)
            cy = side * (kerb - 0.25 - width / 2 - rng.uniform(0.0, 0.3))
            if not want or not st.fits(_candidate_footprint(length, width, cx, cy, yaw), 0.2):
                continue
            _place(st, lay.terrain, np.asarray(v), np.asarray(f), mat, cx, cy, yaw, cls, label,
                   sem)
            n += 1


def _people(st: _Street, lay: _Layout, bg_id: int) -> None:
    """Pedestrians on the sidewalks (a few crossing far ahead), cyclists at the road edge and
    bicycles parked on the sidewalks (class 0: no rider)."""
    rng = _rng(bg_id, 6)
    t = lay.terrain
    n_ped = int(rng.integers(2, 15))
    placed = 0
    for i in range(n_ped * 4):
        if placed == n_ped:
            break
        side, sw = _side(rng, lay)
        crossing = i > 0 and rng.random() < 0.12
        if crossing:
            x = rng.uniform(32.0, 90.0)
            y = rng.uniform(-lay.half_width + 1, lay.half_width - 1) * _kerb_scale(t, x, 1.0)
        else:
            x = rng.uniform(8.0, 45.0) if placed == 0 else rng.uniform(-60.0, 120.0)
            y = side * (float(t.kerb(x)) + rng.uniform(0.4, max(sw - 0.4, 0.5)))
        poly = _rect(x - 0.4, x + 0.4, y - 0.4, y + 0.4)
        if not st.fits(poly, 0.2):
            continue
        v, f, mat = merge_parts(pedestrian_parts(rng))
        _place(st, t, v, f, mat, x, y, rng.uniform(-np.pi, np.pi), PEDESTRIAN,
               f"pedestrian {placed}", RAW_ID["person"])
        placed += 1

    n_cyc = int(rng.integers(1, 5))
    placed = 0
    for i in range(n_cyc * 6):
        if placed == n_cyc:
            break
        side, sw = _side(rng, lay)
        if i < 6 and placed == 0:
            x = rng.uniform(28.0, 55.0)
        else:
            x = rng.uniform(-60.0, -6.0) if rng.random() < 0.3 else rng.uniform(28.0, 120.0)
        kerb = float(t.kerb(x))
        if rng.random() < 0.7 or sw < 3.0:
            y = side * (kerb - rng.uniform(0.6, 1.3))
        else:
            y = side * (kerb + rng.uniform(1.0, sw - 1.0))
        heading = (0.0 if side < 0 else np.pi) + rng.normal(0.0, 0.08)
        if not st.fits(_candidate_footprint(1.8, 0.7, x, y, heading), 0.3):
            continue
        v, f = shapes.cyclist(rng.uniform(1.6, 1.9))
        # Rider and bicycle both bicyclist, as SemanticKITTI labels a ridden bicycle.
        _place(st, t, v, f, mid("clothing"), x, y, heading, CYCLIST, f"cyclist {placed}",
               RAW_ID["bicyclist"])
        placed += 1

    n_bikes = int(rng.integers(0, 8))
    for i in range(n_bikes):
        side, sw = _side(rng, lay)
        x = rng.uniform(-50.0, 100.0)
        y = side * (float(t.kerb(x)) + rng.uniform(0.5, max(sw - 0.5, 0.6)))
        yaw = rng.uniform(-np.pi, np.pi)
        if not st.fits(_candidate_footprint(1.8, 0.6, x, y, yaw), 0.2):
            continue
        v, f, mat = merge_parts(bicycle_parts(rng))
        _place(st, t, v, f, mat, x, y, yaw, UNKNOWN, f"bicycle {i}", BICYCLE_SEMANTIC)


def _side(rng: np.random.Generator, lay: _Layout) -> tuple[int, float]:
    """A street side drawn at even odds (+1 left, -1 right) and its sidewalk's width."""
    side = 1 if rng.random() < 0.5 else -1
    return side, lay.sidewalk[0] if side > 0 else lay.sidewalk[1]


def _kerb_scale(t: Terrain, x: float, margin: float) -> float:
    """Factor that maps a |y| drawn within the wide road (less `margin`) into the road at x."""
    return (float(t.kerb(x)) - margin) / (t.half_width - margin)


def _assemble(bg_id: int, st: _Street, lay: _Layout) -> Background:
    """Merge the pieces into one float64/int32 triangle soup and freeze the arrays."""
    counts = np.array([len(f) for _, f in st.meshes])
    offsets = np.cumsum([0] + [len(m[0]) for m in st.meshes[:-1]])
    v = np.concatenate([m[0] for m in st.meshes]).astype(np.float64)
    f = np.concatenate([m[1] + o for m, o in zip(st.meshes, offsets, strict=True)])
    keep = shapes.drop_degenerate(v, f)  # lofts and lathes leave collapsed triangles
    cls = np.repeat(np.array(st.cls, dtype=np.uint8), counts)[keep]
    inst = np.repeat(np.array(st.inst, dtype=np.int32), counts)[keep]
    mat = np.concatenate(st.mat).astype(np.uint8)[keep]
    sem = np.concatenate(st.sem).astype(np.uint16)[keep]
    f = f[keep]
    faces = f.astype(np.int32)
    for arr in (v, faces, cls, inst, mat, sem):
        arr.setflags(write=False)
    return Background(bg_id=bg_id, vertices=v, faces=faces, face_class=cls,
                      face_instance=inst, obstacles=tuple(st.obstacles),
                      road_half_width=lay.half_width, curb_height=lay.curb_h,
                      face_material=mat, terrain=lay.terrain, face_semantic=sem)


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


PARKED_STREAM = 17  # the random stream of a street's parked-car thinning


def thin_parked_cars(bg: Background, keep: float) -> Background:
    """The street with each of its parked cars (class-car instances) kept with probability
    `keep`, the others' faces and footprints dropped (their kerb space freed). The draws are
    fixed per street and nested: a street always loses the same cars, and a lower `keep` loses
    those and more. `keep` 1 gives `bg` itself."""
    if not 0.0 <= keep <= 1.0:
        raise ConfigError(f"parked_keep: {keep} is not in 0..1")
    if keep >= 1.0:
        return bg
    cars = np.unique(bg.face_instance[bg.face_class == CAR])
    u = np.random.default_rng([PARKED_STREAM, bg.bg_id]).random(len(cars))
    dropped = cars[u >= keep]
    if len(dropped) == 0:
        return bg
    faces = ~np.isin(bg.face_instance, dropped)
    arrays = {"faces": bg.faces[faces], "face_class": bg.face_class[faces],
              "face_instance": bg.face_instance[faces],
              "face_material": None if bg.face_material is None else bg.face_material[faces],
              "face_semantic": None if bg.face_semantic is None else bg.face_semantic[faces]}
    for a in arrays.values():
        if a is not None:
            a.setflags(write=False)
    gone = set(int(i) for i in dropped)
    return replace(bg, obstacles=tuple(o for o in bg.obstacles if o.instance not in gone),
                   **arrays)


# Streets kept built per process. A Simulator keeps the streets it casts at itself (with their
# BVHs), so a larger cache only duplicated them: 15 streets held 121 MB in every worker.
STREETS_KEPT = 2


# What a street is made of, in the order it is placed: dynamic objects first (they are
# guaranteed their slots), then street furniture.
STEPS = (_parked_vehicles, _people, _guard_rails, _poles, _plants, _boundaries, _buildings)


def placed(bg_id: int, steps: tuple[Callable[[_Street, _Layout, int], None], ...] = STEPS
           ) -> tuple[_Street, _Layout]:
    """The ground of street `bg_id` and what `steps` (a leading part of STEPS) place on it."""
    lay = _layout(bg_id)
    st = _Street()
    _ground(st, lay)
    for step in steps:
        step(st, lay, bg_id)
    return st, lay


@functools.lru_cache(maxsize=STREETS_KEPT)
def _build(bg_id: int) -> Background:
    st, lay = placed(bg_id)
    return _assemble(bg_id, st, lay)
