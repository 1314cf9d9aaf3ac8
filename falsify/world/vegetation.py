"""Plants along the street: bushes and hedges on verges and embankments, porous tree canopies
and the far band of trees at the horizon. Foliage is porous (material "foliage"/"hedge"): a
ray crossing it goes on with the material's probability, so a crown is not a solid blob.

Every generator takes the street accumulator, the terrain and its own seeded generator, and
builds only what a ray can reach (nothing behind a closed row of buildings, nothing past 120 m).
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
# Raw SemanticKITTI ids: bushes, hedges and crowns are vegetation, a tree's bark trunk.
VEGETATION, TRUNK = RAW_ID["vegetation"], RAW_ID["trunk"]


def _rect(x0: float, x1: float, y0: float, y1: float) -> np.ndarray:
    return np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]], dtype=np.float64)


def blob(rng: np.random.Generator, center, radii, subdivisions: int,
         jitter: float = 0.18) -> shapes.Mesh:
    """An irregular closed lump (icosphere with per-vertex radial noise)."""
    v, f = shapes.icosphere([0.0, 0.0, 0.0], radii, subdivisions)
    v = v * rng.uniform(1.0 - jitter, 1.0 + jitter, size=(len(v), 1))
    return v + np.asarray(center, dtype=np.float64), f


def bushes(st, t: Terrain, rng: np.random.Generator, side: int, u_range: tuple[float, float],
           x_range: tuple[float, float], density: float) -> int:
    """Scattered bushes on one side's roadside band (u beyond the sidewalk); returns count."""
    u0, u1 = u_range
    if u1 <= u0 or density <= 0:
        return 0
    area = (x_range[1] - x_range[0]) * (u1 - u0)
    n = int(rng.poisson(area * density))
    sw = t.sidewalk[0 if side > 0 else 1]
    made = 0
    for _ in range(n):
        x = float(rng.uniform(*x_range))
        u = float(rng.uniform(u0, u1))
        y = side * (float(t.kerb(x)) + sw + u)
        r = float(rng.uniform(0.4, 1.6))
        poly = _rect(x - r, x + r, y - r, y + r)
        if not st.fits(poly, margin=0.1):
            continue
        z = float(t.height(np.array([x]), np.array([y]))[0])
        h = r * rng.uniform(0.6, 1.1)
        st.add(blob(rng, [x, y, z + 0.6 * h], [r, r * rng.uniform(0.7, 1.2), h], 1),
               UNKNOWN, 0, mid("foliage"), VEGETATION)
        made += 1
    return made


def hedge(st, t: Terrain, rng: np.random.Generator, xa: float, xb: float, y_in: float,
          side: int, label: str) -> None:
    """A trimmed hedge along x from xa to xb whose road-facing side stands at y_in."""
    thick = float(rng.uniform(0.6, 1.3))
    height = float(rng.uniform(0.8, 2.0))
    ya, yb = sorted((y_in, y_in + side * thick))
    xs = np.arange(xa, xb, 2.0)
    for x0 in xs:
        x1 = min(x0 + 2.0, xb)
        zs = t.height(np.array([x0, x1]), np.array([y_in, y_in]))
        base = float(zs.min()) - 0.1
        top = base + 0.1 + height + float(rng.normal(0.0, 0.06))
        v, f = shapes.boxes([x0, ya, base], [x1, yb, top])
        v = v + rng.normal(0.0, 0.04, size=v.shape) * [0, 1, 1]
        st.add((v, f), UNKNOWN, 0, mid("hedge"), VEGETATION)
    st.occupy(label, _rect(xa, xb, ya, yb))


def tree(st, t: Terrain, rng: np.random.Generator, x: float, y: float, crown: float,
         conifer: bool, label: str, detail: int = 2) -> bool:
    """A trunk and a porous crown (an outer and an inner foliage shell) standing on the ground."""
    trunk_r = float(rng.uniform(0.1, 0.3)) * (0.6 + 0.3 * crown / 2.0)
    poly = _rect(x - trunk_r, x + trunk_r, y - trunk_r, y + trunk_r)
    if not st.fits(poly, margin=0.2):
        return False
    ground = float(t.height(np.array([x]), np.array([y]))[0])
    trunk_h = float(rng.uniform(1.6, 3.5))
    iid = st.new_instance()
    st.add(shapes.cylinder([x, y, ground - 0.1], [x, y, ground + trunk_h + crown], trunk_r,
                           8 if detail > 1 else 5, 0.6 * trunk_r), UNKNOWN, iid, mid("bark"),
           TRUNK)
    if conifer:
        top = ground + trunk_h + float(rng.uniform(2.5, 3.5)) * crown
        st.add(shapes.cylinder([x, y, ground + trunk_h * 0.6], [x, y, top], crown,
                               10 if detail > 1 else 6, 0.0), UNKNOWN, iid, mid("foliage"),
               VEGETATION)
    else:
        c = [x, y, ground + trunk_h + 0.8 * crown]
        st.add(blob(rng, c, [crown, crown, crown * 0.9], detail, 0.15), UNKNOWN, iid,
               mid("foliage"), VEGETATION)
        if detail > 1:
            st.add(blob(rng, c, [crown * 0.55] * 3, 1, 0.2), UNKNOWN, iid, mid("foliage"),
                   VEGETATION)
    st.occupy(label, poly)
    return True


def tree_band(st, t: Terrain, rng: np.random.Generator, side: int, u_near: float,
              x_range: tuple[float, float], depth: float, spacing: float) -> int:
    """The far band of trees: rows of large, coarse crowns from u_near outward (to 120 m)."""
    hw, sw = t.half_width, t.sidewalk[0 if side > 0 else 1]
    made = 0
    rows = max(1, int(depth // 6.0))
    for row in range(rows):
        u = u_near + row * 6.0 + float(rng.uniform(0.0, 3.0))
        if hw + sw + u > 110.0:
            break
        x = x_range[0] + float(rng.uniform(0.0, spacing))
        while x < x_range[1]:
            if rng.random() < 0.85:
                y = side * (float(t.kerb(x)) + sw + u + float(rng.uniform(-1.5, 1.5)))
                crown = float(rng.uniform(2.0, 4.5))
                if tree(st, t, rng, x, y, crown, rng.random() < 0.25, f"band tree {made}", 1):
                    made += 1
            x += spacing * float(rng.uniform(0.6, 1.4))
    return made

