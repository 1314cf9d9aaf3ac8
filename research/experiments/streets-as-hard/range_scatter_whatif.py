"""What-if: add per-class range scatter to replayed street scans and compare each street's car
IoU and precision with its place's, clean and scattered. Sigma per class: the real run's
ring-wise |d| median less the streets' own in quadrature, over 0.6745 * sqrt(1.5) (the median of
|d| for iid Gaussian noise of unit sigma); classes the streets already scatter more take none.

  python range_scatter_whatif.py WORLD_RUN REAL_RUN ROWS_PER_STREET REAL.json STREETS.json
(REAL.json, STREETS.json: range_scatter.py on the real run and on the world run)
"""

from __future__ import annotations

import json
import sys

import numpy as np

from falsify.classes import CAR
from falsify.jobs.agreement import _bg_place, by_place, ok_rows, spread_rows, wasserstein1
from falsify.jobs.report import open_model, run_lod
from falsify.results.replay import Replay
from falsify.results.store import open_run
from falsify.semantic import TRAIN_CLASSES, train_ids


def car_scores(pred: np.ndarray, label: np.ndarray, valid: np.ndarray) -> tuple[float, float]:
    p, g = valid & (pred == CAR), valid & (label == CAR)
    tp, union = (p & g).sum(), (p | g).sum()
    return (tp / union if union else np.nan), (tp / p.sum() if p.sum() else np.nan)


def main() -> None:
    world, real, n = sys.argv[1], sys.argv[2], int(sys.argv[3])
    real_d, street_d = (json.load(open(p)) for p in sys.argv[4:6])
    sigma = np.zeros(len(TRAIN_CLASSES), np.float32)
    for k, name in enumerate(TRAIN_CLASSES):
        if name in real_d:
            own = street_d.get(name, [0, 0.0])[1]
            sigma[k] = np.sqrt(max(0.0, real_d[name][1] ** 2 - own ** 2)) / (0.6745 * 1.5 ** 0.5)
    print({TRAIN_CLASSES[k]: round(float(s), 4) for k, s in enumerate(sigma) if s})
    data = open_run(world)
    rows = ok_rows(data)
    seg, _ = open_model(data.meta, True)
    rep = Replay(data.space, lod=run_lod(data.meta))
    rng = np.random.default_rng(0)
    res = {}
    for bg in sorted(rows.background.unique()):
        scores = []
        for _, row in spread_rows(rows[rows.background == bg], n).iterrows():
            _, scan = rep.scan(row)
            img, v = scan.image.copy(), scan.valid
            clean = seg.predict(img[None]).classes[0]
            r = img[..., 4]
            e = rng.standard_normal(r.shape).astype(np.float32) * sigma[train_ids(scan.semantic)]
            img[..., :3] *= np.where(v, (r + e) / np.maximum(r, 1e-3), 1.0)[..., None]
            img[..., 4] = np.where(v, r + e, 0)
            noisy = seg.predict(img[None]).classes[0]
            scores.append(car_scores(clean, scan.label, v) + car_scores(noisy, scan.label, v))
        res[_bg_place(data, bg)] = np.nanmean(np.array(scores, float), 0)
    places = {k: v[1] for k, v in by_place(open_run(real)).items()}
    print("place      real iou/precision | street clean | street scattered")
    for pl in sorted(res):
        if pl in places:
            a = res[pl]
            print(f"{pl:10s} {places[pl]['iou']:.3f}/{places[pl]['precision']:.3f} | "
                  f"{a[0]:.3f}/{a[1]:.3f} | {a[2]:.3f}/{a[3]:.3f}")
    ri = [p["iou"] for p in places.values()]
    rp = [p["precision"] for p in places.values()]
    for j, label in ((0, "clean"), (2, "scattered")):
        wi, wp = [res[p][j] for p in res], [res[p][j + 1] for p in res]
        mae = np.mean([abs(res[p][j] - places[p]["iou"]) for p in res if p in places])
        print(f"{label}: W1 IoU {wasserstein1(wi, ri):.3f}, W1 precision "
              f"{wasserstein1(wp, rp):.3f}, 10th pct {np.percentile(wi, 10):.3f} / "
              f"{np.percentile(ri, 10):.3f}, per-place MAE {mae:.3f}")


if __name__ == "__main__":
    main()
