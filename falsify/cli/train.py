"""`falsify train`: train SqueezeSeg on a folder of ``*.npy`` scans (H, W, 6), resumable exactly
(falsify.models.train says what it writes)."""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
from pathlib import Path

from falsify.checks import require_torch
from falsify.cli.signals import stop_signals, stopped_training


def add_arguments(p: argparse.ArgumentParser) -> None:
    from falsify.models.spec import ALL_CHANNELS, DEFAULT_CHANNELS
    from falsify.models.train import CLASS_SETS

    p.add_argument("--data", required=True, help="folder of *.npy scans (H, W, 6)")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--epochs", type=int, default=30, help="epochs over --data (default 30)")
    p.add_argument("--batch", type=int, default=8, help="scans a step (default 8)")
    p.add_argument("--resume", action="store_true",
                   help="continue from OUT/checkpoint.pt, with the run's options (--data, "
                   "--batch, --lr, --seed, --channels, --classes, ...); --epochs may grow")
    p.add_argument("--seed", type=int, default=0,
                   help="fixes the initial weights and the scans' order (default 0)")
    p.add_argument("--time-limit-min", type=float, default=None,
                   help="stop after this many minutes, the finished epochs kept (--resume "
                   "goes on); default: no limit")
    p.add_argument("--val-data", default=None, help="folder of *.npy scans for car IoU")
    p.add_argument("--lr", type=float, default=1e-3, help="learning rate (default 1e-3)")
    p.add_argument("--lr-decay", type=float, default=0.95,
                   help="the rate is lr * lr_decay ** epoch (default 0.95)")
    p.add_argument("--crf-iterations", type=int, default=3, choices=range(4),
                   help="the CRF's mean-field iterations in the network (0: no CRF; default 3)")
    p.add_argument("--channels", default=",".join(DEFAULT_CHANNELS),
                   help=f"comma list from {','.join(ALL_CHANNELS)}")
    p.add_argument("--precision", default="auto", choices=["auto", "bf16", "fp32"],
                   help="auto: bf16 where the CPU (or GPU) computes it natively, else fp32")
    p.add_argument("--threads", type=int, default=2, help="torch CPU threads (default 2)")
    p.add_argument("--max-steps", type=int, default=None, help=argparse.SUPPRESS)
    p.add_argument("--no-export", action="store_true", help="skip the ONNX export at the end")
    p.add_argument("--loss-on", default="backbone", choices=["backbone", "crf"],
                   help="train on the pre-CRF logits (default) or on the CRF's energies")
    p.add_argument("--init", default=None, help="start from these weights (fresh optimiser)")
    p.add_argument("--crf-only", action="store_true",
                   help="train only the CRF compatibility matrices, the backbone frozen")
    p.add_argument("--classes", default="kitti4", choices=CLASS_SETS,
                   help="what channel 5 holds: our four classes or SemanticKITTI's train ids")
    p.add_argument("--device", default="cpu", choices=["cpu", "cuda"],
                   help="where to train (cuda: a CUDA build of torch and a GPU)")
    p.add_argument("--holdout", action="append", default=[], metavar="SPLITS_TOML",
                   help="a split manifest whose held-out scans --data and --val-data may not "
                   "hold (also $FALSIFY_HOLDOUT and a splits.toml beside the data)")
    p.add_argument("--json", action="store_true",
                   help="print the summary as one JSON document on stdout (the epochs' JSON "
                   "lines go to stderr)")


def run(args) -> int:
    """Train (or resume) with the options given; print each epoch's JSON line and the run's
    summary as JSON (with --json the epochs' lines go to stderr, so stdout is one document). A
    signal stops it with every finished step saved and prints the command that continues it."""
    require_torch("falsify train")
    from falsify.models.train import CHECKPOINT, TrainConfig, train

    cfg = TrainConfig(
        data=args.data, out=args.out, epochs=args.epochs, batch=args.batch, seed=args.seed,
        lr=args.lr, lr_decay=args.lr_decay, crf_iterations=args.crf_iterations,
        channels=tuple(c.strip() for c in args.channels.split(",") if c.strip()),
        precision=args.precision, threads=args.threads, time_limit_min=args.time_limit_min,
        val_data=args.val_data, resume=args.resume, max_steps=args.max_steps,
        export=not args.no_export, loss_on=args.loss_on, init=args.init,
        crf_only=args.crf_only, classes=args.classes, device=args.device,
        holdout=tuple(args.holdout))
    try:
        with stop_signals(), contextlib.redirect_stdout(sys.stderr) if args.json else \
                contextlib.nullcontext():
            summary = train(cfg)
    except KeyboardInterrupt as exc:   # SIGINT, SIGTERM: the checkpoint holds every step done
        return stopped_training(exc, args, Path(cfg.out) / CHECKPOINT, "steps")
    print(json.dumps(summary))
    return 0
