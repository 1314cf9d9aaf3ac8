"""Built things along the street: walls, chain-link fences and railings that rays partly pass,
guard rails, sign posts with retro-reflective plates, and buildings whose windows are recessed
glass (rays pass the glass and end on the floors and walls inside).

Each builder follows the terrain (pieces stand on the lowest ground under them) and tags every
triangle with its material and its raw SemanticKITTI id.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from falsify.semantic import RAW_ID
from falsify.world import shapes
from falsify.world.materials import mid

if TYPE_CHECKING:
    from falsify.world.terrain import Terrain

UNKNOWN = 0
# Raw SemanticKITTI ids of the pieces. Boundary walls (0.6-2.4 m) are fence, not building:
# SemanticKITTI's annotators label small walls and crash barriers as fence and keep building for
# buildings and large walls.
BUILDING, FENCE = RAW_ID["building"], RAW_ID["fence"]
POLE, SIGN = RAW_ID["pole"], RAW_ID["traffic-sign"]


def _rect(x0: float, x1: float, y0: float, y1: float) -> np.ndarray:
    return np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]], dtype=np.float64)


def _quad(p0, p1, p2, p3) -> shapes.Mesh:
    v = np.array([p0, p1, p2, p3], dtype=np.float64)
    return v, np.array([[0, 1, 2], [0, 2, 3]], dtype=np.int64)


def _base(t: Terrain, x0: float, x1: float, y: float) -> float:
    xs = np.linspace(x0, x1, 3)
    return float(t.height(xs, np.full(3, y)).min())


def wall(st, t: Terrain, rng: np.random.Generator, xa: float, xb: float, y_in: float,
         side: int, label: str) -> None:
    """A masonry wall in 4 m pieces, each founded on the ground under it."""
    h = float(rng.uniform(0.6, 2.4))
    ya, yb = sorted((y_in, y_in + side * 0.25))
    for x0 in np.arange(xa, xb, 4.0):
        x1 = min(x0 + 4.0, xb)
        base = _base(t, x0, x1, y_in) - 0.2
        st.add(shapes.boxes([x0, ya, base], [x1, yb, base + 0.2 + h]), UNKNOWN, 0,
               mid("concrete"), FENCE)
    st.occupy(label, _rect(xa, xb, ya, yb))


def fence(st, t: Terrain, rng: np.random.Generator, xa: float, xb: float, y_in: float,
          side: int, label: str) -> None:
    """Chain-link panels (porous) between metal posts, with a top rail."""
    h = float(rng.uniform(1.0, 2.2))
    step = 2.5
    y = y_in + side * 0.05
    for x0 in np.arange(xa, xb, step):
        x1 = min(x0 + step, xb)
        z0, z1 = (float(v) for v in t.height(np.array([x0, x1]), np.array([y, y])))
        st.add(_quad([x0, y, z0], [x1, y, z1], [x1, y, z1 + h], [x0, y, z0 + h]), UNKNOWN, 0,
               mid("chain-link"), FENCE)
        st.add(shapes.boxes([x0 - 0.03, y - 0.03, z0 - 0.2], [x0 + 0.03, y + 0.03, z0 + h + 0.05]),
               UNKNOWN, 0, mid("metal"), FENCE)
        st.add(shapes.boxes([x0, y - 0.02, min(z0, z1) + h - 0.02], [x1, y + 0.02,
                                                                      max(z0, z1) + h + 0.02]),
               UNKNOWN, 0, mid("metal"), FENCE)
    ya, yb = sorted((y - 0.05, y + 0.05))
    st.occupy(label, _rect(xa, xb, ya, yb))


def railing(st, t: Terrain, rng: np.random.Generator, xa: float, xb: float, y_in: float,
            side: int, label: str) -> None:
    """Vertical bars (rays pass between them) under a handrail, 0.9-1.2 m high."""
    h = float(rng.uniform(0.9, 1.2))
    gap = float(rng.uniform(0.11, 0.2))
    y = y_in + side * 0.05
    xs = np.arange(xa, xb, gap)
    base = t.height(xs, np.full(len(xs), y))
    lo = np.stack([xs - 0.012, np.full_like(xs, y - 0.012), base - 0.1], axis=1)
    hi = np.stack([xs + 0.012, np.full_like(xs, y + 0.012), base + h], axis=1)
    st.add(shapes.boxes(lo, hi), UNKNOWN, 0, mid("metal"), FENCE)
    for x0 in np.arange(xa, xb, 4.0):
        x1 = min(x0 + 4.0, xb)
        zb = _base(t, x0, x1, y)
        st.add(shapes.boxes([x0, y - 0.03, zb + h], [x1, y + 0.03, zb + h + 0.06]),
               UNKNOWN, 0, mid("metal"), FENCE)
    ya, yb = sorted((y - 0.05, y + 0.05))
    st.occupy(label, _rect(xa, xb, ya, yb))


def guard_rail(st, t: Terrain, rng: np.random.Generator, xa: float, xb: float, y: float,
               side: int, label: str) -> None:
    """A steel beam (0.3 m tall, 0.5-0.8 m up) on posts every 2 m, following the ground."""
    xs = np.arange(xa, xb + 1e-9, 2.0)
    z = t.height(xs, np.full(len(xs), y))
    off = side * 0.12  # the beam stands on the road side of its posts
    for i in range(len(xs)):
        st.add(shapes.boxes([xs[i] - 0.05, y - 0.05, z[i] - 0.2],
                            [xs[i] + 0.05, y + 0.05, z[i] + 0.75]), UNKNOWN, 0, mid("metal"),
               FENCE)
        if i + 1 < len(xs):
            x0, x1, z0, z1 = xs[i], xs[i + 1], z[i], z[i + 1]
            yb = y - off
            st.add(_quad([x0, yb, z0 + 0.45], [x1, yb, z1 + 0.45], [x1, yb, z1 + 0.75],
                         [x0, yb, z0 + 0.75]), UNKNOWN, 0, mid("metal"), FENCE)
    ya, yb = sorted((y - 0.1, y + 0.1 - 2 * off))
    st.occupy(label, _rect(xa, xb, min(ya, yb), max(ya, yb)))


def sign(st, t: Terrain, rng: np.random.Generator, x: float, y: float, side: int,
         label: str) -> bool:
    """A post with a retro-reflective plate facing the oncoming traffic."""
    poly = _rect(x - 0.2, x + 0.2, y - 0.2, y + 0.2)
    if not st.fits(poly, margin=0.1):
        return False
    z = float(t.height(np.array([x]), np.array([y]))[0])
    h = float(rng.uniform(2.0, 3.0))
    iid = st.new_instance()
    st.add(shapes.cylinder([x, y, z - 0.1], [x, y, z + h], 0.04, 6), UNKNOWN, iid, mid("metal"),
           POLE)
    w = float(rng.uniform(0.5, 0.9))
    st.add(shapes.boxes([x - 0.02, y - w / 2, z + h - w], [x + 0.02, y + w / 2, z + h]),
           UNKNOWN, iid, mid("retro"), SIGN)
    st.occupy(label, poly)
    return True


def building(st, t: Terrain, rng: np.random.Generator, xa: float, xb: float, near: float,
             depth: float, height: float, side: int, label: str) -> None:
    """A block whose road-facing wall has recessed glass windows and floors behind them."""
    y_front = side * near
    y_back = side * (near + depth)
    ya, yb = sorted((y_front, y_back))
    base = _base(t, xa, xb, y_front) - 0.3
    top = base + 0.3 + height
    v, f = shapes.boxes([xa, ya, base], [xb, yb, top])
    front = (4, 5) if side > 0 else (6, 7)  # the -y or +y side of the cube
    keep = np.ones(len(f), bool)
    keep[list(front)] = False
    st.add((v, f[keep]), UNKNOWN, 0, mid("facade"), BUILDING)
    st.occupy(label, _rect(xa, xb, ya, yb))
    floor_h = float(rng.uniform(2.8, 3.6))
    floors = int((height - 0.8) // floor_h)
    pitch = float(rng.uniform(2.2, 3.8))
    n_win = int((xb - xa - 1.0) // pitch)
    recess = float(rng.uniform(0.1, 0.3))
    if floors < 1 or n_win < 1:
        st.add(_quad([xa, y_front, base], [xb, y_front, base], [xb, y_front, top],
                     [xa, y_front, top]), UNKNOWN, 0, mid("facade"), BUILDING)
        return
    win_w = min(float(rng.uniform(0.9, 1.6)), pitch - 0.5)
    win_h = min(float(rng.uniform(1.2, 1.8)), floor_h - 0.8)
    xc = xa + (xb - xa - (n_win - 1) * pitch) / 2 + pitch * np.arange(n_win)
    z_floor = base + 0.3 + 0.8 + floor_h * np.arange(floors)
    zc = z_floor + floor_h * 0.55
    xl, xr = xc - win_w / 2, xc + win_w / 2
    zb, zt = zc - win_h / 2, zc + win_h / 2
    parts: list[shapes.Mesh] = []
    # Facade: horizontal bands between window rows, piers between windows in each row.
    z_edges = np.concatenate([[base], np.ravel(np.stack([zb, zt], 1)), [top]])
    for i in range(0, len(z_edges), 2):
        parts.append(_quad([xa, y_front, z_edges[i]], [xb, y_front, z_edges[i]],
                           [xb, y_front, z_edges[i + 1]], [xa, y_front, z_edges[i + 1]]))
    x_edges = np.concatenate([[xa], np.ravel(np.stack([xl, xr], 1)), [xb]])
    for k in range(floors):
        for i in range(0, len(x_edges), 2):
            parts.append(_quad([x_edges[i], y_front, zb[k]], [x_edges[i + 1], y_front, zb[k]],
                               [x_edges[i + 1], y_front, zt[k]], [x_edges[i], y_front, zt[k]]))
    # Reveals: the four sides of each window opening, from the facade to the glass.
    yg = y_front + side * recess
    gx, gz = np.meshgrid(np.arange(n_win), np.arange(floors), indexing="ij")
    for i, k in zip(gx.ravel(), gz.ravel(), strict=True):
        x0, x1, z0, z1 = xl[i], xr[i], zb[k], zt[k]
        parts.append(_quad([x0, y_front, z0], [x1, y_front, z0], [x1, yg, z0], [x0, yg, z0]))
        parts.append(_quad([x0, y_front, z1], [x1, y_front, z1], [x1, yg, z1], [x0, yg, z1]))
        parts.append(_quad([x0, y_front, z0], [x0, yg, z0], [x0, yg, z1], [x0, y_front, z1]))
        parts.append(_quad([x1, y_front, z0], [x1, yg, z0], [x1, yg, z1], [x1, y_front, z1]))
    st.add(shapes.merge(parts), UNKNOWN, 0, mid("facade"), BUILDING)
    glass = [_quad([xl[i], yg, zb[k]], [xr[i], yg, zb[k]], [xr[i], yg, zt[k]],
                   [xl[i], yg, zt[k]]) for i, k in zip(gx.ravel(), gz.ravel(), strict=True)]
    st.add(shapes.merge(glass), UNKNOWN, 0, mid("glass"), BUILDING)
    # Floor slabs inside (what a ray through a window ends on), and curtains in some rooms.
    slabs = [_quad([xa, ya, z], [xb, ya, z], [xb, yb, z], [xa, yb, z]) for z in z_floor]
    st.add(shapes.merge(slabs), UNKNOWN, 0, mid("concrete"), BUILDING)
    shut = rng.random(len(glass)) < float(rng.uniform(0.0, 0.5))
    if shut.any():
        yc = yg + side * 0.1
        blinds = [_quad([xl[i], yc, zb[k]], [xr[i], yc, zb[k]], [xr[i], yc, zt[k]],
                        [xl[i], yc, zt[k]])
                  for (i, k), s in zip(zip(gx.ravel(), gz.ravel(), strict=True), shut,
                                       strict=True) if s]
        st.add(shapes.merge(blinds), UNKNOWN, 0, mid("clothing"), BUILDING)
