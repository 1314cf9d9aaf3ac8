"""`falsify gate`: fail (exit 1) when a run has too many blind spots."""

from __future__ import annotations

import argparse
import json
import sys


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("run", help="run directory (holding results.sqlite)")
    lim = p.add_mutually_exclusive_group()
    lim.add_argument("--max-blind-spots", type=int, metavar="N",
                     help="allowed number of blind spots (default 0)")
    lim.add_argument("--baseline", metavar="RUN_OR_JSON",
                     help="fail only on blind spots not in this run or `gate --json` file")
    p.add_argument("--threshold", type=float, metavar="T",
                   help="mIoU threshold in (0, 1] (default: the run's, else 0.65)")
    p.add_argument("--junit", metavar="FILE",
                   help="also write JUnit XML, one testcase per cell, named for the run: those "
                   "that fail the gate fail, accepted blind spots and empty cells are skipped")
    p.add_argument("--allow-incomplete", action="store_true",
                   help="gate a run stopped before its end, or still being written, on the "
                   "samples it holds (default: refuse it, exit 2)")
    p.add_argument("--json", action="store_true", help="print the verdict as JSON")


def _streams() -> tuple[tuple[str, int], ...]:
    """This process's output descriptors, where they are files (not under a test's capture)."""
    out = []
    for name, stream in (("standard output", sys.stdout), ("standard error", sys.stderr)):
        try:
            out.append((name, stream.fileno()))
        except (AttributeError, OSError, ValueError):   # io.UnsupportedOperation is both
            pass
    return tuple(out)


def run(args) -> int:
    from falsify.jobs.gate import (
        check_outputs,
        completeness_note,
        format_text,
        judge,
        write_junit,
    )

    check_outputs(args.run, args.baseline, args.junit, _streams())
    result = judge(args.run, threshold=args.threshold, max_blind_spots=args.max_blind_spots,
                   baseline=args.baseline, allow_incomplete=args.allow_incomplete)
    if args.junit:
        write_junit(result, args.junit)
    if args.json:
        if note := completeness_note(result):   # the text says it; JSON readers' logs too
            print(f"falsify gate: {result.run}: {note}", file=sys.stderr)
        print(json.dumps(result.to_json(), indent=2))
    else:
        print(format_text(result))
    return result.exit_code
