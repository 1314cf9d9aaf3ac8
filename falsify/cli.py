"""The `falsify` command line: one subcommand per job; user errors exit 2 with one clear line."""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

from falsify.checks import (
    MAX_SAMPLES,
    check_out_dir,
    check_out_file,
    check_range,
    check_seed,
)
from falsify.errors import FalsifyError
from falsify.paths import CONFIGS

DEFAULT_CONFIG = CONFIGS / "paper.toml"


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

    check_out_dir(args.out)
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

    check_out_dir(args.out)
    check_seed(args.seed)
    space = load_space(args.config)
    if args.scans <= 0:
        raise UsageError(f"--scans: {args.scans} must be > 0")
    if not 0 <= args.first_background <= 999_000:
        raise UsageError(f"--first-background: {args.first_background} must be in 0..999000")
    if not 0 <= args.max_cars <= 40:
        raise UsageError(f"--max-cars: {args.max_cars} must be in 0..40")
    if args.backgrounds < 1:
        raise UsageError(f"--backgrounds: {args.backgrounds} must be >= 1")
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
    def progress(done: int, total: int) -> None:
        print(f"  {done}/{total} scans", flush=True)

    summary = write_dataset(sensor, Path(args.out), args.scans, seed=args.seed, opts=opts,
                            on_progress=None if args.json else progress)
    emit(args, summary, f"wrote {summary['written']} scans to {args.out} "
         f"({summary['scans']} in the set); points per class {summary['points_per_class']}")
    return 0


# -- predict and train ----------------------------------------------------------------------
def _read_scans(paths: list[str], sensor_name: str):
    """Range images from .npy files (our layout) or KITTI .bin files (+ .label beside)."""
    import numpy as np

    from falsify.kitti import load_scan_npy, read_kitti
    from falsify.sensor import load_sensor

    images = []
    sensor = None
    for p in map(Path, paths):
        if p.suffix == ".bin":
            sensor = sensor or load_sensor(sensor_name)
            label = p.with_suffix(".label")
            images.append(read_kitti(p, label if label.exists() else None, sensor).image)
        elif p.suffix == ".npy":
            images.append(load_scan_npy(p))
        else:
            raise UsageError(f"{p}: expected a .npy range image or a KITTI .bin scan")
    shapes = {im.shape for im in images}
    if len(shapes) > 1:
        raise UsageError(f"scans have different shapes: {sorted(shapes)}")
    return np.stack(images)


def cmd_predict(args) -> int:
    import numpy as np

    from falsify.fileio import write_npy
    from falsify.metrics import CLASSES, class_scores, confusion, pooled
    from falsify.models.runner import load_segmenter

    check_out_dir(args.out)
    scans = _read_scans(args.scans, args.sensor)
    model = load_segmenter(args.model, backend=args.backend)
    out = Path(args.out)
    counts = []
    per_scan = []
    labelled = bool((scans[..., 5] > 0).any())
    for i in range(0, len(scans), 8):
        pred = model.predict(scans[i:i + 8])
        for k, cls in enumerate(pred.classes):
            name = Path(args.scans[i + k]).stem
            write_npy(out / f"{name}.pred.npy", cls.astype(np.uint8))
            label = np.where(scans[i + k][..., 4] > 0, scans[i + k][..., 5], 0).astype(np.uint8)
            c = confusion(cls, label, len(CLASSES))
            counts.append(c)
            per_scan.append({"scan": args.scans[i + k], "car_iou": class_scores(c)[1].iou})
    summary: dict = {"model": model.spec.name, "model_hash": model.model_hash,
                     "backend": args.backend, "scans": len(scans), "out": str(out)}
    lines = [f"predicted {len(scans)} scans with {model.spec.name} "
             f"({model.model_hash[:12]}, {args.backend}) into {out}"]
    if labelled:
        scores = class_scores(pooled(counts))
        summary["pooled"] = {s.name: {"iou": s.iou, "precision": s.precision,
                                      "recall": s.recall, "tp": s.tp, "fp": s.fp, "fn": s.fn,
                                      "note": s.note} for s in scores}
        summary["per_scan"] = per_scan
        lines.append("class        IoU    precision  recall   (TP, FP, FN pooled over scans)")
        for s in scores:
            def f(v):
                return "   -  " if v is None else f"{v:6.3f}"
            lines.append(f"{s.name:11s} {f(s.iou)}  {f(s.precision)}    {f(s.recall)}"
                         + (f"   ({s.note})" if s.note else ""))
    emit(args, summary, "\n".join(lines))
    return 0


def cmd_train(args) -> int:
    from falsify.models.train import main as train_main
    return int(train_main(args.train_args) or 0)


# -- grid and search ------------------------------------------------------------------------
class ProgressBar:
    """Draws a run's progress as one line on stderr: a bar, rate, ETA and the lowest IoU."""

    def __init__(self) -> None:
        self._last = 0.0

    def __call__(self, p, final: bool) -> None:
        now = time.perf_counter()
        if not final and now - self._last < 0.25:
            return
        self._last = now
        elapsed = now - p.started
        rate = p.computed / elapsed if elapsed > 0 else 0.0
        total = f"/{p.total}" if p.total else ""
        eta = ""
        if p.total and rate > 0:
            eta = f" ETA {max(0.0, (p.total - p.done) / rate):5.0f}s"
        low = "-" if p.lowest is None else f"{p.lowest:.3f}"
        bar = ""
        if p.total:
            filled = int(24 * min(1.0, p.done / p.total))
            bar = "[" + "#" * filled + "." * (24 - filled) + "] "
        tty = sys.stderr.isatty()
        end = "\n" if final or not tty else "\r"
        if not tty and not final and p.done % 200 and p.done != p.total:
            return
        sys.stderr.write(f"{bar}{p.done}{total} samples  {rate:6.1f}/s{eta}  "
                         f"lowest IoU {low}{end}")
        sys.stderr.flush()


def summary_text(s) -> str:
    """A run's summary (RunSummary) in a few lines."""
    low = s.lowest
    where = "" if low is None else ", ".join(f"{k}={v}" for k, v in low["sample"].items()
                                             if k in ("x", "y", "yaw", "background",
                                                      "car_model"))
    lines = [
        f"{s.samples} samples ({s.computed_this_time} computed now, {s.invalid} invalid, "
        f"{s.undefined} undefined) in {s.elapsed_s:.1f} s",
        f"blind spots: {s.blind_spots} of {s.cells} cells below mIoU {s.threshold}",
        f"lowest car IoU: {'-' if low is None else low['car_iou']} at {where}",
        f"mean car IoU: {s.mean_car_iou}",
        f"retraining set: {s.retraining_samples} scans in {Path(s.run) / 'retrain'}",
    ]
    if s.report:
        lines.append(f"report: {s.report}")
    return "\n".join(lines)


def _run(args, command: str, algorithm: str) -> int:
    from falsify.runs import RunRequest, execute

    req = RunRequest(
        config=Path(args.config), out=Path(args.out), command=command, algorithm=algorithm,
        budget=getattr(args, "budget", None), seed=args.seed, model=args.model,
        backend=args.backend, workers=args.workers, resume=args.resume,
        threshold=args.threshold, fidelity=args.fidelity, report=not args.no_report,
        max_samples=args.max_samples)
    summary = execute(req, on_progress=None if args.quiet else ProgressBar())
    emit(args, summary.to_json(), summary_text(summary))
    return 0


def cmd_grid(args) -> int:
    return _run(args, "grid", "grid")


def cmd_search(args) -> int:
    if args.budget is None or args.budget < 1:
        raise UsageError("--budget: a number of evaluations >= 1 is required")
    return _run(args, "search", args.algorithm)


def _run_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("config")
    p.add_argument("--out", required=True, help="run directory (results.sqlite, maps, report)")
    p.add_argument("--model", default=None,
                   help="an ONNX segmentation model with its .json spec (default: bundled)")
    p.add_argument("--backend", choices=["onnx", "torch"], default="onnx")
    p.add_argument("--workers", type=int, default=1, help="local worker processes")
    p.add_argument("--seed", type=int, default=None, help="default: the config's seed")
    p.add_argument("--resume", action="store_true", help="continue a killed run")
    p.add_argument("--threshold", type=float, default=None,
                   help="mIoU below which a cell is a blind spot (default: config, 0.65)")
    p.add_argument("--fidelity", default="exact", choices=["fast", "balanced", "exact"])
    p.add_argument("--no-report", action="store_true")
    p.add_argument("--max-samples", type=int, default=MAX_SAMPLES,
                   help=f"refuse a grid or budget larger than this (default {MAX_SAMPLES:,})")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--json", action="store_true")


# -- bench ----------------------------------------------------------------------------------
def cmd_bench(args) -> int:
    from falsify import bench

    check_range(args.samples, "--samples", 1, MAX_SAMPLES)
    check_range(args.workers, "--workers", 1, 64)
    check_range(args.naive_samples, "--naive-samples", 1)
    check_range(args.repeats, "--repeats", 1)
    if not 0 < args.fraction <= 1:
        raise UsageError(f"--fraction: {args.fraction} must be in (0, 1]")
    if args.out:
        check_out_dir(args.out)
    if args.what == "search" and Path(args.config) == DEFAULT_CONFIG:
        args.config = str(CONFIGS / "yaw.toml")
    if args.what == "model":
        import numpy as np

        from falsify.models.runner import BUNDLED_ONNX
        from falsify.models.variants import bench_models
        files = sorted(Path(args.scans).glob("*.npy"))[: args.samples] if args.scans else []
        if args.scans and not files:
            raise UsageError(f"--scans {args.scans}: no .npy scans there")
        if files:
            scans = _read_scans([str(f) for f in files], "kitti-hdl64e-front")
        else:
            from falsify.dataset import held_out_scans
            from falsify.sensor import load_sensor
            scans = held_out_scans(load_sensor("kitti-hdl64e-front"), args.samples)
        onnx = Path(args.model) if args.model else BUNDLED_ONNX
        from falsify.dataset import calibration_scans
        from falsify.sensor import load_sensor
        rows = bench_models(np.asarray(scans), onnx, repeats=args.repeats,
                            threads=args.threads,
                            calibration=calibration_scans(load_sensor("kitti-hdl64e-front")))
        result = {"benchmark": "model", "model": str(onnx), "frames": len(scans),
                  "machine": bench.machine(), "variants": rows}
        text = "\n".join(f"{r['variant']:16s} {r['ms_per_frame']:8.1f} ms/frame "
                         f"{r['fps']:6.1f} fps  car IoU diff {r['car_iou_diff']:+.4f}"
                         for r in rows)
    elif args.what == "pipeline":
        pipe = bench.bench_pipeline(args.config, samples=args.samples, workers=args.workers,
                                    model=args.model)
        result = pipe.to_json()
        one = result["one_process"]
        text = (f"pipeline: {pipe.samples_per_s} samples/s on {pipe.workers} workers; one "
                f"process {one['samples_per_s']} samples/s against "
                f"{one['inference_only_samples_per_s']} for inference alone (overhead "
                f"{pipe.overhead:.1%})")
    elif args.what == "search":
        if not args.out:
            raise UsageError("bench search needs --out DIR (its runs are resumable there)")
        result = bench.bench_search(args.config, args.out, workers=args.workers,
                                    model=args.model, fraction=args.fraction)
        text = "\n".join(
            f"{r['algorithm']:12s} lowest {r['lowest']} after {r['evaluations']} evaluations; "
            f"within 0.02 of the grid's {result['grid_lowest']} after "
            f"{r['evaluations_to_target']}" for r in result["algorithms"])
    elif args.what == "scan":
        sb = bench.bench_scan(args.config, samples=args.samples, workers=args.workers,
                              naive_samples=args.naive_samples)
        result = sb.to_json()
        text = (f"scan: {round(sb.fast_n, 1)} scans/s on {sb.workers} processes "
                f"({round(sb.fast_1, 1)} on 1), naive {round(sb.naive, 3)} scans/s: "
                f"{round(sb.fast_n / sb.naive, 1)}x")
    else:
        raise UsageError(f"bench {args.what}: not available")
    emit(args, result, text)
    return 0


# -- report, gate and tradeoff ----------------------------------------------------------------
def cmd_report(args) -> int:
    from falsify.reporting import write_report

    if args.out:
        check_out_file(args.out)
    out = write_report(Path(args.run), Path(args.out) if args.out else None,
                       Path(args.compare) if args.compare else None,
                       predict=not args.no_predict)
    size = out.stat().st_size
    summary = {"run": args.run, "out": str(out), "bytes": size, "compare": args.compare}
    emit(args, summary, f"wrote {out} ({size / 1024:.0f} KiB)")
    return 0


def cmd_gate(args) -> int:
    from falsify.gate import format_text, judge, write_junit

    result = judge(args.run, threshold=args.threshold,
                      max_blind_spots=args.max_blind_spots, baseline=args.baseline)
    if args.junit:
        write_junit(result, args.junit)
    if args.json:
        print(json.dumps(result.to_json(), indent=2))
    else:
        print(format_text(result))
    return result.exit_code


def cmd_tradeoff(args) -> int:
    from falsify.tradeoff import parse_knobs, run_tradeoff

    summary = run_tradeoff(args.config, args.out, parse_knobs(args.knobs), model=args.model,
                           limit=args.limit)
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

    pr = sub.add_parser("predict", help="run the network on scans; IoU where labelled")
    pr.add_argument("scans", nargs="+", help=".npy range images or KITTI .bin files")
    pr.add_argument("--model", default=None)
    pr.add_argument("--backend", choices=["onnx", "torch"], default="onnx")
    pr.add_argument("--sensor", default="kitti-hdl64e-front",
                    help="preset used to project .bin scans")
    pr.add_argument("--out", required=True)
    pr.add_argument("--json", action="store_true")
    pr.set_defaults(func=cmd_predict)

    tr = sub.add_parser("train", add_help=False,
                        help="train SqueezeSeg (same options as python -m falsify.models.train)")
    tr.add_argument("train_args", nargs=argparse.REMAINDER)
    tr.set_defaults(func=cmd_train)

    g = sub.add_parser("grid", help="evaluate the full factorial grid of a space")
    _run_options(g)
    g.set_defaults(func=cmd_grid)

    from falsify.sampler.base import ALGORITHMS
    se = sub.add_parser("search", help="search a space for low car IoU within a budget")
    _run_options(se)
    se.add_argument("--algorithm", required=True, choices=[a for a in ALGORITHMS if a != "grid"],
                    metavar="NAME", help="random, sobol, or an NLopt algorithm: "
                    + ", ".join(a for a in ALGORITHMS if a not in ("grid", "random", "sobol")))
    se.add_argument("--budget", type=int, default=None, help="number of evaluations")
    se.set_defaults(func=cmd_search)

    from falsify.tradeoff import KNOBS
    b = sub.add_parser("bench", help="measure a fast path beside its naive path")
    b.add_argument("what", choices=["scan", "model", "pipeline", "search"])
    b.add_argument("--config", default=str(DEFAULT_CONFIG))
    b.add_argument("--samples", type=int, default=1000)
    b.add_argument("--naive-samples", type=int, default=5)
    b.add_argument("--workers", type=int, default=2)
    b.add_argument("--model", default=None, help="bench model: an ONNX model (default bundled)")
    b.add_argument("--scans", default=None,
                   help="bench model: a folder of labelled .npy scans (default: generated)")
    b.add_argument("--repeats", type=int, default=3)
    b.add_argument("--threads", type=int, default=2, choices=range(1, 65), metavar="N",
                   help="bench model: inference threads (a grid worker uses 1)")
    b.add_argument("--out", default=None, help="bench search: where its runs go")
    b.add_argument("--fraction", type=float, default=0.2,
                   help="bench search: budget as a fraction of the dense grid")
    b.add_argument("--json", action="store_true")
    b.set_defaults(func=cmd_bench)

    r = sub.add_parser("report", help="write a self-contained HTML report of a run")
    r.add_argument("run", help="run directory (holding results.sqlite)")
    r.add_argument("--compare", metavar="RUN_BEFORE",
                   help="an earlier run (e.g. before retraining): adds the difference map")
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

    t = sub.add_parser("tradeoff", help="measure speed against mIoU-map error for each knob",
                       description="Evaluate one sample set under each setting of each knob "
                       "against a reference setting; write tradeoff.csv, .json and .html.")
    t.add_argument("config")
    t.add_argument("--out", required=True, help="output directory")
    t.add_argument("--knobs", default=",".join(KNOBS),
                   help=f"comma-separated subset of {','.join(KNOBS)} (default: all)")
    t.add_argument("--model", default=None,
                   help="ONNX model with its .json spec (and .pt beside it for torch and CRF); "
                   "default: bundled")
    t.add_argument("--limit", type=int, default=None,
                   help="use only the first N samples of the grid (quick runs)")
    t.add_argument("--json", action="store_true")
    t.set_defaults(func=cmd_tradeoff)
    return p


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv[:1] == ["train"]:   # training parses its own options (and its --help)
        from falsify.models.train import main as train_main
        return int(train_main(argv[1:]) or 0)
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
