"""`falsify adjust WEIGHTS.pt --val DIR --out ADJUSTED.pt`: choose alpha on synthetic validation
scans and write the adjusted weights (falsify.models.adjust says why)."""

from __future__ import annotations

import argparse
import json
from dataclasses import asdict
from pathlib import Path

from falsify.checks import require_torch
from falsify.errors import FalsifyError


def add_arguments(p: argparse.ArgumentParser) -> None:
    from falsify.models.adjust import DEFAULT_ALPHAS

    p.add_argument("weights", help="a state dict (.pt) or a training checkpoint.pt")
    p.add_argument("--val", required=True, help="folder of synthetic .npy validation scans")
    p.add_argument("--out", required=True, help="the adjusted state dict (.pt) to write")
    p.add_argument("--alphas", default=",".join(map(str, DEFAULT_ALPHAS)),
                   help="comma-separated alphas to try (default 0, 0.05, ..., 1)")
    p.add_argument("--json", action="store_true", help="print the result as JSON")


def run(args) -> int:
    require_torch("falsify adjust")
    from falsify.models.adjust import adjust_weights

    out = Path(args.out)
    result = adjust_weights(args.weights, args.val, out, _alphas(args.alphas))
    if args.json:
        print(json.dumps({**asdict(result), "out": str(out)}, indent=1))
    else:
        print(adjust_text(result, out))
    return 0


def _alphas(text: str) -> list[float]:
    try:
        values = [float(t) for t in text.split(",") if t.strip()]
    except ValueError:
        raise FalsifyError(f"--alphas {text!r}: write comma-separated numbers in [0, 2]") \
            from None
    if not values or any(not 0.0 <= v <= 2.0 for v in values):
        raise FalsifyError(f"--alphas {text!r}: write comma-separated numbers in [0, 2]")
    return values


def adjust_text(result, out: Path) -> str:
    """Car IoU, precision and recall per alpha, the chosen one marked."""
    lines = [f"{result.scans} scans of {result.val}; car IoU / precision / recall per alpha:"]
    for s in result.scores:
        mark = "  <- chosen" if s.alpha == result.chosen else ""
        prec = "-" if s.car_precision is None else f"{s.car_precision:.3f}"
        lines.append(f"  alpha {s.alpha:4.2f}  {s.car_iou:.4f} / {prec} / {s.car_recall:.3f}{mark}")
    lines.append(f"wrote {out} (alpha {result.chosen})")
    return "\n".join(lines)
