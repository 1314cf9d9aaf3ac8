"""What a perfect world reaches on a grid of fewer streets than places: `falsify agreement`'s
floor (each street scoring exactly its own place's real value), beside W1 for random subsets of
the real places of the same size (the spread an arbitrary choice of places would give).

  python research/experiments/streets-as-hard/grid_floor.py WORLD_RUN REAL_RUN [WORLD REAL ...]
      [--draws 2000] [--json OUT]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from falsify.jobs.agreement import METRICS, run_agreement, wasserstein1


def floor(world_run: str, real_run: str, draws: int) -> dict:
    res = run_agreement(world_run, real_run)
    if res.floor is None:
        raise SystemExit(f"{world_run}: its streets stand for no place of {real_run}")
    out = {"world": Path(world_run).name, "real": Path(real_run).name, **res.floor.to_json()}
    rng = np.random.default_rng(0)
    for m in res.metrics:
        every = np.array([v for v in m.real_values.values() if np.isfinite(v)])
        rand = [wasserstein1(list(rng.choice(every, res.floor.places, replace=False)),
                             list(every)) for _ in range(draws)]
        out.setdefault("w1_random_median", {})[m.metric] = float(np.median(rand))
        out.setdefault("w1_random_p90", {})[m.metric] = float(np.percentile(rand, 90))
        out.setdefault("p10_real", {})[m.metric] = m.real.p10
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
        print(f"{row['world']}: {row['places']} of {row['real_places']} places, "
              f"map MAE {row['map_mae']:.4f}")
        for m in METRICS:
            print(f"  {m:9s} W1 {row['w1'][m]:.4f} (random subsets: median "
                  f"{row['w1_random_median'][m]:.4f}, 90th pct {row['w1_random_p90'][m]:.4f}); "
                  f"p10 {row['p10'][m]:.3f} against {row['p10_real'][m]:.3f}")
    if a.json:
        a.json.write_text(json.dumps(rows, indent=1) + "\n")


if __name__ == "__main__":
    main()
