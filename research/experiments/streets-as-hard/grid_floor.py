"""What a perfect world reaches on a grid of fewer streets than places: each street scores
exactly its own place's real value (the real run's per-place means, and its cells' scores),
so the only gap left is which places the grid's streets stand for. Prints, per probe, W1 and
the 10th percentile of those places' values against all the real run's places, W1 for random
subsets of the same size (the spread an arbitrary choice of places would give), and the cell
map's MAE of those places' real rows against all the real rows.

  python research/experiments/streets-as-hard/grid_floor.py WORLD_RUN REAL_RUN [WORLD REAL ...]
      [--draws 2000] [--json OUT]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from falsify.jobs.agreement import by_place, map_agreement, ok_rows, placed_columns, wasserstein1
from falsify.results.miou_maps import miou_map
from falsify.results.store import open_run


def floor(world_run: str, real_run: str, draws: int) -> dict:
    data = open_run(real_run)
    real, world = by_place(data), by_place(open_run(world_run))
    have = sorted(set(world) & set(real))
    out = {"world": Path(world_run).name, "real": Path(real_run).name, "places": len(real),
           "streets_places": have}
    ok, col = ok_rows(data), placed_columns(data)["iou"]
    mine = ok["background"].map(lambda bg: data.space.background_place(int(bg)) in have)
    full, part = (miou_map(rows, data.space, "x", "y", col) for rows in (ok, ok[mine]))
    out["map_mae"] = map_agreement(part, full, data.threshold).mae
    rng = np.random.default_rng(0)
    for metric in ("precision", "iou"):
        every = np.array([real[p][1][metric] for p in sorted(real)])
        sub = np.array([real[p][1][metric] for p in have])
        rand = [wasserstein1(list(every[rng.choice(len(every), len(have), replace=False)]),
                             list(every)) for _ in range(draws)]
        out[metric] = {"w1": wasserstein1(list(sub), list(every)),
                       "w1_random_median": float(np.median(rand)),
                       "w1_random_p90": float(np.percentile(rand, 90)),
                       "p10_streets_places": float(np.percentile(sub, 10)),
                       "p10_real": float(np.percentile(every, 10))}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("runs", nargs="+", help="pairs: WORLD_RUN REAL_RUN")
    ap.add_argument("--draws", type=int, default=2000)
    ap.add_argument("--json", type=Path)
    a = ap.parse_args()
    if len(a.runs) % 2:
        ap.error("runs come in pairs: WORLD_RUN REAL_RUN")
    rows = [floor(w, r, a.draws) for w, r in zip(a.runs[::2], a.runs[1::2], strict=True)]
    for row in rows:
        print(f"{row['world']}: {len(row['streets_places'])} of {row['places']} places")
        for m in ("precision", "iou"):
            f = row[m]
            print(f"  {m:9s} W1 {f['w1']:.4f} (random subsets: median {f['w1_random_median']:.4f}, "
                  f"90th pct {f['w1_random_p90']:.4f}); p10 {f['p10_streets_places']:.3f} "
                  f"against {f['p10_real']:.3f}")
        print(f"  cell map MAE {row['map_mae']:.4f}")
    if a.json:
        a.json.write_text(json.dumps(rows, indent=1) + "\n")


if __name__ == "__main__":
    main()
