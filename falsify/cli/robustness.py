"""`falsify robustness`: per effect and severity the network's score, mCE and mRR."""

from __future__ import annotations

import argparse

from falsify.cli.common import ALLOW_INCOMPLETE_HELP, emit


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("run", nargs="+", help="run directories of spaces with effect dims (0 "
                   "among each's values: the clean rows); several runs, one effect each, pool "
                   "their clean rows")
    p.add_argument("--reference", metavar="RUN", nargs="+",
                   help="runs of the same spaces, in the same order, with the reference "
                   "network (for CE, mCE)")
    p.add_argument("--column", default=None,
                   help="the score (default: inserted_iou, the placed object's own; in runs "
                   "without it, the run's objective)")
    p.add_argument("--allow-incomplete", action="store_true",
                   help=ALLOW_INCOMPLETE_HELP)
    p.add_argument("--json", action="store_true")


def run(args) -> int:
    from falsify.jobs.robustness import robustness, robustness_text

    result = robustness(args.run, args.reference, args.column, args.allow_incomplete)
    emit(args, result.to_json(), robustness_text(result))
    return 0
