"""Per class, the ring-wise second difference of range d = r - (r_left + r_right) / 2 where the
three pixels share the class (range < 40 m, inserted cars and their neighbours left out):
quantiles of |d| over one row per background of a run.

  python range_scatter.py RUN OUT.json
"""

from __future__ import annotations

import json
import sys

import numpy as np

from falsify.data.real_backgrounds.scanner import INSERTED_INSTANCE
from falsify.jobs.agreement import ok_rows
from falsify.jobs.report import run_lod
from falsify.results.replay import Replay
from falsify.results.store import open_run
from falsify.semantic import TRAIN_CLASSES, train_ids


def ring_scatter(run: str) -> dict[str, list[float]]:
    """{class: [points, |d| p50, p90, p99]} over one ok row per background."""
    data = open_run(run)
    rep = Replay(data.space, lod=run_lod(data.meta))
    acc: dict[int, list[np.ndarray]] = {}
    for _, row in ok_rows(data).groupby("background").head(1).iterrows():
        _, scan = rep.scan(row)
        r, v, tid = scan.image[..., 4], scan.valid, train_ids(scan.semantic)
        rl, rr = np.roll(r, 1, 1), np.roll(r, -1, 1)
        tl, tr = np.roll(tid, 1, 1), np.roll(tid, -1, 1)
        ok = v & np.roll(v, 1, 1) & np.roll(v, -1, 1) & (tid == tl) & (tid == tr) & (r < 40)
        ok[:, 0] = ok[:, -1] = False
        ins = scan.instance >= INSERTED_INSTANCE
        ok &= ~(ins | np.roll(ins, 1, 1) | np.roll(ins, -1, 1))
        d = r - (rl + rr) / 2
        for c in np.unique(tid[ok]):
            acc.setdefault(int(c), []).append(d[ok & (tid == c)])
    out = {}
    for c, parts in sorted(acc.items()):
        x = np.abs(np.concatenate(parts))
        if len(x) >= 200:
            out[TRAIN_CLASSES[c]] = [len(x), *(round(float(q), 4)
                                               for q in np.percentile(x, [50, 90, 99]))]
    return out


if __name__ == "__main__":
    res = ring_scatter(sys.argv[1])
    for name, (n, p50, p90, p99) in res.items():
        print(f"{name:14s} n {n:7d} |d| p50 {p50:.4f} p90 {p90:.4f} p99 {p99:.4f}")
    with open(sys.argv[2], "w") as f:
        json.dump(res, f, indent=1)
