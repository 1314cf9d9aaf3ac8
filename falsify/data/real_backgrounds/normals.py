"""Surface normals of a range image's returns estimated from their image neighbours."""

from __future__ import annotations

import numpy as np

# A neighbouring return farther than this share of the range (0.5 m at least) is another
# surface: rows on a road grazed at range lie metres apart, a car's edge against a wall more.
NEIGHBOUR_GAP = 0.25


def estimated_normals(xyz: np.ndarray, valid: np.ndarray, origin: np.ndarray,
                      direction: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each return's surface normal from its image neighbours (the cross product of the steps
    to the next return along the row and down the column, each on the side whose return is
    nearer, within NEIGHBOUR_GAP of the range), turned to face the sensor, and the cosine of its
    ray to it; where no neighbour qualifies, the surface is taken to face the ray (cosine 1).
    The normal map of surfel SLAM is made so from the vertex map (SuMa: Behley and Stachniss,
    "Efficient Surfel-Based SLAM using 3D Laser Range Data in Urban Environments", RSS 2018)."""
    p = np.where(valid[..., None], xyz.astype(np.float64), np.nan)
    gap = np.maximum(0.5, NEIGHBOUR_GAP * np.linalg.norm(p - origin, axis=-1))
    steps = []
    for axis in (1, 0):
        fwd = np.roll(p, -1, axis=axis) - p
        back = p - np.roll(p, 1, axis=axis)
        edge = [slice(None)] * 2
        edge[axis] = -1
        fwd[tuple(edge)] = np.nan
        edge[axis] = 0
        back[tuple(edge)] = np.nan
        nf, nb = np.linalg.norm(fwd, axis=-1), np.linalg.norm(back, axis=-1)
        use_back = ~(nf <= nb) & (nb <= gap)
        step = np.where(use_back[..., None], back, fwd)
        ok = np.where(use_back, nb, nf) <= gap
        steps.append(np.where(ok[..., None], step, np.nan))
    n = np.cross(steps[0], steps[1])
    norm = np.linalg.norm(n, axis=-1)
    good = np.isfinite(norm) & (norm > 1e-12)
    n = np.where(good[..., None], n / np.where(good, norm, 1.0)[..., None], -direction)
    facing = (n * direction).sum(axis=-1)
    n = np.where((facing > 0)[..., None], -n, n)
    return n, np.abs(facing)
