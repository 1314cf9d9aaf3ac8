"""What a probe's false car points on the near roadside (sidewalk and terrain within 15 m)
react to: the same replayed scans predicted as cast, with everything but the ground and cars
taken away, with only |y| < 6 m kept, without the rows from 40 down, with the sidewalk lowered
0.12 m, and with every point lifted 0.1 m (as from a sensor 0.1 m lower). Counts a scan.

  python height_sensitivity.py RUN PLACE[,PLACE...] ROWS_PER_PLACE
"""

from __future__ import annotations

import sys

import numpy as np

from falsify.classes import CAR
from falsify.jobs.agreement import _bg_name, _bg_place, ok_rows, spread_rows
from falsify.jobs.report import open_model, run_lod
from falsify.results.replay import Replay
from falsify.results.store import open_run
from falsify.semantic import TRAIN_CLASSES, train_ids

ID = {c: TRAIN_CLASSES.index(c) for c in ("road", "sidewalk", "terrain")}


def cut(img: np.ndarray, gone: np.ndarray) -> np.ndarray:
    out = img.copy()
    out[gone] = 0
    return out


def shifted(img: np.ndarray, valid: np.ndarray, dz: np.ndarray | float) -> np.ndarray:
    out = img.copy()
    out[..., 2] += np.where(valid, dz, 0.0)
    out[..., 4] = np.where(valid, np.linalg.norm(out[..., :3], axis=-1), 0.0)
    return out


def main() -> None:
    run, places, n = sys.argv[1], sys.argv[2].split(","), int(sys.argv[3])
    data = open_run(run)
    rows = ok_rows(data)
    names = {bg: _bg_place(data, bg) or _bg_name(data, bg) for bg in rows.background.unique()}
    seg, _ = open_model(data.meta, True)
    rep = Replay(data.space, lod=run_lod(data.meta))
    for place in places:
        bgs = [bg for bg, name in names.items() if name == place]
        counts: dict[str, list[int]] = {}
        for _, row in spread_rows(rows[rows.background.isin(bgs)], n).iterrows():
            _, scan = rep.scan(row)
            img, v, tid = scan.image, scan.valid, train_ids(scan.semantic)
            side = v & np.isin(tid, [ID["sidewalk"], ID["terrain"]]) & (img[..., 4] < 15)
            ground = np.isin(tid, list(ID.values())) | (scan.label == CAR)
            low_rows = np.broadcast_to(np.arange(v.shape[0])[:, None] >= 40, v.shape)
            cases = {"as cast": img, "ground and cars only": cut(img, ~ground),
                     "|y| < 6 m only": cut(img, np.abs(img[..., 1]) >= 6),
                     "rows 40+ taken away": cut(img, low_rows),
                     "sidewalk 0.12 m lower": shifted(img, v & (tid == ID["sidewalk"]), -0.12),
                     "every point 0.1 m higher": shifted(img, v, 0.1)}
            for name, case in cases.items():
                pred = seg.predict(case[None]).classes[0]
                counts.setdefault(name, []).append(int((side & (pred == CAR)).sum()))
        print(place, {k: round(float(np.mean(c))) for k, c in counts.items()})


if __name__ == "__main__":
    main()
