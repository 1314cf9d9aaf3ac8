"""What-if of the vegetation's ring-wise range scatter (range_scatter.py's |d|) on a run's
streets with the foliage and hedge pass-through probabilities scaled, and optionally each leafy
hit moved behind its mesh by an exponential depth (variant W's canopy depth, not in falsify):
the fit of variants V and W in docs/experiments/streets_as_hard.md.

  python vegetation_scatter.py RUN SCALE [DEPTH_M]

SCALE multiplies the shipped pass probabilities (foliage 0.45, hedge 0.25); the streets are
rebuilt in this process, so nothing outside it changes.
"""

from __future__ import annotations

import sys

import numpy as np
from range_scatter import ring_scatter

from falsify.sensor import raycast, simulator
from falsify.world import materials


def canopy_depth(mean_m: float):
    """A cast_through that moves each foliage or hedge hit behind its mesh by an exponential
    depth of mean `mean_m`, hash-decided per ray and triangle."""
    leafy = np.zeros(len(materials.MATERIALS), bool)
    leafy[[materials.MATERIAL_ID["foliage"], materials.MATERIAL_ID["hedge"]]] = True
    plain = raycast.cast_through

    def cast(caster, origin, dirs, max_dist, face_pass, ray_ids, seed):
        t, prim = plain(caster, origin, dirs, max_dist, face_pass, ray_ids, seed)
        # a triangle is leafy where its pass probability is a leafy material's
        leafy_p = materials.PASS_PROB[leafy]
        hit = np.flatnonzero(prim >= 0)
        on = np.isin(face_pass[prim[hit]], leafy_p) & (face_pass[prim[hit]] > 0)
        idx = hit[on]
        u = raycast.unit_hash(ray_ids[idx], prim[idx], seed ^ 0x1EAF)
        t = t.copy()
        t[idx] += -mean_m * np.log1p(-u)
        return t, prim
    return cast


if __name__ == "__main__":
    scale = float(sys.argv[2])
    for name in ("foliage", "hedge"):
        materials.PASS_PROB[materials.MATERIAL_ID[name]] *= scale
    if len(sys.argv) > 3:
        simulator.cast_through = canopy_depth(float(sys.argv[3]))
    n, p50, p90, p99 = ring_scatter(sys.argv[1])["vegetation"]
    print(f"scale {scale} depth {sys.argv[3] if len(sys.argv) > 3 else 0}: vegetation n {n} "
          f"|d| p50 {p50:.4f} p90 {p90:.4f} p99 {p99:.4f}")
