"""Per place of the fit split: the median height over the fitted road plane of the roadside
ground (sidewalk, terrain) in the strip from 0.2 m inside to 3 m beyond each road edge
(fit-world's edges), 5-15 m ahead, with its point count.

  python roadside_height.py SEMANTICKITTI_ROOT
"""

from __future__ import annotations

import sys

import numpy as np

from falsify.jobs.fit_world import (
    GROUP_IDS,
    ROAD_IDS,
    ground_plane,
    labelled_scans,
    place_of,
    scene_stats,
)
from falsify.semantic import RAW_ID, split_label

FIT = ["01", "02", "04", "05", "07", "09", "10"]

for name, pts, lab in labelled_scans([sys.argv[1]], FIT):
    sem = split_label(lab)[0]
    x, y, z = (pts[:, k].astype(float) for k in range(3))
    road = (x > 0) & (np.abs(y) <= x) & np.isin(sem, ROAD_IDS) & (np.hypot(x, y) < 30)
    a, b, c, _ = ground_plane(x[road], y[road], z[road])
    h = z - (a * x + b * y + c)
    place = place_of(name, pts, lab, scene_stats(name, pts, lab))
    cols = [name]
    for sign, edge in ((1, place.edge_left_m), (-1, place.edge_right_m)):
        strip = (x > 5) & (x < 15) & (sign * y > edge - 0.2) & (sign * y < edge + 3.0)
        for group in ("sidewalk", "terrain"):
            on = strip & np.isin(sem, [RAW_ID[k] for k in GROUP_IDS[group] if k in RAW_ID])
            med = float(np.median(h[on])) if on.sum() > 20 else float("nan")
            cols.append(f"{'L' if sign > 0 else 'R'} {group} n {on.sum():4d} h {med:+.2f}")
    print("  ".join(cols))
