"""Per-class intensity of the fit split's real scans against a space's streets, front 90 degrees:
W1, median and interquartile range per SemanticKITTI training class, and the mean W1 over the
classes above 2 % of the real points (one column per config).

    python research/experiments/streets-as-hard/intensity_by_class.py $SEMANTICKITTI \
        configs/paper.toml [OTHER_CONFIG ...] [--json OUT]
"""

from __future__ import annotations

import argparse
import json

import numpy as np
from scipy.stats import wasserstein_distance

from falsify.data.velodyne import kitti_arrays
from falsify.jobs.fit_world import labelled_scans
from falsify.semantic import TRAIN_CLASSES, split_label, train_ids
from falsify.sensor.lidar import load_sensor
from falsify.sensor.simulator import Simulator
from falsify.world.space import load_space

FIT = ["01", "02", "04", "05", "07", "09", "10"]


def front(p: np.ndarray) -> np.ndarray:
    return (p[:, 0] > 0) & (np.abs(p[:, 1]) < p[:, 0])


def by_class(pairs) -> dict[int, np.ndarray]:
    """Intensities of the front points per train id, over (points, labels) pairs."""
    out: dict[int, list] = {}
    for p, lab in pairs:
        t, m = train_ids(split_label(lab)[0]), front(p)
        for c in np.unique(t[m]):
            out.setdefault(int(c), []).append(p[m & (t == c), 3])
    return {c: np.concatenate(v) for c, v in out.items()}


def streets(config: str):
    """(points, labels) of each background of the space, no car placed, seed = background."""
    space = load_space(config)
    sim = Simulator(load_sensor(space.sensor), background_source=space.background_source())
    for bg in space.dims["background"].values:
        yield kitti_arrays(sim.render(bg, [], sim.ego_pose(bg), np.random.default_rng(bg)))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("semantickitti")
    ap.add_argument("configs", nargs="+")
    ap.add_argument("--json")
    a = ap.parse_args()
    real = by_class((p, lab) for _, p, lab in labelled_scans([a.semantickitti], FIT))
    total = sum(len(v) for v in real.values())
    doc = {}
    for cfg in a.configs:
        syn = by_class(streets(cfg))
        rows = {}
        for c, r in sorted(real.items()):
            s = syn.get(c)
            if s is None or len(s) < 50:
                continue
            q = lambda v: float(np.subtract(*np.percentile(v, [75, 25])))  # noqa: E731
            rows[TRAIN_CLASSES[c]] = {"share": len(r) / total,
                                      "w1": float(wasserstein_distance(r, s)),
                                      "median": [float(np.median(r)), float(np.median(s))],
                                      "iqr": [q(r), q(s)]}
        big = [v["w1"] for v in rows.values() if v["share"] > 0.02]
        doc[cfg] = {"classes": rows, "mean_w1_above_2pct": float(np.mean(big))}
        print(f"{cfg}: mean W1 over classes above 2 %: {np.mean(big):.4f}")
        for k, v in rows.items():
            print(f"  {k:14s} share {v['share']:.3f} W1 {v['w1']:.3f} median real "
                  f"{v['median'][0]:.3f} streets {v['median'][1]:.3f} IQR real {v['iqr'][0]:.3f} "
                  f"streets {v['iqr'][1]:.3f}")
    if a.json:
        with open(a.json, "w") as f:
            json.dump(doc, f, indent=1)


if __name__ == "__main__":
    main()
