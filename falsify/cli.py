"""The `falsify` command line: one subcommand per job; user errors exit 2 with one clear line."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from falsify.errors import FalsifyError


ROOT = Path(__file__).resolve().parent.parent
DEFAULT_CONFIG = ROOT / "configs" / "paper.toml"


class UsageError(FalsifyError):
    """A bad command-line argument."""


class Parser(argparse.ArgumentParser):
    """argparse that reports errors as one line and exit code 2 (its own convention too)."""

    def error(self, message: str):  # noqa: D401 - argparse API
        self.exit(2, f"falsify: error: {message}\n")


def _set_pairs(pairs: list[str]) -> dict[str, str]:
    out = {}
    for item in pairs:
        if "=" not in item:
            raise UsageError(f"--set {item!r}: expected KEY=VALUE, e.g. --set x=2.5")
        key, value = item.split("=", 1)
        out[key.strip()] = value.strip()
    return out


def emit(args, summary: dict, text: str) -> None:
    """Print the summary as JSON with --json, else as text."""
    if getattr(args, "json", False):
        print(json.dumps(summary, indent=2, sort_keys=True, default=str))
    else:
        print(text)


# -- scan -----------------------------------------------------------------------------------
def cmd_scan(args) -> int:
    from falsify.fileio import write_bytes, write_npy
    from falsify.preview import encode_png, scan_picture
    from falsify.scene import InvalidSample, Simulator
    from falsify.sensor import load_sensor
    from falsify.space import load_space

    space = load_space(args.config)
    sample = space.make(_set_pairs(args.set or []))
    sensor = load_sensor(space.sensor)
    sim = Simulator(sensor, space.user_cars)
    try:
        scan = sim.scan(sample)
    except InvalidSample as exc:
        raise FalsifyError(f"invalid sample: {exc}") from None
    out = Path(args.out)
    write_npy(out / "scan.npy", scan.image)
    write_bytes(out / "scan.png", encode_png(scan_picture(scan.image)))
    summary = {
        "sample": sample.as_dict(), "sensor": sensor.name, "shape": list(scan.image.shape),
        "points": int(scan.valid.sum()), "car_points": scan.count(1),
        "files": [str(out / "scan.npy"), str(out / "scan.png")],
    }
    emit(args, summary, f"wrote {out / 'scan.npy'} and {out / 'scan.png'}: "
         f"{summary['points']} points, {summary['car_points']} on cars")
    return 0


# -- dataset --------------------------------------------------------------------------------
def cmd_dataset(args) -> int:
    from falsify.dataset import TrafficOptions, write_dataset
    from falsify.sensor import load_sensor
    from falsify.space import load_space

    space = load_space(args.config)
    if args.scans <= 0:
        raise UsageError(f"--scans: {args.scans} must be > 0")
    if not 0 <= args.first_background <= 999_000:
        raise UsageError(f"--first-background: {args.first_background} must be in 0..999000")
    if not 0 <= args.ray_drop < 1 or not 0 <= args.range_noise <= 1:
        raise UsageError("--ray-drop must be in [0, 1) and --range-noise in [0, 1] m")
    used = {int(b) for b in space.dims["background"].grid()}
    span = set(range(args.first_background, args.first_background + args.backgrounds))
    if used & span:
        raise UsageError(f"--first-background {args.first_background}: training backgrounds "
                         f"overlap the config's test backgrounds {sorted(used & span)[:5]}; "
                         "choose ids disjoint from the falsification space")
    sensor = load_sensor(space.sensor, ray_drop=args.ray_drop, range_noise=args.range_noise)
    opts = TrafficOptions(max_cars=args.max_cars, backgrounds=args.backgrounds,
                          first_background=args.first_background)
    summary = write_dataset(sensor, Path(args.out), args.scans, seed=args.seed, opts=opts,
                            progress=not args.json)
    emit(args, summary, f"wrote {summary['written']} scans to {args.out} "
         f"({summary['scans']} in the set); points per class {summary['points_per_class']}")
    return 0


# -- bench ----------------------------------------------------------------------------------
def cmd_bench(args) -> int:
    from falsify import bench

    if args.what == "scan":
        result = bench.bench_scan(args.config, samples=args.samples, workers=args.workers,
                                  naive_samples=args.naive_samples)
        w = args.workers
        text = (f"scan: {result[f'fast_scans_per_s_{w}_processes']} scans/s on {w} processes "
                f"({result['fast_scans_per_s_1_process']} on 1), naive "
                f"{result['naive_scans_per_s']} scans/s: {result[f'speedup_{w}_processes']}x")
    else:
        raise UsageError(f"bench {args.what}: not available")
    emit(args, result, text)
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = Parser(prog="falsify", description=__doc__)
    sub = p.add_subparsers(dest="command", required=True, parser_class=Parser)

    s = sub.add_parser("scan", help="ray-cast one sample of a space into a labelled scan")
    s.add_argument("config")
    s.add_argument("--out", required=True)
    s.add_argument("--set", action="append", metavar="KEY=VALUE",
                   help="fix a dimension (repeatable); other dims take their first value")
    s.add_argument("--json", action="store_true")
    s.set_defaults(func=cmd_scan)

    d = sub.add_parser("dataset", help="write training scans from random auto-driving scenes")
    d.add_argument("config", help="a space config: its sensor is used, not its dims")
    d.add_argument("--scans", type=int, required=True)
    d.add_argument("--out", required=True)
    d.add_argument("--seed", type=int, default=0)
    d.add_argument("--first-background", type=int, default=1000)
    d.add_argument("--backgrounds", type=int, default=1000)
    d.add_argument("--max-cars", type=int, default=12)
    d.add_argument("--ray-drop", type=float, default=0.05,
                   help="probability that a return is dropped (real sensors lose some)")
    d.add_argument("--range-noise", type=float, default=0.02, help="range noise sigma, m")
    d.add_argument("--json", action="store_true")
    d.set_defaults(func=cmd_dataset)

    b = sub.add_parser("bench", help="measure a fast path beside its naive path")
    b.add_argument("what", choices=["scan"])
    b.add_argument("--config", default=str(DEFAULT_CONFIG))
    b.add_argument("--samples", type=int, default=1000)
    b.add_argument("--naive-samples", type=int, default=5)
    b.add_argument("--workers", type=int, default=2)
    b.add_argument("--json", action="store_true")
    b.set_defaults(func=cmd_bench)

    from reports.cli import register
    register(sub)
    return p


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except FalsifyError as exc:
        print(f"falsify: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("falsify: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
