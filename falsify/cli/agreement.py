"""`falsify agreement`: how alike a network fails on our streets and on real scans; with
limits, a check that exits 1 when the world misses one."""

from __future__ import annotations

import argparse

from falsify.cli.common import ALLOW_INCOMPLETE_HELP, emit


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("world_run", help="run directory of the world (our streets)")
    p.add_argument("real_run", help="run directory of the same positions on real scans")
    p.add_argument("--threshold", type=float, metavar="T",
                   help="mIoU below which a cell is blind (default: the real run's)")
    p.add_argument("--fp-samples", type=int, default=0, metavar="N",
                   help="replay N rows of each run to count false-positive car points by "
                   "the class they lie on (default 0: skip)")
    lim = p.add_argument_group("targets", "limits on the distances; given any, the command "
                               "exits 1 when the world misses one")
    lim.add_argument("--max-w1", type=float, metavar="D",
                     help="most 1-Wasserstein distance of the per-background IoU and of the "
                     "precision, each, in [0, 1]")
    lim.add_argument("--max-p10-gap", type=float, metavar="D",
                     help="most |world - real| of the per-background IoU's 10th percentile")
    lim.add_argument("--max-map-mae", type=float, metavar="D",
                     help="most mean absolute difference of the two x × y IoU maps")
    lim.add_argument("--max-place-mae", type=float, metavar="D",
                     help="most mean |street - place| of the placed car's IoU over the real "
                     "places both runs hold (missed when they hold none)")
    p.add_argument("--allow-incomplete", action="store_true",
                   help=ALLOW_INCOMPLETE_HELP)
    p.add_argument("--json", action="store_true")


def run(args) -> int:
    from falsify.jobs.agreement import Limits, format_text, run_agreement

    limits = Limits(args.max_w1, args.max_p10_gap, args.max_map_mae, args.max_place_mae)
    result = run_agreement(args.world_run, args.real_run, threshold=args.threshold,
                           fp_samples=args.fp_samples, limits=limits,
                           allow_incomplete=args.allow_incomplete)
    emit(args, result.to_json(), format_text(result))
    return 0 if result.passed else 1
