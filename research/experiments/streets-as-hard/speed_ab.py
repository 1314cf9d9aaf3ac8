"""Scan rate of today's streets against the streets as built, interleaved: each round times a
block of warm scans of one, then the other (order alternating by round), in the same process(es),
so a VM's drift between rounds moves both sides alike. Prints per-round rates and the ratio.

  python research/experiments/streets-as-hard/speed_ab.py [--rounds 12] [--block 250] [--workers 2]

"Before" is research/experiments/streets-as-hard/paper-as-built.toml cast with the object
frames' return model (kitti-hdl64e); "after" is configs/paper.toml as shipped.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[3]
BEFORE = ROOT / "research/experiments/streets-as-hard/paper-as-built.toml"
AFTER = ROOT / "configs/paper.toml"


def _scanner(config: Path, returns: str | None):
    from falsify.bench.scan import possible, warm
    from falsify.data.real_backgrounds import scanner_for
    from falsify.sensor.lidar import load_sensor
    from falsify.world.space import load_space

    space = load_space(config)
    sensor = load_sensor(space.sensor, **({} if returns is None else {"returns": returns}))
    sim = scanner_for(space, sensor=sensor, lod=2)
    grid = possible(sim, space.grid())
    warm(sim, grid)
    return sim, grid


def _rounds(args) -> list[tuple[float, float, float, float]]:
    """(before s, before n, after s, after n) per round, this process's share of the samples."""
    rounds, block, part, parts = args
    (before, grid_b), (after, grid_a) = _scanner(BEFORE, "kitti-hdl64e"), _scanner(AFTER, None)
    can = {repr(s.as_dict()) for s in grid_a}   # the same samples on both sides: those that
    grid = [s for s in grid_b if repr(s.as_dict()) in can]   # can exist on both streets
    sides = [(before, grid), (after, grid)]
    out = []
    for k in range(rounds):
        times = [0.0, 0.0]
        order = (0, 1) if k % 2 == 0 else (1, 0)
        for side in order:
            sim, grid = sides[side]
            picks = [grid[(k * block + i) % len(grid)] for i in range(part, block, parts)]
            t0 = time.perf_counter()
            for s in picks:
                sim.scan(s)
            times[side] = time.perf_counter() - t0
        out.append((times[0], len(picks), times[1], len(picks)))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--rounds", type=int, default=12)
    ap.add_argument("--block", type=int, default=250)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--json", type=Path)
    a = ap.parse_args()
    from falsify.bench.machine import machine

    result = {"cpu": machine(), "rounds": a.rounds, "block": a.block, "runs": {}}
    for workers in sorted({1, a.workers}):
        if workers == 1:
            parts = [_rounds((a.rounds, a.block, 0, 1))]
        else:
            with mp.get_context("spawn").Pool(workers) as pool:
                parts = pool.map(_rounds, [(a.rounds, a.block, p, workers)
                                           for p in range(workers)])
        rows = []
        for k in range(a.rounds):
            # workers run side by side: a round's rate is its scans over the slowest worker's time
            tb = max(p[k][0] for p in parts)
            ta = max(p[k][2] for p in parts)
            nb = sum(p[k][1] for p in parts)
            na = sum(p[k][3] for p in parts)
            rows.append({"before": nb / tb, "after": na / ta, "ratio": (na / ta) / (nb / tb)})
            print(f"{workers} process(es), round {k + 1:2d}: before {nb / tb:7.1f} scans/s, "
                  f"after {na / ta:7.1f}, ratio {rows[-1]['ratio']:.2f}")
        ratios = sorted(r["ratio"] for r in rows)
        print(f"{workers} process(es): ratio min {ratios[0]:.2f}, median "
              f"{ratios[len(ratios) // 2]:.2f}, max {ratios[-1]:.2f}")
        result["runs"][str(workers)] = rows
    if a.json:
        a.json.write_text(json.dumps(result, indent=1) + "\n")


if __name__ == "__main__":
    main()
