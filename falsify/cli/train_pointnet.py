"""`falsify train-pointnet`: train the reference PointNet (falsify.models.pointnet) on npy scans
with SemanticKITTI train ids."""

from __future__ import annotations

import argparse
import json


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--data", required=True)
    p.add_argument("--out", required=True)
    p.add_argument("--val-data", default=None)
    p.add_argument("--epochs", type=int, default=20)
    p.add_argument("--batch", type=int, default=16)
    p.add_argument("--points", type=int, default=16384)
    p.add_argument("--lr", type=float, default=1e-3)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    p.add_argument("--time-limit-min", type=float, default=None)


def run(args) -> int:
    """Train; print the last epoch's log line as JSON."""
    from falsify.models.pointnet import train  # imports torch

    last = train(args.data, args.out, args.epochs, args.batch, args.points, args.lr, args.seed,
                 args.device, args.time_limit_min, args.val_data)
    print(json.dumps(last))
    return 0
