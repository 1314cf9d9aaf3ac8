"""The designed-hole experiment: find a hole, explain it, retrain on it, against a random control.

Step 1 measures the hole the issue proposed (crossing and turning headings) with both bundled
SqueezeSegs over twelve headings (designed-hole/yaw.toml). Step 2 is the experiment, on a hole
that is there: dense fog (50 m visibility) in designed-hole/hole.toml, which the bundled network,
trained on clear-weather scans only, has never seen. For each seed, two `falsify retrain` runs:

  targeted  --selection rules   R's samples under the rules `falsify explain` finds on V
  control   --selection random  as many of R's samples, drawn at random from the whole space

Both fine-tune the same weights on the same 600 of the network's own training scans plus their
selected scans, for the same epochs; the seed sets the training order (and the control's draw),
so seed s of one arm pairs with seed s of the other. The read-out, fixed before the runs: the
targeted run wins a pair if its mean car IoU over V's samples under the rules (the hole) beats
the control's by at least 0.05, and no held-out set (drive-style synthetic, the real KITTI sets,
semantickitti-mini's evaluation split) drops by more than 0.01 car IoU in either arm.

    python research/experiments/designed_hole.py data/designed-hole \
        --out research/experiments/designed-hole/results.json

Resumable: finished grids and retraining runs are reused (`falsify retrain --resume`).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]
HOLE = HERE / "designed-hole" / "hole.toml"
YAW = HERE / "designed-hole" / "yaw.toml"
MODEL = ROOT / "models" / "weights" / "squeezeseg.onnx"
WIN = 0.05          # the targeted run's lead on the hole's mean that wins a pair
MAX_DROP = 0.01     # the most any held-out set may drop
RECIPE = ["--validation-backgrounds", "0-2", "--retraining-backgrounds", "3-6",
          "--train-scans", "600", "--oversample", "1", "--epochs", "2", "--workers", "2"]


def falsify(*args: str) -> dict:
    """Run a falsify command with --json; its parsed output."""
    done = subprocess.run([sys.executable, "-m", "falsify", *args, "--json"], check=True,
                          capture_output=True, text=True)
    return json.loads(done.stdout)


def yaw_table(work: Path) -> dict:
    """Mean car IoU and samples below the threshold per heading, for both bundled networks."""
    from falsify.results.store import open_run

    out = {}
    for model in ("squeezeseg", "squeezeseg-drive"):
        run = work / f"yaw-{model}"
        falsify("grid", str(YAW), "--model", model, "--out", str(run), "--workers", "2",
                "--quiet", *(["--resume"] if (run / "results.sqlite").exists() else []))
        data = open_run(run)
        ok = data.ok
        by = ok.groupby("yaw")[data.score_column]
        out[model] = {f"{yaw:g}": {"mean": round(float(g.mean()), 4),
                                   "below": int((g < data.space.threshold).sum()),
                                   "samples": int(len(g))} for yaw, g in by}
    return out


def retrain(work: Path, selection: str, seed: int) -> dict:
    out = work / f"{selection}-s{seed}"
    args = ["retrain", str(HOLE), "--model", str(MODEL), "--train-data", str(work / "train"),
            "--out", str(out), "--seed", str(seed), "--selection", selection, *RECIPE]
    return falsify(*args, *(["--resume"] if (out / "stages.json").exists() else []))


def checks(summary: dict) -> dict:
    return {c["name"]: {"before": c["before"], "after": c["after"], "change": c["change"]}
            for c in summary["checks"] if c["before"] is not None}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("work", type=Path, help="folder for the runs (resumable)")
    ap.add_argument("--seeds", default="0,1,2")
    ap.add_argument("--out", type=Path, required=True, help="the results JSON")
    args = ap.parse_args()
    work = args.work
    work.mkdir(parents=True, exist_ok=True)
    result: dict = {"yaw": yaw_table(work), "pairs": []}
    if not (work / "train" / "index.json").exists():
        falsify("dataset", str(ROOT / "configs" / "paper.toml"), "--scans", "600", "--seed", "1",
                "--first-background", "1000", "--backgrounds", "625", "--workers", "2",
                "--out", str(work / "train"))
    for seed in map(int, args.seeds.split(",")):
        arms = {sel: retrain(work, sel, seed) for sel in ("rules", "random")}
        t, c = arms["rules"], arms["random"]
        lead = t["region"]["mean_after"] - c["region"]["mean_after"]
        drops = {f"{arm}: {name}": v["change"] for arm, s in (("targeted", t), ("control", c))
                 for name, v in checks(s).items() if v["change"] < -MAX_DROP}
        result["pairs"].append({
            "seed": seed, "rules": t["region"]["rules"], "hole_samples": t["region"]["samples"],
            "hole_before": t["region"]["mean_before"],
            "targeted": {"hole_after": t["region"]["mean_after"],
                         "hole_below_after": t["region"]["below_after"],
                         "scans": t["retraining_scans"], "mean_cells": t["mean_after"],
                         "checks": checks(t)},
            "control": {"hole_after": c["region"]["mean_after"],
                        "hole_below_after": c["region"]["below_after"],
                        "scans": c["retraining_scans"], "mean_cells": c["mean_after"],
                        "checks": checks(c)},
            "lead": round(lead, 4), "drops_over_bound": drops,
            "targeted_wins": lead >= WIN and not drops})
        print(f"seed {seed}: hole {t['region']['mean_before']} -> targeted "
              f"{t['region']['mean_after']}, control {c['region']['mean_after']} "
              f"(lead {lead:+.4f}); drops over {MAX_DROP}: {drops or 'none'}", flush=True)
    wins = sum(p["targeted_wins"] for p in result["pairs"])
    result["read_out"] = (f"targeted wins {wins} of {len(result['pairs'])} pairs "
                          f"(lead >= {WIN} on the hole's mean, no held-out drop over {MAX_DROP})")
    print(result["read_out"])
    args.out.write_text(json.dumps(result, indent=1) + "\n", encoding="utf-8")


if __name__ == "__main__":
    main()
