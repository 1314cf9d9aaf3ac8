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
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from falsify.classes import CAR
from falsify.errors import ConfigError
from falsify.world import shapes
from falsify.world.street_furniture import (
    _boundaries,
    _buildings,
    _guard_rails,
    _plants,
    _poles,
)
from falsify.world.street_layout import (
    _DEFAULT_MAT,
    FREE_ZONE,
    KERB_OBSTACLE,
    NARROW_KERB,
    NARROW_P,
    NARROW_WIDE_AHEAD,
    NARROW_WIDE_BEHIND,
    ROAD_X,
    SEMANTIC_OF_CLASS,
    SENSOR_CLEARANCE,
    TOWN_HALF_WIDTH,
    TOWN_P,
    TOWN_SIDEWALK,
    Footprint,
    _ground,
    _Layout,
    _layout,
    _Street,
)
from falsify.world.street_users import _parked_vehicles, _people
from falsify.world.terrain import Terrain

# The layout's names callers and tests read from here stay importable from here.
__all__ = [
    "FREE_ZONE", "KERB_OBSTACLE", "MAX_BACKGROUND_ID", "NARROW_KERB", "NARROW_P",
    "NARROW_WIDE_AHEAD", "NARROW_WIDE_BEHIND", "SENSOR_CLEARANCE", "STEPS", "TOWN_HALF_WIDTH",
    "TOWN_P", "TOWN_SIDEWALK", "Background", "Footprint", "build_background", "placed",
    "thin_parked_cars",
]

MAX_BACKGROUND_ID: int = 999_999


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
    # The ego's pitch (degrees) and height (m) over its pose on the terrain, for a street that
    # stands for a real place (falsify.world.places): how that place's sensor saw its road.
    ego_pitch_deg: float = 0.0
    ego_dz: float = 0.0
    # Where across the road (m, +left of the crown) the ego stands: off the crown on a street
    # whose kerbs stand where its place's do, on each side (the paper's positions stay the
    # sensor's: a sampled car moves with it).
    ego_dy: float = 0.0
    # Whether the kerbs stop a sampled car: not on a street whose road is as narrow as its
    # place's, where a car may stand on the sidewalk or verge as one inserted in the real scan
    # may (the kerbs still stop the ego).
    kerbs_stop_cars: bool = True

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


def assemble(bg_id: int, st: _Street, lay: _Layout) -> Background:
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


def placed(bg_id: int, steps: tuple[Callable[[_Street, _Layout, int], None], ...] = STEPS,
           lay: _Layout | None = None, free_zone=FREE_ZONE, sensor_y: float = 0.0
           ) -> tuple[_Street, _Layout]:
    """The ground of street `bg_id` and what `steps` (a leading part of STEPS) place on it;
    `lay` replaces the street's own layout, `free_zone` the test site kept clear, `sensor_y`
    where across the road the sensor stands (kept clear around)."""
    lay = lay or _layout(bg_id)
    st = _Street(free_zone, sensor_y)
    _ground(st, lay)
    for step in steps:
        step(st, lay, bg_id)
    return st, lay


@functools.lru_cache(maxsize=STREETS_KEPT)
def _build(bg_id: int) -> Background:
    st, lay = placed(bg_id)
    return assemble(bg_id, st, lay)
