"""argparse wiring of `falsify report` and `falsify gate`; each command returns its exit code."""

from __future__ import annotations

import json
from pathlib import Path


def cmd_report(args) -> int:
    from falsify.cli import emit
    from reports.html import write_report

    retrain = None
    if args.retrain:
        from falsify.errors import FalsifyError
        if not args.compare:
            raise FalsifyError("--retrain needs --compare RUN_BEFORE (the run before retraining)")
        try:
            retrain = json.loads(Path(args.retrain).read_text(encoding="utf-8"))
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise FalsifyError(f"--retrain {args.retrain}: not a readable summary ({exc})") \
                from None
        if not isinstance(retrain, dict) or "blind_before" not in retrain:
            raise FalsifyError(f"--retrain {args.retrain}: not a `falsify retrain` summary.json")
    out = write_report(Path(args.run), Path(args.out) if args.out else None,
                       Path(args.compare) if args.compare else None,
                       predict=not args.no_predict, retrain=retrain)
    size = out.stat().st_size
    summary = {"run": args.run, "out": str(out), "bytes": size, "compare": args.compare}
    emit(args, summary, f"wrote {out} ({size / 1024:.0f} KiB)")
    return 0


def cmd_gate(args) -> int:
    from falsify.gate import evaluate, format_text, write_junit

    result = evaluate(args.run, threshold=args.threshold,
                      max_blind_spots=args.max_blind_spots, baseline=args.baseline)
    if args.junit:
        write_junit(result, args.junit)
    if args.json:
        print(json.dumps(result.to_json(), indent=2))
    else:
        print(format_text(result))
    return result.exit_code


def register(sub) -> None:
    """Add the `report` and `gate` subcommands to falsify's argparse subparsers."""
    r = sub.add_parser("report", help="write a self-contained HTML report of a run")
    r.add_argument("run", help="run directory (holding results.sqlite)")
    r.add_argument("--compare", metavar="RUN_BEFORE",
                   help="an earlier run (e.g. before retraining): adds the difference map")
    r.add_argument("--retrain", metavar="SUMMARY_JSON",
                   help="a `falsify retrain` summary.json: adds the experiment's section")
    r.add_argument("--out", metavar="FILE", help="output file (default RUN/report.html)")
    r.add_argument("--no-predict", action="store_true",
                   help="show label-only previews (do not load the model)")
    r.add_argument("--json", action="store_true")
    r.set_defaults(func=cmd_report)

    g = sub.add_parser("gate", help="fail (exit 1) when a run has too many blind spots",
                       description="Count blind spots: (x, y) cells whose mIoU is below the "
                       "threshold. Exit 0 within the limit, 1 over it, 2 on bad input.")
    g.add_argument("run", help="run directory (holding results.sqlite)")
    lim = g.add_mutually_exclusive_group()
    lim.add_argument("--max-blind-spots", type=int, metavar="N",
                     help="allowed number of blind spots (default 0)")
    lim.add_argument("--baseline", metavar="RUN_OR_JSON",
                     help="fail only on blind spots not in this run or `gate --json` file")
    g.add_argument("--threshold", type=float, metavar="T",
                   help="mIoU threshold in (0, 1] (default: the run's, else 0.65)")
    g.add_argument("--junit", metavar="FILE", help="also write JUnit XML, one testcase per cell")
    g.add_argument("--json", action="store_true", help="print the verdict as JSON")
    g.set_defaults(func=cmd_gate)
