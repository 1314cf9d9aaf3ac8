"""Targeted run against its paired control at the cells that were blind before, per pair.

Reads the maps copied to other-world/ by reproduce-other-world.sh and prints, per --seed pair,
where the targeted run leads and by how much, with the read-outs fixed before the runs: a pair
"shows selection matters" if the targeted run leads at >= 2/3 of the blind cells and by > 0.01
(the control wins a pair by the mirror); over all pairs, selection matters if it does in a
majority of pairs and the mean lead over the pairs is > 0.01 (the control wins by the mirror),
otherwise it is not resolved. Run from the repo root:
python research/paper-retraining/compare_pairs.py
"""
from __future__ import annotations

import csv
import sys
from pathlib import Path

THRESHOLD = 0.65
BAR = 0.01


def cell_map(path: Path) -> dict[tuple[float, float], float]:
    """Mean IoU per (x, y) cell of one map CSV."""
    with path.open() as f:
        return {(float(r["x"]), float(r["y"])): float(r["miou"]) for r in csv.DictReader(f)}


def pairs(root: Path) -> list[tuple[int, Path, Path]]:
    """(seed, targeted run, control run) for every seed with both: seed 0 is blind/ and
    control/, seed N blind-seedN/ and control-seedN/."""
    out = []
    for targeted in root.glob("blind*"):
        name = targeted.name
        seed = 0 if name == "blind" else int(name.removeprefix("blind-seed"))
        control = root / targeted.name.replace("blind", "control")
        if control.is_dir():
            out.append((seed, targeted, control))
    return sorted(out)


def main(root: Path) -> None:
    leads, wins, losses = [], 0, 0
    for seed, targeted, control in pairs(root):
        before = cell_map(targeted / "miou_before.csv")
        blind = [c for c, v in before.items() if v < THRESHOLD]
        t = cell_map(targeted / "miou_after.csv")
        k = cell_map(control / "miou_after.csv")
        diff = [t[c] - k[c] for c in blind]
        ahead, lead = sum(d > 0 for d in diff), sum(diff) / len(diff)
        leads.append(lead)
        won = ahead >= 2 * len(blind) / 3 and lead > BAR
        lost = len(blind) - ahead >= 2 * len(blind) / 3 and lead < -BAR
        wins, losses = wins + won, losses + lost
        verdict = "selection matters" if won else "the control wins" if lost else "not shown"
        print(f"seed {seed}: targeted ahead at {ahead} of {len(blind)} blind cells, mean lead "
              f"{lead:+.4f}; fixed {sum(t[c] >= THRESHOLD for c in blind)} vs "
              f"{sum(k[c] >= THRESHOLD for c in blind)}; {verdict}")
    if leads:
        mean = sum(leads) / len(leads)
        if wins > len(leads) / 2 and mean > BAR:
            pooled = "selection matters"
        elif losses > len(leads) / 2 and mean < -BAR:
            pooled = "the control wins"
        else:
            pooled = f"not resolved with {len(leads)} pairs"
        print(f"over {len(leads)} pairs: targeted wins {wins}, control wins {losses}, mean lead "
              f"{mean:+.4f}: {pooled}")


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1
         else Path(__file__).resolve().parent / "other-world")
