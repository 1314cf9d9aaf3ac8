"""`falsify export WEIGHTS.pt --out MODEL.onnx`: export trained weights with their spec."""

from __future__ import annotations

import argparse
import json

from falsify.checks import require_torch
from falsify.cli.common import int_in


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("weights", help="a state dict (.pt) or a training checkpoint.pt")
    p.add_argument("--out", required=True, help="the .onnx to write (spec .json beside it)")
    p.add_argument("--crf-iterations", type=int, default=3, choices=range(4),
                   help="the CRF's mean-field iterations in the graph (0: none; default 3)")
    p.add_argument("--height", type=int, default=64, help="range image rows (default 64)")
    p.add_argument("--width", type=int, default=512,
                   help="range image columns (default 512)")
    p.add_argument("--note", action="append", default=[], metavar="KEY=VALUE",
                   help="extra facts recorded in the spec (repeatable)")
    p.add_argument("--int8", default=None, metavar="PATH",
                   help="also write a static int8 copy (CRF kept fp32) to PATH, calibrated on "
                   "training-style synthetic scenes")
    p.add_argument("--calibration-scans", type=int_in(1, 1024), default=None,
                   metavar="N", help="--int8: how many scenes to calibrate on (default 64)")
    p.add_argument("--json", action="store_true",
                   help="the files written are printed as JSON either way; accepted, as "
                   "every command takes it")


def run(args) -> int:
    """Export; print the files written as JSON."""
    require_torch("falsify export")
    from falsify.models.export import export_weights

    written = export_weights(args.weights, args.out, crf_iterations=args.crf_iterations,
                             height=args.height, width=args.width, notes=args.note,
                             int8=args.int8, calibration_scans=args.calibration_scans)
    print(json.dumps(written))
    return 0
