"""`falsify search`: search a space for low car IoU within a budget."""

from __future__ import annotations

import argparse

from falsify.cli.common import UsageError
from falsify.cli.run import run_job, run_options


def add_arguments(p: argparse.ArgumentParser) -> None:
    from falsify.sampler.base import ALGORITHMS
    run_options(p)
    p.add_argument("--algorithm", required=True, choices=[a for a in ALGORITHMS if a != "grid"],
                   metavar="NAME", help="random, sobol, cross-entropy, level-set (which cells "
                   "are blind, with few evaluations), bo (Bayesian "
                   "optimisation, Optuna's TPE: pip install \"falsify[bo]\"), or an NLopt "
                   "algorithm: " + ", ".join(a for a in ALGORITHMS if a not in (
                       "grid", "random", "sobol", "cross-entropy", "level-set", "bo")))
    p.add_argument("--budget", type=int, default=None,
                   help="number of evaluations (level-set: at most; without it, until every "
                   "cell is decided)")
    p.add_argument("--confidence", type=float, default=None, metavar="P",
                   help="level-set: a cell is decided once its P interval excludes the "
                   "threshold (default 0.95)")


def run(args) -> int:
    if args.budget is not None and args.budget < 1:
        raise UsageError(f"--budget: {args.budget} must be a number of evaluations >= 1")
    if args.budget is None and args.algorithm != "level-set":
        raise UsageError("--budget: a number of evaluations >= 1 is required (only "
                         "--algorithm level-set may run without one: until every cell is "
                         "decided)")
    return run_job(args, "search", args.algorithm)
