"""Road users along a street: vehicles parked at the kerbs (cars, and vans, trucks, buses and
trailers), pedestrians, cyclists and parked bicycles, each standing on the terrain with its
oriented footprint kept as an obstacle.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from falsify.classes import CAR, CYCLIST, PEDESTRIAN, UNKNOWN
from falsify.rotations import rot_x, rot_y, rot_z
from falsify.semantic import RAW_ID
from falsify.world import shapes
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
from falsify.world.street_layout import _kerb_scale, _Layout, _rect, _rng, _side, _Street
from falsify.world.terrain import Terrain


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
    st.occupy(label, _footprint(v), iid, yaw)


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
    _pedestrians(st, lay, rng)
    _cyclists(st, lay, rng)
    _parked_bicycles(st, lay, rng)


# attempt(i, placed, side, sidewalk width): whether the i-th try stood an object, `placed` before it
Attempt = Callable[[int, int, int, float], bool]


def _place_some(rng: np.random.Generator, lay: _Layout, wanted: int, tries: int,
                attempt: Attempt) -> None:
    """Up to `wanted` objects in at most `tries` attempts, each on a street side drawn at even
    odds (_side) before the attempt draws the rest."""
    placed = 0
    for i in range(tries):
        if placed == wanted:
            break
        side, sw = _side(rng, lay)
        if attempt(i, placed, side, sw):
            placed += 1


def _pedestrians(st: _Street, lay: _Layout, rng: np.random.Generator) -> None:
    """Pedestrians on the sidewalks, the first 8-45 m ahead; some crossing the road far ahead."""
    t = lay.terrain

    def attempt(i: int, placed: int, side: int, sw: float) -> bool:
        crossing = i > 0 and rng.random() < 0.12
        if crossing:
            x = rng.uniform(32.0, 90.0)
            y = rng.uniform(-lay.half_width + 1, lay.half_width - 1) * _kerb_scale(t, x, 1.0)
        else:
            x = rng.uniform(8.0, 45.0) if placed == 0 else rng.uniform(-60.0, 120.0)
            y = side * (float(t.kerb(x)) + rng.uniform(0.4, max(sw - 0.4, 0.5)))
        poly = _rect(x - 0.4, x + 0.4, y - 0.4, y + 0.4)
        if not st.fits(poly, 0.2):
            return False
        v, f, mat = merge_parts(pedestrian_parts(rng))
        _place(st, t, v, f, mat, x, y, rng.uniform(-np.pi, np.pi), PEDESTRIAN,
               f"pedestrian {placed}", RAW_ID["person"])
        return True

    n_ped = int(rng.integers(2, 15))
    _place_some(rng, lay, n_ped, n_ped * 4, attempt)


def _cyclists(st: _Street, lay: _Layout, rng: np.random.Generator) -> None:
    """Cyclists riding along the road's edge (some on the sidewalk), the first 28-55 m ahead."""
    t = lay.terrain

    def attempt(i: int, placed: int, side: int, sw: float) -> bool:
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
            return False
        v, f = shapes.cyclist(rng.uniform(1.6, 1.9))
        # Rider and bicycle both bicyclist, as SemanticKITTI labels a ridden bicycle.
        _place(st, t, v, f, mid("clothing"), x, y, heading, CYCLIST, f"cyclist {placed}",
               RAW_ID["bicyclist"])
        return True

    n_cyc = int(rng.integers(1, 5))
    _place_some(rng, lay, n_cyc, n_cyc * 6, attempt)


def _parked_bicycles(st: _Street, lay: _Layout, rng: np.random.Generator) -> None:
    """Bicycles without riders parked on the sidewalks, one try each."""
    t = lay.terrain

    def attempt(i: int, placed: int, side: int, sw: float) -> bool:
        x = rng.uniform(-50.0, 100.0)
        y = side * (float(t.kerb(x)) + rng.uniform(0.5, max(sw - 0.5, 0.6)))
        yaw = rng.uniform(-np.pi, np.pi)
        if not st.fits(_candidate_footprint(1.8, 0.6, x, y, yaw), 0.2):
            return False
        v, f, mat = merge_parts(bicycle_parts(rng))
        _place(st, t, v, f, mat, x, y, yaw, UNKNOWN, f"bicycle {i}", BICYCLE_SEMANTIC)
        return True

    n_bikes = int(rng.integers(0, 8))
    _place_some(rng, lay, n_bikes, n_bikes, attempt)
