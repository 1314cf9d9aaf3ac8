"""Road users that are not cars: delivery vans, trucks, buses and trailers, parked bicycles, and
pedestrians in varied poses, each with per-triangle materials.

Classes follow KITTI and SqueezeSeg's conversion of it: only `Car` boxes are car, so vans,
trucks, buses and trailers are class 0 (unknown, "not car"), a parked bicycle without a rider is
class 0, a pedestrian is class 2 and a bicycle with its rider class 3. (The built-in car model
"van" of falsify.world.cars is a people carrier and stays car.) Frames as in falsify.world.cars:
origin at the footprint centre on the ground, +x forward.
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import numpy as np

from falsify.semantic import RAW_ID
from falsify.world import shapes
from falsify.world.materials import PAINTS, mid

OTHER_VEHICLES: tuple[str, ...] = ("delivery van", "box truck", "bus", "trailer")
# Their raw SemanticKITTI ids: a van whose cargo box stands apart from its cab counts as truck
# there, a bus as bus (trained as other-vehicle), a trailer as other-vehicle; none is car (10),
# so they stay class 0 in the four-class view as in KITTI's boxes.
OTHER_VEHICLE_SEMANTIC: dict[str, int] = {
    "delivery van": RAW_ID["truck"], "box truck": RAW_ID["truck"], "bus": RAW_ID["bus"],
    "trailer": RAW_ID["other-vehicle"]}
BICYCLE_SEMANTIC: int = RAW_ID["bicycle"]  # a parked bicycle, no rider

Part = tuple[np.ndarray, np.ndarray, int]  # vertices, faces, material id


def merge_parts(parts: list[Part]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Concatenate tagged meshes into vertices, faces and a per-face material (degenerate
    faces dropped), with the footprint centred on the origin and the lowest point at z = 0."""
    verts, faces, mats, offset = [], [], [], 0
    for v, f, m in parts:
        verts.append(np.asarray(v, np.float64))
        faces.append(np.asarray(f, np.int64) + offset)
        mats.append(np.full(len(f), m, np.uint8))
        offset += len(v)
    v = np.concatenate(verts)
    f = np.concatenate(faces)
    mat = np.concatenate(mats)
    keep = shapes.drop_degenerate(v, f)
    lo, hi = v.min(axis=0), v.max(axis=0)
    v = v - [(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, lo[2]]
    return v, f[keep], mat[keep]


def _wheels(xs, half_track: float, r: float, width: float = 0.25) -> list[Part]:
    out = []
    for x in xs:
        for s in (1.0, -1.0):
            c = [x, s * half_track, r]
            out.append((*shapes.cylinder(np.add(c, [0, -width / 2, 0]),
                                         np.add(c, [0, width / 2, 0]), r, 12), mid("rubber")))
    return out


def _glass_band(x0, x1, y, z0, z1) -> Part:
    v = np.array([[x0, y, z0], [x1, y, z0], [x1, y, z1], [x0, y, z1]], np.float64)
    return v, np.array([[0, 1, 2], [0, 2, 3]]), mid("glass")


def vehicle_parts(kind: str, rng: np.random.Generator) -> list[Part]:
    """One vehicle of `kind` (see OTHER_VEHICLES) with seeded proportions and paint."""
    paint = PAINTS[int(rng.integers(len(PAINTS)))]
    build = _VEHICLE_BUILDERS.get(kind)
    if build is None:
        raise ValueError(f"unknown vehicle kind {kind!r}; allowed: {', '.join(OTHER_VEHICLES)}")
    return build(rng, paint)


def _delivery_van(rng: np.random.Generator, paint: int) -> list[Part]:
    """A delivery van: a tall cargo box behind a low cab with a sloped windscreen."""
    length, width, height = rng.uniform(5.3, 6.6), rng.uniform(1.95, 2.1), rng.uniform(2.4, 2.8)
    cab = 1.0
    half = length / 2
    parts: list[Part] = [
        (*shapes.boxes([-half, -width / 2, 0.35], [half - cab, width / 2, height]), paint),
        (*shapes.boxes([half - cab, -width / 2, 0.35], [half, width / 2, 1.15]), paint),
    ]
    # Sloped windscreen and the cab roof.
    v = np.array([[half - cab, -width / 2 + 0.05, height - 0.1],
                  [half - cab, width / 2 - 0.05, height - 0.1],
                  [half - 0.15, width / 2 - 0.05, 1.15],
                  [half - 0.15, -width / 2 + 0.05, 1.15]])
    parts.append((v, np.array([[0, 2, 1], [0, 3, 2]]), mid("glass")))
    parts.append((*shapes.boxes([half - cab - 0.5, -0.5, 0.5], [half - cab, 0.5, 1.3]),
                  mid("interior")))
    for s in (1, -1):
        parts.append(_glass_band(half - cab + 0.05, half - 0.3, s * width / 2, 1.2,
                                 height - 0.25))
    parts += _wheels([half - 0.9, -half + 1.0], width / 2 - 0.15, 0.36)
    return parts


def _box_truck(rng: np.random.Generator, paint: int) -> list[Part]:
    """A box truck: a cargo box on a frame behind a cab with windows."""
    length, width = rng.uniform(7.0, 10.5), 2.5
    height = rng.uniform(3.2, 3.9)
    cab = 2.1
    half = length / 2
    parts = [
        (*shapes.boxes([-half, -width / 2, 1.0], [half - cab - 0.2, width / 2, height]),
         mid("paint bright")),
        (*shapes.boxes([half - cab, -width / 2 + 0.05, 0.6], [half, width / 2 - 0.05, 1.6]),
         paint),
        (*shapes.boxes([half - cab, -width / 2 + 0.05, 2.5], [half - 0.3, width / 2 - 0.05,
                                                               3.0]), paint),
        (*shapes.boxes([half - cab, -width / 2 + 0.05, 1.6], [half - cab + 0.4,
                                                               width / 2 - 0.05, 2.5]), paint),
        (*shapes.boxes([-half, -0.4, 0.6], [half - cab, 0.4, 1.0]), mid("metal")),
        (*shapes.boxes([half - cab + 0.5, -0.6, 0.9], [half - 0.6, 0.6, 1.8]),
         mid("interior")),
    ]
    v = np.array([[half - 0.3, -width / 2 + 0.05, 2.5], [half - 0.3, width / 2 - 0.05, 2.5],
                  [half, width / 2 - 0.05, 1.6], [half, -width / 2 + 0.05, 1.6]])
    parts.append((v, np.array([[0, 2, 1], [0, 3, 2]]), mid("glass")))
    for s in (1, -1):
        parts.append(_glass_band(half - cab + 0.4, half - 0.3, s * (width / 2 - 0.05), 1.6,
                                 2.5))
    parts += _wheels([half - 1.2, -half + 1.6, -half + 2.9], width / 2 - 0.2, 0.5, 0.35)
    return parts


def _bus(rng: np.random.Generator, paint: int) -> list[Part]:
    """A bus: a long body with a glass band along both sides and at the front."""
    length, width, height = rng.uniform(10.5, 12.5), 2.55, rng.uniform(2.9, 3.3)
    half = length / 2
    parts = [
        (*shapes.boxes([-half, -width / 2, 0.3], [half, width / 2, 1.1]), paint),
        (*shapes.boxes([-half, -width / 2, height - 0.45], [half, width / 2, height]), paint),
        (*shapes.boxes([-half, -width / 2, 1.1], [-half + 0.6, width / 2, height - 0.45]),
         paint),
        (*shapes.boxes([-half + 1.0, -width / 2 + 0.3, 0.5], [half - 1.5, width / 2 - 0.3,
                                                              1.5]), mid("interior")),
    ]
    for s in (1, -1):
        parts.append(_glass_band(-half + 0.6, half, s * width / 2, 1.1, height - 0.45))
    parts.append((np.array([[half, -width / 2, 1.1], [half, width / 2, 1.1],
                            [half, width / 2, height - 0.45],
                            [half, -width / 2, height - 0.45]]),
                  np.array([[0, 1, 2], [0, 2, 3]]), mid("glass")))
    parts += _wheels([half - 2.5, -half + 3.0], width / 2 - 0.2, 0.5, 0.3)
    return parts


def _trailer(rng: np.random.Generator, paint: int) -> list[Part]:
    """A trailer: a closed box or a flatbed with low sides, and its drawbar."""
    length, width = rng.uniform(3.5, 8.0), rng.uniform(2.0, 2.5)
    half = length / 2
    if rng.random() < 0.5:  # closed box trailer
        body = shapes.boxes([-half, -width / 2, 0.7], [half, width / 2, rng.uniform(2.2, 3.4)])
    else:  # flatbed with low sides
        body = shapes.merge([shapes.boxes([-half, -width / 2, 0.7], [half, width / 2, 0.8]),
                             shapes.boxes([-half, -width / 2, 0.8], [half, -width / 2 + 0.05,
                                                                      1.2]),
                             shapes.boxes([-half, width / 2 - 0.05, 0.8], [half, width / 2,
                                                                           1.2])])
    parts = [(*body, paint),
             (*shapes.boxes([half, -0.05, 0.5], [half + 1.4, 0.05, 0.6]), mid("metal"))]
    parts += _wheels([0.0] if length < 6 else [-0.6, 0.6], width / 2 - 0.15, 0.35)
    return parts


_VEHICLE_BUILDERS: dict[str, Callable[[np.random.Generator, int], list[Part]]] = {
    "delivery van": _delivery_van, "box truck": _box_truck, "bus": _bus, "trailer": _trailer}


@functools.lru_cache(maxsize=16)
def vehicle_model(kind: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The fixed instance of `kind` used as dataset traffic: vertices, faces and per-face
    material (read-only: cached)."""
    rng = np.random.default_rng([OTHER_VEHICLES.index(kind), 77])
    v, f, mat = merge_parts(vehicle_parts(kind, rng))
    for a in (v, f, mat):
        a.setflags(write=False)
    return v, f, mat


def bicycle_parts(rng: np.random.Generator) -> list[Part]:
    """A riderless bicycle along +x: two wheels, frame tubes, bar and saddle."""
    r = float(rng.uniform(0.3, 0.36))
    rear, front = np.array([-0.52, 0.0, r]), np.array([0.52, 0.0, r])
    crank, seat, bar = np.array([-0.05, 0, 0.3]), np.array([-0.22, 0, 0.9]), np.array(
        [0.42, 0, 0.98])
    parts: list[Part] = [(*shapes.torus(rear, [0, 1, 0], r - 0.02, 0.02, 20, 6), mid("rubber")),
                         (*shapes.torus(front, [0, 1, 0], r - 0.02, 0.02, 20, 6), mid("rubber"))]
    for a, b in ((rear, crank), (rear, seat), (crank, seat), (crank, bar - [0.05, 0, 0.1]),
                 (seat, bar - [0.05, 0, 0.1]), (front, bar)):
        parts.append((*shapes.cylinder(a, b, 0.018, 6), mid("metal")))
    parts.append((*shapes.cylinder([0.42, -0.28, 0.98], [0.42, 0.28, 0.98], 0.018, 6),
                  mid("metal")))
    parts.append((*shapes.oriented_box(seat + [0, 0, 0.04], [0.25, 0.12, 0.06]),
                  mid("clothing")))
    return parts


def pedestrian_parts(rng: np.random.Generator) -> list[Part]:
    """A person in a seeded pose: walking or standing, adult or child, with or without a bag,
    some leaning forward (looking at a phone, pushing)."""
    child = rng.random() < 0.15
    height = float(rng.uniform(1.05, 1.45) if child else rng.uniform(1.5, 1.98))
    walking = rng.random() < 0.6
    stride = float(rng.uniform(0.3, 0.7) if walking else rng.uniform(0.0, 0.15))
    v, f = shapes.person(height, stride, float(rng.uniform(0.0, 0.45)))
    parts: list[Part] = [(v, f, mid("clothing"))]
    s = height / 1.75
    kind = rng.random()
    if kind < 0.25:  # backpack
        parts.append((*shapes.oriented_box([-0.2 * s, 0, 1.2 * s], [0.18 * s, 0.3 * s,
                                                                     0.4 * s]), mid("clothing")))
    elif kind < 0.4:  # bag in one hand
        parts.append((*shapes.oriented_box([0.0, 0.3 * s, 0.7 * s], [0.3, 0.12, 0.3]),
                      mid("clothing")))
    lean = float(rng.uniform(0.0, 0.2)) if rng.random() < 0.3 else 0.0
    if lean:
        c, sn = np.cos(lean), np.sin(lean)
        rot = np.array([[c, 0.0, sn], [0.0, 1.0, 0.0], [-sn, 0.0, c]])
        parts = [(p[0] @ rot.T, p[1], p[2]) for p in parts]
    return parts
