"""`falsify explain`: what a run's failing samples have in common."""

from __future__ import annotations

import argparse

from falsify.cli.common import ALLOW_INCOMPLETE_HELP, emit


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("run", help="run directory (holding results.sqlite)")
    p.add_argument("--threshold", type=float, metavar="T",
                   help="per-sample car IoU below which a sample fails (default: the run's)")
    # the limits are falsify.jobs.explain's MAX_*, written out: importing it here would load
    # pandas for every command's parser
    p.add_argument("--depth", type=int, default=2,
                   help="conditions per rule, at most: 1 to 4 (default 2)")
    p.add_argument("--rules", type=int, default=5,
                   help="rules to find, at most: 1 to 20 (default 5)")
    p.add_argument("--clusters", type=int, default=4,
                   help="clusters of failing samples: 1 to 20 (default 4)")
    p.add_argument("--seed", type=int, default=0, help="seed of the clustering (default 0)")
    p.add_argument("--allow-incomplete", action="store_true",
                   help=ALLOW_INCOMPLETE_HELP)
    p.add_argument("--json", action="store_true")


def run(args) -> int:
    from falsify.jobs.explain import explain_run, format_text

    result = explain_run(args.run, threshold=args.threshold, depth=args.depth,
                         rules=args.rules, clusters=args.clusters, seed=args.seed,
                         allow_incomplete=args.allow_incomplete)
    emit(args, result.to_json(), format_text(result))
    return 0
