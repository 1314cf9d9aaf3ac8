"""Targeted run against its paired control at the cells that were blind before, per pair.

Reads the maps copied to other-world/ by reproduce-other-world.sh and prints, per --seed pair,
where the targeted run leads and by how much, with the read-out fixed before the runs: a pair
"shows selection matters" if the targeted run leads at >= 2/3 of the blind cells and by > 0.01.
Run from the repo root: python docs/paper-retraining/compare_pairs.py
"""
from __future__ import annotations

import csv
import sys
from pathlib import Path

THRESHOLD = 0.65
PAIRS = {0: ("blind", "control"), 1: ("blind-seed1", "control-seed1"),
         2: ("blind-seed2", "control-seed2")}


def cell_map(path: Path) -> dict[tuple[float, float], float]:
    """Mean IoU per (x, y) cell of one map CSV."""
    with path.open() as f:
        return {(float(r["x"]), float(r["y"])): float(r["miou"]) for r in csv.DictReader(f)}


def main(root: Path) -> None:
    leads = []
    for seed, (targeted, control) in PAIRS.items():
        if not (root / targeted).is_dir() or not (root / control).is_dir():
            continue
        before = cell_map(root / targeted / "miou_before.csv")
        blind = [c for c, v in before.items() if v < THRESHOLD]
        t = cell_map(root / targeted / "miou_after.csv")
        k = cell_map(root / control / "miou_after.csv")
        diff = [t[c] - k[c] for c in blind]
        ahead, lead = sum(d > 0 for d in diff), sum(diff) / len(diff)
        leads.append(lead)
        shows = ahead >= 2 * len(blind) / 3 and lead > 0.01
        print(f"seed {seed}: targeted ahead at {ahead} of {len(blind)} blind cells, mean lead "
              f"{lead:+.4f}; fixed {sum(t[c] >= THRESHOLD for c in blind)} vs "
              f"{sum(k[c] >= THRESHOLD for c in blind)}; "
              f"{'selection matters' if shows else 'not shown'}")
    if leads:
        print(f"mean lead over {len(leads)} pairs: {sum(leads) / len(leads):+.4f}")


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1
         else Path(__file__).resolve().parent / "other-world")
