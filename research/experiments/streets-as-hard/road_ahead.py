"""Where the road lies ahead of the sensor, a street against its place: the median z (sensor
frame) of road points with |y| < 2 m in 5 m steps from 5 to 25 m ahead, and the pitch and roll
of the plane `falsify fit-world` fits to the road within 30 m, one row per background of each
run (a world run and a real run of the same space).

  python road_ahead.py REAL_RUN WORLD_RUN
"""

from __future__ import annotations

import math
import sys

import numpy as np

from falsify.jobs.agreement import _bg_name, _bg_place, ok_rows
from falsify.jobs.fit_world import ground_plane
from falsify.jobs.report import run_lod
from falsify.results.replay import Replay
from falsify.results.store import open_run
from falsify.semantic import TRAIN_CLASSES, train_ids

STEPS = (5.0, 10.0, 15.0, 20.0)


def profiles(run: str) -> dict[str, list[float]]:
    data = open_run(run)
    rep = Replay(data.space, lod=run_lod(data.meta))
    out = {}
    for bg, rows in ok_rows(data).groupby("background"):
        _, scan = rep.scan(rows.iloc[0])
        x, y, z = (scan.image[..., k] for k in range(3))
        road = scan.valid & (train_ids(scan.semantic) == TRAIN_CLASSES.index("road"))
        vals = []
        for x0 in STEPS:
            on = road & (x >= x0) & (x < x0 + 5.0) & (np.abs(y) < 2.0)
            vals.append(float(np.median(z[on])) if on.sum() > 10 else float("nan"))
        near = road & (np.hypot(x, y) < 30.0)
        a, b, _, _ = ground_plane(x[near], y[near], z[near])
        vals += [math.degrees(math.atan(a)), math.degrees(math.atan(b))]
        out[_bg_place(data, bg) or _bg_name(data, bg)] = vals
    return out


if __name__ == "__main__":
    real, world = profiles(sys.argv[1]), profiles(sys.argv[2])
    for place in sorted(real):
        if place in world:
            r, w = real[place], world[place]
            diff = " ".join(f"{b - a:+.2f}" for a, b in zip(r[:4], w[:4], strict=True))
            print(f"{place}  real {' '.join(f'{v:+.2f}' for v in r[:4])}  street - real "
                  f"{diff}  pitch / roll real {r[4]:+.2f} / {r[5]:+.2f}, street "
                  f"{w[4]:+.2f} / {w[5]:+.2f}")
