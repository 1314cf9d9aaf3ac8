"""`falsify train-pointnet`: train the reference PointNet (falsify.models.pointnet) on npy scans
with SemanticKITTI train ids, resumable exactly (falsify.models.train_pointnet says what it
writes)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from falsify.checks import require_torch
from falsify.cli.common import emit, holdout_option
from falsify.cli.signals import stop_signals, stopped_training


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--data", required=True,
                   help="folder of *.npy scans (H, W, 6) whose label channel holds SemanticKITTI "
                   "train ids (falsify dataset --labels semantickitti)")
    p.add_argument("--out", required=True,
                   help="output folder: checkpoint.pt, train_log.jsonl, pointnet.pt, "
                   "pointnet.onnx + .json; one holding a run needs --resume")
    p.add_argument("--val-data", default=None,
                   help="folder of *.npy scans scored after each epoch (val_car_iou, val_miou; "
                   "default: none)")
    p.add_argument("--epochs", type=int, default=20, help="epochs to train, >= 1 (default 20)")
    p.add_argument("--batch", type=int, default=16, help="scans a step, >= 1 (default 16)")
    p.add_argument("--points", type=int, default=16384,
                   help="points drawn from each scan a step, >= 1 (default 16384)")
    p.add_argument("--lr", type=float, default=1e-3, help="Adam's learning rate, > 0 "
                   "(default 0.001)")
    p.add_argument("--seed", type=int, default=0, help="seeds the weights and the points drawn "
                   "(default 0)")
    p.add_argument("--device", default="cpu", choices=["cpu", "cuda"],
                   help="where to train (default cpu)")
    p.add_argument("--time-limit-min", type=float, default=None,
                   help="stop after the epoch that passes this many minutes, and export "
                   "(default: no limit)")
    p.add_argument("--resume", action="store_true",
                   help="continue from OUT/checkpoint.pt with the run's options (--data, --batch, "
                   "--points, --lr, --seed); --epochs may grow")
    holdout_option(p)
    p.add_argument("--json", action="store_true",
                   help="print the summary as one JSON document (the epochs' lines go to stderr)")


def run(args) -> int:
    """Train (or resume); print each epoch's line and the run's summary (JSON with --json). A
    signal stops it with its finished epochs saved and prints the command that continues it."""
    require_torch("falsify train-pointnet")
    from falsify.models.train_pointnet import CHECKPOINT, PointNetTrainConfig, train

    cfg = PointNetTrainConfig(
        data=args.data, out=args.out, epochs=args.epochs, batch=args.batch, points=args.points,
        lr=args.lr, seed=args.seed, device=args.device, time_limit_min=args.time_limit_min,
        val_data=args.val_data, resume=args.resume, holdout=tuple(args.holdout or ()))
    stream = sys.stderr if args.json else sys.stdout
    try:
        with stop_signals():
            summary = train(cfg, lambda r: print(epoch_text(r, cfg.epochs), file=stream,
                                                  flush=True))
    except KeyboardInterrupt as exc:   # SIGINT, SIGTERM: the checkpoint holds every epoch done
        return stopped_training(exc, args, Path(cfg.out) / CHECKPOINT, "epochs")
    emit(args, summary, summary_text(summary))
    return 0


def epoch_text(record: dict, epochs: int) -> str:
    """One epoch's progress line: its loss, validation IoU where scored, and seconds."""
    val = "" if record.get("val_miou") is None and record.get("val_car_iou") is None else (
        f", val mIoU {_num(record.get('val_miou'))}, car IoU {_num(record.get('val_car_iou'))}")
    return (f"epoch {record['epoch']}/{epochs}: loss {record['loss']:.4f}{val}, "
            f"{record['seconds']} s")


def summary_text(s: dict) -> str:
    """The run's summary in a few lines: epochs trained and why it stopped, the last loss and
    validation IoU, the files written."""
    why = "" if s["stopped"] == "done" else f" (stopped: {s['stopped']}; --resume goes on)"
    lines = [f"trained {s['epoch']} of {s['epochs']} epochs in {s['seconds']} s{why}: loss "
             f"{s['loss']:.4f}, val mIoU {_num(s['val_miou'])}, car IoU "
             f"{_num(s['val_car_iou'])}",
             f"weights: {s['weights']}, {s['onnx']} (+ .json); log: {s['log']}"]
    return "\n".join(lines)


def _num(value: float | None) -> str:
    return "-" if value is None else f"{value:.3f}"

