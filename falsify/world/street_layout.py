"""A street's cross-section and what is placed along it: the world frame's fixed zones, the
layout drawn from a background's id (lanes, kerbs, sidewalks, town and narrowing streets, the
terrain), the ground meshes with the kerbs' obstacle outlines, and the `_Street` the placement
steps add their meshes and footprints to.

World frame: metres, origin on the road's crown below the sensor, +x forward, +y left, +z up.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from falsify.classes import UNKNOWN
from falsify.semantic import RAW_ID
from falsify.world import shapes
from falsify.world.materials import mid
from falsify.world.terrain import Terrain, draw_terrain, terrain_meshes

KERB_OBSTACLE: str = "curb"   # the label the kerbs' obstacle outlines start with
ROAD_X: tuple[float, float] = (-170.0, 230.0)  # road, sidewalks and terrain span this x range
FREE_ZONE: tuple[tuple[float, float], tuple[float, float]] = ((0.0, 25.0), (-8.5, 7.5))
SENSOR_CLEARANCE: float = 3.0  # metres around the sensor (0, sensor_y) holding nothing but road
TERRAIN_HALF_WIDTH: float = 300.0  # the ground reaches out to |y| = this

FIRST_STREET_INSTANCE = 1000   # the street's own objects; the sample's placed ones lie below
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
    heading: float | None = None   # where the object faces (rad from +x); None: no front



def _rect(x0: float, x1: float, y0: float, y1: float) -> np.ndarray:
    """Counter-clockwise axis-aligned rectangle polygon."""
    return np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]], dtype=np.float64)


class _Street:
    """Accumulates meshes with labels and materials, and the footprints used for placement."""

    def __init__(self, free_zone=FREE_ZONE, sensor_y: float = 0.0) -> None:
        self.free_zone = free_zone   # ((x0, x1), (y0, y1)) that no object may enter
        self.sensor_y = sensor_y     # where across the road the ego stands
        self.meshes: list[shapes.Mesh] = []
        self.cls: list[int] = []
        self.inst: list[int] = []
        self.mat: list[np.ndarray] = []
        self.sem: list[np.ndarray] = []  # raw SemanticKITTI ids per face
        self.obstacles: list[Footprint] = []
        self.boxes: list[np.ndarray] = []  # (4,) x0, x1, y0, y1 of placed objects
        self.next_id = FIRST_STREET_INSTANCE

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

    def overhang_edge(self, edge: float) -> float:
        """The |y| an overhang (crown, lamp arm) keeps beyond over the test site: `edge`, set
        for FREE_ZONE, or as far past a narrower zone's side."""
        if self.free_zone == FREE_ZONE:
            return edge
        return max(abs(v) for v in self.free_zone[1]) + edge - max(abs(v) for v in FREE_ZONE[1])

    def fits(self, poly: np.ndarray, margin: float = 0.3) -> bool:
        """True when a footprint keeps off the free zone, the sensor and every placed object."""
        x0, y0 = poly.min(axis=0) - margin
        x1, y1 = poly.max(axis=0) + margin
        (fx0, fx1), (fy0, fy1) = self.free_zone
        if x1 > fx0 and x0 < fx1 and y1 > fy0 and y0 < fy1:
            return False
        dx = max(x0, 0.0, -x1)
        dy = max(y0 - self.sensor_y, 0.0, self.sensor_y - y1)
        if dx * dx + dy * dy < SENSOR_CLEARANCE**2:
            return False
        if self.boxes:
            b = np.asarray(self.boxes)
            hit = (x1 > b[:, 0]) & (x0 < b[:, 1]) & (y1 > b[:, 2]) & (y0 < b[:, 3])
            if hit.any():
                return False
        return True

    def occupy(self, label: str, poly: np.ndarray, instance: int = 0,
               heading: float | None = None) -> None:
        self.obstacles.append(Footprint(label, poly, instance, heading))
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



def _side(rng: np.random.Generator, lay: _Layout) -> tuple[int, float]:
    """A street side drawn at even odds (+1 left, -1 right) and its sidewalk's width."""
    side = 1 if rng.random() < 0.5 else -1
    return side, lay.sidewalk[0] if side > 0 else lay.sidewalk[1]


def _kerb_scale(t: Terrain, x: float, margin: float) -> float:
    """Factor that maps a |y| drawn within the wide road (less `margin`) into the road at x."""
    return (float(t.kerb(x)) - margin) / (t.half_width - margin)
