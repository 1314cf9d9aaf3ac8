"""`falsify agreement`: how alike a network fails on our streets and on real scans."""

from __future__ import annotations

import argparse

from falsify.cli.common import emit


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("world_run", help="run directory of the world (our streets)")
    p.add_argument("real_run", help="run directory of the same positions on real scans")
    p.add_argument("--threshold", type=float, metavar="T",
                   help="mIoU below which a cell is blind (default: the real run's)")
    p.add_argument("--fp-samples", type=int, default=0, metavar="N",
                   help="replay N rows of each run to count false-positive car points by "
                   "the class they lie on (default 0: skip)")
    p.add_argument("--json", action="store_true")


def run(args) -> int:
    from falsify.jobs.agreement import format_text, run_agreement

    result = run_agreement(args.world_run, args.real_run, threshold=args.threshold,
                           fp_samples=args.fp_samples)
    emit(args, result.to_json(), format_text(result))
    return 0
