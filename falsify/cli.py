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
                          first_background=args.first_background, traffic=args.traffic)
    summary = write_dataset(sensor, Path(args.out), args.scans, seed=args.seed, opts=opts,
                            progress=not args.json)
    emit(args, summary, f"wrote {summary['written']} scans to {args.out} "
         f"({summary['scans']} in the set); points per class {summary['points_per_class']}")
    return 0


# -- predict and train ----------------------------------------------------------------------
def _read_scans(paths: list[str], sensor_name: str):
    """Range images from .npy files (our layout) or KITTI .bin files (+ .label beside)."""
    import numpy as np

    from falsify.scan import load_scan_npy, read_kitti
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
    from models.runner import load_segmenter

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
    from models.train import main as train_main
    return int(train_main(args.train_args) or 0)


# -- grid and search ------------------------------------------------------------------------
def _run(args, command: str, algorithm: str) -> int:
    from falsify.runs import RunRequest, execute, summary_text

    req = RunRequest(
        config=Path(args.config), out=Path(args.out), command=command, algorithm=algorithm,
        budget=getattr(args, "budget", None), seed=args.seed, model=args.model,
        backend=args.backend, workers=args.workers, resume=args.resume,
        threshold=args.threshold, fidelity=args.fidelity, report=not args.no_report,
        quiet=args.quiet)
    summary = execute(req)
    emit(args, summary, summary_text(summary))
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
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--json", action="store_true")


# -- bench ----------------------------------------------------------------------------------
def cmd_bench(args) -> int:
    from falsify import bench

    if args.what == "search" and Path(args.config) == DEFAULT_CONFIG:
        args.config = str(ROOT / "configs" / "yaw.toml")
    if args.what == "model":
        import numpy as np

        from models.bench import bench_models
        from models.runner import BUNDLED_ONNX
        files = sorted(Path(args.scans).glob("*.npy"))[: args.samples] if args.scans else []
        if args.scans and not files:
            raise UsageError(f"--scans {args.scans}: no .npy scans there")
        if files:
            scans = _read_scans([str(f) for f in files], "kitti-hdl64e-front")
        else:
            scans = _held_out_scans(args.samples)
        onnx = Path(args.model) if args.model else BUNDLED_ONNX
        from falsify.tradeoff import calibration_scans
        rows = bench_models(np.asarray(scans), onnx, repeats=args.repeats,
                            threads=args.threads,
                            calibration=calibration_scans("kitti-hdl64e-front"))
        result = {"benchmark": "model", "model": str(onnx), "frames": len(scans),
                  "machine": bench.machine(), "variants": rows}
        text = "\n".join(f"{r['variant']:16s} {r['ms_per_frame']:8.1f} ms/frame "
                         f"{r['fps']:6.1f} fps  car IoU diff {r['car_iou_diff']:+.4f}"
                         for r in rows)
    elif args.what == "pipeline":
        result = bench.bench_pipeline(args.config, samples=args.samples, workers=args.workers,
                                      model=args.model)
        one = result["one_process"]
        text = (f"pipeline: {result[f'{args.workers}_workers']['samples_per_s']} samples/s on "
                f"{args.workers} workers; one process {one['samples_per_s']} samples/s against "
                f"{one['inference_only_samples_per_s']} for inference alone (overhead "
                f"{one['overhead']:.1%})")
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


# -- retrain --------------------------------------------------------------------------------
def cmd_retrain(args) -> int:
    from falsify.retrain import RetrainJob, RetrainRequest, parse_ids, result_text

    model = Path(args.model)
    if not model.suffix and not model.exists():  # a bundled name, e.g. squeezeseg-drive
        model = ROOT / "models" / "weights" / f"{args.model}.onnx"
    req = RetrainRequest(
        config=Path(args.config), model=model, train_data=Path(args.train_data),
        out=Path(args.out), validation=parse_ids(args.validation_backgrounds,
                                                 "--validation-backgrounds"),
        retraining=parse_ids(args.retraining_backgrounds, "--retraining-backgrounds"),
        threshold=args.threshold, epochs=args.epochs, time_limit_min=args.time_limit_min,
        precision=args.precision, batch=args.batch, lr=args.lr, seed=args.seed,
        oversample=args.oversample, train_scans=args.train_scans,
        held_out_scans=args.held_out_scans, kitti=Path(args.kitti) if args.kitti else None,
        workers=args.workers, resume=args.resume)
    result = RetrainJob(req, progress=not args.json).run()
    emit(args, result.to_json(), result_text(result))
    return 0


def _held_out_scans(n: int):
    """Labelled synthetic scans on backgrounds no training or test config uses (ids 9000+)."""
    import numpy as np

    from falsify.dataset import TrafficOptions, scene_for
    from falsify.scene import Simulator
    from falsify.sensor import load_sensor

    sim = Simulator(load_sensor("kitti-hdl64e-front"), max_bvh=1)
    opts = TrafficOptions(backgrounds=max(1, n), first_background=9000)
    images = []
    for i in range(n):
        bg, pose, cars = scene_for(i * 8, 77, sim, opts)
        images.append(sim.render(bg, cars, pose).image)
    return np.stack(images)


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
    from falsify.dataset import TRAFFIC_KINDS
    d.add_argument("--traffic", choices=TRAFFIC_KINDS, default="scattered",
                   help="scattered: cars anywhere on the road; drive: lane-following traffic "
                   "like a driving log")
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

    tr = sub.add_parser("train", help="train SqueezeSeg (same options as python -m models.train)",
                        add_help=False)
    tr.add_argument("train_args", nargs=argparse.REMAINDER)
    tr.set_defaults(func=cmd_train)

    g = sub.add_parser("grid", help="evaluate the full factorial grid of a space")
    _run_options(g)
    g.set_defaults(func=cmd_grid)

    from sampler.base import ALGORITHMS
    se = sub.add_parser("search", help="search a space for low car IoU within a budget")
    _run_options(se)
    se.add_argument("--algorithm", required=True, choices=[a for a in ALGORITHMS if a != "grid"],
                    metavar="NAME", help="random, sobol, or an NLopt algorithm: "
                    + ", ".join(a for a in ALGORITHMS if a not in ("grid", "random", "sobol")))
    se.add_argument("--budget", type=int, default=None, help="number of evaluations")
    se.set_defaults(func=cmd_search)

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

    rt = sub.add_parser("retrain", help="the paper's experiment: blind spots on V, fine-tune on "
                        "R's scans there, re-test V and held-out sets (resumable)")
    rt.add_argument("config")
    rt.add_argument("--model", required=True, help="an .onnx with its .pt beside it, or a "
                    "bundled name such as squeezeseg-drive")
    rt.add_argument("--train-data", required=True, help="the model's training scans")
    rt.add_argument("--validation-backgrounds", required=True, metavar="IDS", help="V, e.g. 0-6")
    rt.add_argument("--retraining-backgrounds", required=True, metavar="IDS",
                    help="R, e.g. 7-14")
    rt.add_argument("--out", required=True)
    rt.add_argument("--resume", action="store_true", help="continue at the unfinished stage")
    rt.add_argument("--threshold", type=float, default=None)
    rt.add_argument("--epochs", type=int, default=1)
    rt.add_argument("--time-limit-min", type=float, default=None)
    rt.add_argument("--precision", default="auto", choices=["auto", "bf16", "fp32"])
    rt.add_argument("--batch", type=int, default=8)
    rt.add_argument("--lr", type=float, default=3e-4)
    rt.add_argument("--seed", type=int, default=0)
    rt.add_argument("--oversample", type=int, default=20,
                    help="times each selected scan appears in the fine-tuning set")
    rt.add_argument("--train-scans", type=int, default=None,
                    help="use only the first N training scans")
    rt.add_argument("--held-out-scans", type=int, default=200)
    rt.add_argument("--kitti", default=str(ROOT.parent / "shared" / "data" / "kitti"),
                    help="real KITTI sets for the checks (skipped where absent)")
    rt.add_argument("--workers", type=int, default=2)
    rt.add_argument("--json", action="store_true")
    rt.set_defaults(func=cmd_retrain)

    from reports.cli import register
    register(sub)
    from falsify.tradeoff import register as register_tradeoff
    register_tradeoff(sub)
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
