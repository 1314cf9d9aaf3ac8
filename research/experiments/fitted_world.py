"""The fitted-world training experiment (docs/experiments/fitted_world.md), resumable: every
step whose output exists is skipped, so a killed run continues where it stopped.

    python research/experiments/fitted_world.py data/fitted-world \
        --out research/experiments/fitted-world/results.json
    python research/experiments/fitted_world.py data/fitted-world-parked \
        --profile configs/worlds/semantickitti-fit-parked.json --train-seed 31 --val-seed 32 \
        --init models/weights/squeezeseg.pt --baseline squeezeseg \
        --out research/experiments/fitted-world-parked/results.json

(the first run fine-tuned the network bundled then, now `squeezeseg-v1`; its defaults are
these options').

Steps: the profiled training and validation sets; a fine-tune of the bundled network, one epoch
at a time (each epoch's checkpoint kept); per epoch, the logit adjustment chosen on synthetic
validation and an ONNX export; the fit split's pooled car IoU per epoch, which chooses; the
evaluation split, only reported. Nothing here reads the evaluation split before the choice.
The real scans are read from $SEMANTICKITTI (semantickitti-mini). A work folder whose epochs
were trained elsewhere (gpu_new_world.sh: epochE-adjusted.pt, adjust-epochE.json,
epochE/squeezeseg.onnx) is scored without datasets: `--epochs 3`.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
MINI = Path(os.environ.get("SEMANTICKITTI", "semantickitti-mini"))   # a SemanticKITTI root
PROFILE = ROOT / "configs" / "worlds" / "semantickitti-fit.json"
INIT = ROOT / "models" / "weights" / "squeezeseg-v1.pt"
BASELINE = "squeezeseg-v1"
FIT = "01,02,04,05,07,09,10"
EVALUATION = "00,03,06,08"
EPOCHS = 1
RECIPE = ["--lr", "1.5e-4", "--lr-decay", "0.7", "--batch", "8"]
ALPHAS = "0,0.25,0.5,0.6,0.65,0.7,0.75,0.8,0.85,0.9,1.0"


def run(cmd: list[str], log: Path | None = None) -> str:
    print("+", " ".join(cmd), flush=True)
    res = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
    if log is not None:
        log.write_text(res.stdout + res.stderr)
    if res.returncode != 0:
        sys.exit(f"failed ({res.returncode}): {' '.join(cmd)}\n{res.stderr[-2000:]}")
    return res.stdout


def dataset(out: Path, scans: int, seed: int, first: int, backgrounds: int,
            profile: Path) -> None:
    if (out / "index.json").exists() and len(list(out.glob("*.npy"))) >= scans:
        return
    run(["falsify", "dataset", "configs/paper.toml", "--scans", str(scans), "--seed", str(seed),
         "--first-background", str(first), "--backgrounds", str(backgrounds), "--world",
         str(profile), "--out", str(out), "--workers", "2", "--json"])


def car(pred: dict) -> dict:
    """Pooled and per-sequence car IoU / precision / recall of a `predict --json` result."""
    def pick(c: dict) -> dict:
        return {k: c[k] for k in ("iou", "precision", "recall", "tp", "fp", "fn")}
    return {"pooled": pick(pred["pooled"]["car"]),
            **{s["name"]: pick(s["pooled"]["car"]) for s in pred["sets"]}}


def predict(model: Path | str, sequences: str, out: Path) -> dict:
    if not (out / "predict.json").exists():
        text = run(["falsify", "predict", str(MINI), "--sequences", sequences, "--model",
                    str(model), "--out", str(out), "--json"])
        (out / "predict.json").write_text(text)
    return car(json.loads((out / "predict.json").read_text()))


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("work", type=Path)
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--profile", type=Path, default=PROFILE)
    p.add_argument("--train-seed", type=int, default=21)
    p.add_argument("--val-seed", type=int, default=22)
    p.add_argument("--init", type=Path, default=INIT, help="the weights fine-tuned")
    p.add_argument("--baseline", default=BASELINE, help="the network to beat on the fit split")
    p.add_argument("--epochs", type=int, default=EPOCHS)
    a = p.parse_args()
    work = a.work.resolve()
    work.mkdir(parents=True, exist_ok=True)
    train, val = work / "train", work / "val"
    profile = a.profile.resolve()
    # A work folder whose epochs were trained elsewhere (gpu_new_world.sh) needs no datasets.
    if not all((work / f"epoch{e}" / "squeezeseg.onnx").exists() for e in range(1, a.epochs + 1)):
        dataset(train, 4000, a.train_seed, 1000, 625, profile)
        dataset(val, 400, a.val_seed, 5000, 50, profile)

    result: dict = {"profile": str(profile.relative_to(ROOT)), "init": a.init.name,
                    "baseline": a.baseline, "epochs": {}}
    result["bundled_fit"] = predict(a.baseline, FIT, work / "bundled-fit")
    model_dir = work / "model"
    for e in range(1, a.epochs + 1):
        kept = work / f"epoch{e}-checkpoint.pt"
        adjusted = work / f"epoch{e}-adjusted.pt"
        if not kept.exists() and not adjusted.exists():
            resume = ["--resume"] if (model_dir / "checkpoint.pt").exists() else ["--init",
                                                                                   str(a.init.resolve())]
            run(["falsify", "train", "--data", str(train), "--out",
                 str(model_dir), "--epochs", str(e), "--val-data", str(val), "--no-export",
                 *RECIPE, *resume], log=work / f"train-epoch{e}.log")
            shutil.copyfile(model_dir / "checkpoint.pt", kept)
        if not adjusted.exists():
            run(["falsify", "adjust", str(kept), "--val", str(val),
                 "--out", str(adjusted), "--alphas", ALPHAS, "--json"],
                log=work / f"adjust-epoch{e}.json")
        onnx = work / f"epoch{e}" / "squeezeseg.onnx"
        if not onnx.exists():
            run(["falsify", "export", str(adjusted), "--out", str(onnx)])
        adjust = json.loads((work / f"adjust-epoch{e}.json").read_text())
        result["epochs"][e] = {"adjust": adjust,
                               "fit": predict(onnx, FIT, work / f"epoch{e}-fit")}
    best = max(result["epochs"], key=lambda e: result["epochs"][e]["fit"]["pooled"]["iou"])
    result["chosen_epoch"] = best
    result["ships"] = (result["epochs"][best]["fit"]["pooled"]["iou"]
                       > result["bundled_fit"]["pooled"]["iou"])
    # Only now, and only to report: the evaluation split, for the chosen epoch and the bundled.
    onnx = work / f"epoch{best}" / "squeezeseg.onnx"
    result["chosen_evaluation"] = predict(onnx, EVALUATION, work / "chosen-eval")
    result["bundled_evaluation"] = predict(a.baseline, EVALUATION, work / "bundled-eval")
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps(result, indent=2, sort_keys=True) + "\n")
    print(json.dumps({k: result[k] for k in ("chosen_epoch", "ships")}))


if __name__ == "__main__":
    main()
