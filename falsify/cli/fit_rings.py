"""`falsify fit-rings`: fit the HDL-64E's ring geometry on KITTI's object frames
(falsify.jobs.fit_rings says how)."""

from __future__ import annotations

import argparse
import json
from dataclasses import asdict

from falsify.cli.common import holdout_option


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("bins", nargs="+", help="KITTI .bin frames in their ring order, or folders "
                   "of them (an object directory's velodyne/); held-out frames are refused")
    holdout_option(p)
    p.add_argument("--json", action="store_true", help="print the fit as JSON")


def run(args) -> int:
    """Fit; print each ring's elevation and origin height, and the preset's two lists."""
    from falsify.data.velodyne import fit_frames
    from falsify.jobs.fit_rings import fit

    paths = fit_frames(args.bins, args.holdout or (), "fit-rings' frames")
    rings = fit(paths)
    if args.json:
        print(json.dumps({"frames": [str(p) for p in paths],
                          "rings": [asdict(r) for r in rings]}, indent=1))
        return 0
    print(rings_text(rings))
    return 0


def rings_text(rings) -> str:
    """The fit as a table, then the sensor preset's elevations_deg and ring_offsets_m."""
    lines = ["ring  theta_deg   dz_m  residual_deg  points"]
    for r in rings:
        lines.append(f"{r.ring:4d} {r.theta_deg:10.4f} {r.dz_m:6.4f} {r.residual_deg:13.5f} "
                     f"{r.points:7d}")
    lines.append(f"elevations_deg = {[r.theta_deg for r in rings]}")
    lines.append(f"ring_offsets_m = {[r.dz_m for r in rings]}")
    return "\n".join(lines)
