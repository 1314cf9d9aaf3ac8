"""Where a probe's false car points lie, per real place a run's backgrounds are or stand for:
points a scan by SemanticKITTI class, and the 10/50/90th percentiles of their height (sensor
frame), range, |y| and the surface's tilt (|n_z| from range-image neighbours), over n rows of
each place spread in evaluation order, replayed and predicted again with the run's model.

  python false_cars_by_place.py RUN PLACE[,PLACE...] N
"""

from __future__ import annotations

import sys

import numpy as np

from falsify.classes import CAR
from falsify.jobs.agreement import _bg_place, ok_rows, spread_rows
from falsify.jobs.report import open_model, run_lod
from falsify.results.replay import Replay
from falsify.results.store import open_run
from falsify.semantic import TRAIN_CLASSES, train_ids


def tilt(image: np.ndarray) -> np.ndarray:
    """|n_z| of each pixel's surface, from the cross product of its neighbours' differences."""
    xyz = image[..., :3]
    n = np.cross(np.roll(xyz, -1, 1) - np.roll(xyz, 1, 1), np.roll(xyz, -1, 0) - np.roll(xyz, 1, 0))
    return np.abs(n[..., 2]) / (np.linalg.norm(n, axis=-1) + 1e-9)


def false_cars(run: str, places: list[str], n: int) -> dict[str, dict]:
    data = open_run(run)
    rows = ok_rows(data)
    seg, _ = open_model(data.meta, True)
    replay = Replay(data.space, lod=run_lod(data.meta))
    out = {}
    for place in places:
        bgs = [bg for bg in rows["background"].unique() if _bg_place(data, bg) == place]
        picked = spread_rows(rows[rows["background"].isin(bgs)], n)
        parts = []
        for _, row in picked.iterrows():
            _, scan = replay.scan(row)
            img = scan.image
            fp = scan.valid & (seg.predict(img[None]).classes[0] == CAR) & (scan.label != CAR)
            parts.append(np.column_stack([img[..., 2][fp], img[..., 4][fp], np.abs(img[..., 1][fp]),
                                          tilt(img)[fp], train_ids(scan.semantic[fp])]))
        a = np.concatenate(parts) if parts else np.zeros((0, 5))
        ids, counts = np.unique(a[:, 4].astype(int), return_counts=True)
        q = {k: [round(float(v), 2) for v in np.percentile(a[:, c], [10, 50, 90])] if len(a)
             else None for c, k in enumerate(("z", "range", "abs_y", "tilt"))}
        out[place] = {"rows": len(picked), "per_scan": round(len(a) / max(len(picked), 1)),
                      "by_class": {TRAIN_CLASSES[i]: round(c / len(picked))
                                   for i, c in zip(ids, counts, strict=True)}, **q}
    return out


if __name__ == "__main__":
    for place, r in false_cars(sys.argv[1], sys.argv[2].split(","), int(sys.argv[3])).items():
        print(place, r)
