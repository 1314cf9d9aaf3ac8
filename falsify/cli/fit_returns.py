"""`falsify fit-returns`: fit the sensor's return model on KITTI's object frames
(falsify.jobs.fit_returns says what is fitted)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("bins", nargs="+", help="KITTI object frames (velodyne/*.bin)")
    p.add_argument("--out", required=True)


def run(args) -> int:
    """Fit, write the return model to --out and print its main parameters as JSON."""
    from falsify.data.velodyne import fit_frames
    from falsify.jobs.fit_returns import fit

    paths = fit_frames(args.bins)
    out = fit(paths)
    Path(args.out).write_text(json.dumps(out, indent=1) + "\n")
    p = out["params"]
    print(json.dumps({k: p[k] for k in ("reflectivity", "cos_exp", "atten_m", "p_min", "p_max",
                                        "i0", "k")}))
    return 0
