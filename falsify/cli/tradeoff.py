"""`falsify tradeoff`: speed against mIoU-map error for each knob."""

from __future__ import annotations

import argparse
import math

from falsify.cli.common import emit, int_in


def add_arguments(p: argparse.ArgumentParser) -> None:
    from falsify.bench.knobs import KNOBS
    p.add_argument("config")
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--knobs", default=",".join(KNOBS),
                   help=f"comma-separated subset of {','.join(KNOBS)} (default: all)")
    p.add_argument("--model", default=None,
                   help="ONNX model with its .json spec (and .pt beside it for torch and CRF); "
                   "default: bundled")
    p.add_argument("--limit", type=int, default=None,
                   help="use only the first N samples of the grid (quick runs)")
    p.add_argument("--threads", type=int_in(1, 64), default=1, metavar="N",
                   help="inference threads while timing (default 1: what each --workers "
                   "process of a run uses)")
    p.add_argument("--json", action="store_true")


def run(args) -> int:
    from falsify.bench.tradeoff import parse_knobs, run_tradeoff

    summary = run_tradeoff(args.config, args.out, parse_knobs(args.knobs), model=args.model,
                           limit=args.limit, threads=args.threads)
    emit(args, summary, tradeoff_text(summary))
    return 0


def tradeoff_text(summary: dict) -> str:
    """The rows as a fixed-width text table."""
    def f(v, spec: str) -> str:
        return "-" if v is None or (isinstance(v, float) and math.isnan(v)) else format(v, spec)

    lines = [f"{'knob':10s} {'setting':16s} {'ms/sample':>9s} {'speedup':>7s} {'mean err':>8s} "
             f"{'max err':>7s} {'jaccard':>7s} {'blind':>5s} {'samples':>7s}  notes"]
    for r in summary["rows"]:
        mark = "*" if r["is_reference"] else " "
        lines.append(f"{r['knob']:10s} {r['setting'] + mark:16s} "
                     f"{f(r['time_per_sample_ms'], '9.1f')} {f(r['speedup'], '7.2f')} "
                     f"{f(r['map_mean_abs_error'], '8.4f')} {f(r['map_max_abs_error'], '7.4f')} "
                     f"{f(r['blind_spot_jaccard'], '7.3f')} {f(r['blind_spots'], '5d')} "
                     f"{r['samples']:7d}  {r['notes']}")
    lines.append(f"(* reference; {summary['samples']} samples; wrote {summary['files']['csv']}, "
                 f"{summary['files']['html']})")
    return "\n".join(lines)
