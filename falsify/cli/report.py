"""`falsify report`: a self-contained HTML report of a run."""

from __future__ import annotations

import argparse
from pathlib import Path

from falsify.checks import check_out_file
from falsify.cli.common import UsageError, emit


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("run", help="run directory (holding results.sqlite)")
    p.add_argument("--compare", metavar="RUN_BEFORE",
                   help="an earlier run (e.g. before retraining): adds the difference map")
    p.add_argument("--retrain", metavar="SUMMARY_JSON",
                   help="a `falsify retrain` summary.json: adds the experiment's section")
    p.add_argument("--out", metavar="FILE", help="output file (default RUN/report.html)")
    p.add_argument("--no-predict", action="store_true",
                   help="show label-only previews (do not load the model)")
    p.add_argument("--device", choices=["cpu", "cuda"], default="cpu",
                   help="where the run's model predicts the previews")
    p.add_argument("--json", action="store_true")


def run(args) -> int:
    from falsify.jobs.report import write_report_of

    retrain = None
    if args.retrain:
        from falsify.jobs.retrain import read_summary
        if not args.compare:
            raise UsageError("--retrain needs --compare RUN_BEFORE (the run before retraining)")
        retrain = read_summary(Path(args.retrain), "--retrain")
    if args.out:
        check_out_file(args.out, suffixes=(".html", ".htm"))
    written = write_report_of(Path(args.run), Path(args.out) if args.out else None,
                              Path(args.compare) if args.compare else None,
                              predict=not args.no_predict, retrain=retrain, device=args.device)
    out, differs, done = written.path, list(written.differences), written.completeness
    size = out.stat().st_size
    summary = {"run": args.run, "out": str(out), "bytes": size, "compare": args.compare,
               "compare_differs": differs, **done.to_json()}
    text = f"wrote {out} ({size / 1024:.0f} KiB)"
    if done.complete is False:
        text += f"\nwarning: incomplete run: {done.text()}; the report covers only those"
    if differs:
        text += ("\nwarning: the runs compared are of different spaces, so the difference "
                 "map mixes the network's change with the scenes':\n  " + "\n  ".join(differs))
    emit(args, summary, text)
    return 0
