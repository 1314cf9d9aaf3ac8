"""Street furniture along a street's layout: guard rails, street lights and signs, boundaries
(walls, fences, railings, hedges), plants (street trees, bushes, the far band of trees) and
buildings, each step drawing from its own random stream of the background's id.
"""

from __future__ import annotations

import numpy as np

from falsify.classes import UNKNOWN
from falsify.semantic import RAW_ID
from falsify.world import buildings, shapes, vegetation
from falsify.world.materials import mid
from falsify.world.street_layout import (
    ROAD_X,
    TOWN_SETBACK,
    _Layout,
    _near_zone,
    _rect,
    _rng,
    _side_kind,
    _slope_top,
    _Street,
)


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
                edge = st.overhang_edge(8.9) if t.narrow == 0.0 or _near_zone(x) else kerb - 2.0
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
                    edge = st.overhang_edge(8.8) if t.narrow == 0.0 or _near_zone(x) else kerb - 2.5
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
