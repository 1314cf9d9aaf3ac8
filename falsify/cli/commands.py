"""The `falsify` command line: one subcommand per job; user errors exit 2 with one clear line."""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import shlex
import signal
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

from falsify.checks import (
    MAX_SAMPLES,
    check_out_dir,
    check_out_file,
    check_range,
    check_seed,
)
from falsify.errors import FalsifyError
from falsify.paths import CONFIGS, config_path

DEFAULT_CONFIG = CONFIGS / "paper.toml"
# `dataset`'s drop for sensors without a fitted return model: real sensors lose some returns.
UNIFORM_RAY_DROP = 0.05
MODEL_HELP = ("an ONNX segmentation model with its .json spec, a bundled model's name, or a "
              "Python plug-in MODULE:FACTORY or FILE.py:FACTORY (see falsify.models.plugin) "
              "(default: bundled)")
BACKEND_HELP = "onnx or torch for a model file; python (set by itself) for a plug-in"
DEVICE_HELP = ("where the network runs: cpu, or cuda (torch and plug-ins: a CUDA build of "
               "torch; onnx: pip install onnxruntime-gpu)")


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
    from falsify.data.real_backgrounds import scanner_for
    from falsify.data.velodyne import kitti_arrays
    from falsify.fileio import write_bytes, write_npy
    from falsify.images.png import encode_png
    from falsify.images.scan_pictures import scan_picture
    from falsify.sensor.lidar import load_sensor
    from falsify.sensor.simulator import InvalidSample
    from falsify.world.space import load_space

    check_out_dir(args.out)
    space = load_space(args.config)
    sample = space.make(_set_pairs(args.set or []))
    sensor = load_sensor(space.sensor)
    sim = scanner_for(space, sensor)
    camera = None
    if args.camera is not None:
        space.require_streets("--camera")
        from falsify.sensor.camera import camera_preset
        from falsify.sensor.look import look_of
        camera = camera_preset(args.camera)
        look_of(sample)  # a value the camera cannot render fails before anything is written
    try:
        scan = sim.scan(sample)
    except InvalidSample as exc:
        raise FalsifyError(f"invalid sample: {exc}") from None
    out = Path(args.out)
    summary = {
        "sample": sample.as_dict(), "sensor": sensor.name, "shape": list(scan.image.shape),
        "points": int(scan.valid.sum()), "car_points": scan.count(1),
        "files": [str(out / f"scan.{e}") for e in ("npy", "png", "bin", "label")],
    }
    extra: dict[str, bytes] = {}
    if camera is not None:
        from falsify.cli.camera import scan_camera_files
        extra, summary["camera"] = scan_camera_files(sim, camera, sample, scan)
    write_npy(out / "scan.npy", scan.image)
    write_bytes(out / "scan.png", encode_png(scan_picture(scan.image)))
    points, labels = kitti_arrays(scan)   # SemanticKITTI's own files: x, y, z, remission; labels
    write_bytes(out / "scan.bin", points.tobytes())
    write_bytes(out / "scan.label", labels.tobytes())
    for name, data in extra.items():
        write_bytes(out / name, data)
        summary["files"].append(str(out / name))
    emit(args, summary, f"wrote {out / 'scan.npy'}, .png, .bin and .label: "
         f"{summary['points']} points, {summary['car_points']} on cars")
    return 0


# -- dataset --------------------------------------------------------------------------------
def cmd_dataset(args) -> int:
    from falsify.data.training import TrafficOptions, write_dataset, write_dataset_parallel
    from falsify.sensor.lidar import load_sensor
    from falsify.world.space import load_space

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
    if args.ray_drop is None:
        # A fitted return model already drops returns as the real sensor does.
        args.ray_drop = 0.0 if load_sensor(space.sensor).returns else UNIFORM_RAY_DROP
    if not 0 <= args.ray_drop < 1 or not 0 <= args.range_noise <= 1:
        raise UsageError("--ray-drop must be in [0, 1) and --range-noise in [0, 1] m")
    used = {int(b) for b in space.dims["background"].grid()}
    span = set(range(args.first_background, args.first_background + args.backgrounds))
    if used & span:
        raise UsageError(f"--first-background {args.first_background}: training backgrounds "
                         f"overlap the config's test backgrounds {sorted(used & span)[:5]}; "
                         "choose ids disjoint from the falsification space")
    sensor = load_sensor(space.sensor, ray_drop=args.ray_drop, range_noise=args.range_noise)
    world = None
    if args.world is not None:
        from falsify.world.profile import load_profile
        if args.traffic != "scattered":
            raise UsageError(f"--world with --traffic {args.traffic}: a profile draws scattered "
                             "scenes only (--traffic scattered)")
        world = load_profile(args.world)
    opts = TrafficOptions(max_cars=args.max_cars, backgrounds=args.backgrounds,
                          first_background=args.first_background, traffic=args.traffic,
                          world=world)
    if args.format == "kitti-object":
        from falsify.cli.camera import dataset_kitti_object
        summary, text = dataset_kitti_object(sensor, args.camera, Path(args.out), args.scans,
                                             args.seed, opts)
        emit(args, summary, text)
        return 0
    def progress(done: int, total: int) -> None:
        print(f"  {done}/{total} scans", flush=True)

    if args.workers < 1 or args.workers > 64:
        raise UsageError(f"--workers: {args.workers} must be in 1..64")
    if args.workers > 1 and args.format != "npy":
        raise UsageError(f"--workers {args.workers}: only --format npy writes in parallel")
    if args.labels != "kitti4" and args.format != "npy":
        raise UsageError(f"--labels {args.labels}: only --format npy holds labels in channel 5 "
                         "(semantickitti files carry SemanticKITTI's ids anyway)")
    kwargs = dict(seed=args.seed, opts=opts, weather=space, fmt=args.format, labels=args.labels)
    if args.workers > 1:
        summary = write_dataset_parallel(args.workers, sensor, Path(args.out), args.scans,
                                         **kwargs)
    else:
        summary = write_dataset(sensor, Path(args.out), args.scans,
                                on_progress=None if args.json else progress, **kwargs)
    emit(args, summary, f"wrote {summary['written']} scans to {args.out} "
         f"({summary['scans']} in the set); points per class {summary['points_per_class']}")
    return 0


# -- fit-world ------------------------------------------------------------------------------
def cmd_fit_world(args) -> int:
    from falsify.fileio import write_json
    from falsify.jobs.fit_world import describe, distances, fit_world, summarise
    from falsify.sensor.lidar import load_sensor
    from falsify.world.space import load_space

    out = check_out_file(args.out)
    sequences = _predict_sequences(args.sequences, args.scans)
    compare = {}
    for path in args.compare or []:
        if not Path(path).exists():
            raise UsageError(f"--compare {path}: no such file or folder")
    sensor = load_sensor(load_space(args.config).sensor)
    if not 1 <= args.base_scans <= 10_000:
        raise UsageError(f"--base-scans: {args.base_scans} must be in 1..10000")
    try:
        keeps = tuple(float(v) for v in args.parked_keep.split(","))
    except ValueError:
        keeps = ()
    if not keeps or not all(0.0 <= k <= 1.0 for k in keeps):
        raise UsageError(f"--parked-keep: {args.parked_keep!r} is not a comma list of shares "
                         "in 0..1")
    fit = fit_world(args.scans, sequences, sensor, name=args.name, base_scans=args.base_scans,
                    keep_grid=keeps, holdout=args.holdout or ())
    for path in args.compare or []:
        # A SemanticKITTI root is described per sequence, as predict reports it.
        from falsify.world.real_scans import available_sequences
        seqs = available_sequences([path]) or [None]
        for q in seqs:
            stats = describe([path], None if q is None else [q])
            key = path if q is None else f"{path}:{q}"
            compare[key] = {**summarise(stats), "distance_to_fit": distances(stats, fit.fit)}
    doc = {**fit.as_dict(), "compare": compare, "out": str(out)}
    write_json(out, fit.profile.to_json())
    emit(args, doc, _fit_world_text(doc))
    return 0


def _fit_world_text(doc: dict) -> str:
    """Median (5-95 %) per statistic for the fit scans, the world and each compared set."""
    from falsify.jobs.fit_world import STAT_KEYS

    cols = [("fit", doc["fit"], None), ("world", doc["world"], doc["distance_world_to_fit"]),
            ("profiled world", doc["profiled_world"], doc["distance_profiled_to_fit"])]
    cols += [(k, v, v["distance_to_fit"]) for k, v in doc["compare"].items()]
    lines = [f"wrote {doc['out']}: world profile {doc['profile']['name']!r} from "
             f"{doc['fit']['scans']} fit scans (world base: {doc['world']['scans']} of its "
             "training scenes); median [5-95 %], and W1 to the fit scans",
             "parked cars kept: " + ", ".join(
                 f"{t['keep']:g} ({t['score']:.3f})" for t in doc["parked_keep_tries"])
             + f" -> {doc['profile']['parked_keep']:g}"]
    for name, summ, dist in cols:
        lines.append(f"{name} ({summ['scans']} scans)")
        for k in STAT_KEYS:
            s = summ[k]
            d = "" if dist is None else f"   W1 {dist[k]:.4f}"
            lines.append(f"  {k:12s} {s['p50']:8.3f} [{s['p5']:7.3f} .. {s['p95']:7.3f}]{d}")
    return "\n".join(lines)


# -- predict and train ----------------------------------------------------------------------
def cmd_predict(args) -> int:
    from falsify.data.scansets import load_sets
    from falsify.fileio import write_bytes, write_npy
    from falsify.images.png import encode_png
    from falsify.images.scan_pictures import prediction_picture
    from falsify.jobs.predict import evaluate
    from falsify.models.runner import backend_for, load_segmenter
    from falsify.sensor.lidar import load_sensor

    check_out_dir(args.out)
    sequences = _predict_sequences(args.sequences, args.scans)
    sets = load_sets(args.scans, load_sensor(args.sensor), sequences=sequences)
    for s in sets:
        for source in s.unlabelled:
            print(f"falsify: warning: no labels for {source} (looked for {Path(source).stem}"
                  ".label beside it and in ../labels/)", file=sys.stderr)
    model = load_segmenter(args.model, backend=args.backend, device=args.device)
    args.backend = backend_for(args.model, args.backend)
    result = evaluate(model, sets)
    out = Path(args.out)
    for s, scans in zip(result.sets, sets, strict=True):
        folder = out / s.name if len(result.sets) > 1 else out
        labelled = scans.labelled()
        for k, (source, cls) in enumerate(zip(s.sources, s.predictions, strict=True)):
            write_npy(folder / f"{Path(source).stem}.pred.npy", cls)
            picture = prediction_picture(scans.images[k], cls, labelled=bool(labelled[k]))
            write_bytes(folder / f"{Path(source).stem}.png", encode_png(picture))
    summary = {**result.as_dict(), "backend": args.backend, "out": str(out)}
    labelled = result.labelled_sets > 0
    if not labelled:
        summary = {k: v for k, v in summary.items() if k not in ("pooled", "bands", "sets")}
    emit(args, summary, _predict_text(result, args.backend, out, labelled))
    return 0


def _predict_sequences(value: str | None, scans: list[str]) -> list[str] | None:
    """--sequences as a list of two-digit ids found under the SemanticKITTI roots named; a
    UsageError names the option and the allowed values."""
    if value is None:
        return None
    from falsify.world.real_scans import SEQUENCE_ID, available_sequences

    allowed = available_sequences(scans)
    hint = (f"allowed: {', '.join(allowed)}" if allowed else "no SemanticKITTI root or "
            "sequences/ folder (sequences/SS/velodyne/*.bin) among the scans")
    ids = [v.strip() for v in value.split(",")]
    for v in ids:
        if not SEQUENCE_ID.fullmatch(v):
            raise UsageError(f"--sequences {value}: {v!r} is not a two-digit sequence id; {hint}")
        if v not in allowed:
            raise UsageError(f"--sequences {value}: no sequence {v} in the scans named; {hint}")
    return sorted(set(ids))


def _predict_text(result, backend: str, out: Path, labelled: bool) -> str:
    """Per set: pooled scores per class, then car IoU, precision and recall per range band; the
    same pooled over every set when several are labelled."""
    def f(v):
        return "   -  " if v is None else f"{v:6.3f}"

    def scores(pooled, bands) -> list[str]:
        lines = ["class        IoU    precision  recall   (TP, FP, FN pooled over scans)"]
        for c in pooled.classes:
            lines.append(f"{c.name:11s} {f(c.iou)}  {f(c.precision)}    {f(c.recall)}"
                         + (f"   ({c.note})" if c.note else ""))
        if pooled.miou is not None:
            lines.append(f"mIoU over the classes in the labels: {pooled.miou:.3f}")
        lines.append("car by range  IoU    precision  recall   TP      FP      FN")
        for band, sc in bands:
            c = sc.car()
            lines.append(f"{band:11s} {f(c.iou)}  {f(c.precision)}    {f(c.recall)}  "
                         f"{c.tp:6d}  {c.fp:6d}  {c.fn:6d}")
        return lines

    n = sum(len(s.sources) for s in result.sets)
    lines = [f"predicted {n} scans with {result.model} ({result.model_hash[:12]}, {backend}) "
             f"into {out} (.pred.npy classes and .png pictures per scan)"]
    if result.unlabelled:
        lines.append(f"{len(result.unlabelled)} scans without labels (named above): predicted, "
                     "left out of every score")
    if not labelled:
        return "\n".join(lines)
    for s in result.sets:
        lines.append(f"\n{s.name}: {len(s.sources)} scans"
                     + (f", {len(s.unlabelled)} without labels, not scored" if s.unlabelled
                        else "")
                     + (f", {s.ignored_pixels} pixels ignored" if s.ignored_pixels else ""))
        if s.scored:
            lines += scores(s.pooled, s.bands)
    if result.labelled_sets > 1:
        scored = sum(s.scored for s in result.sets)
        lines.append(f"\nall {result.labelled_sets} labelled sets pooled: {scored} scans")
        lines += scores(result.pooled, result.bands)
    return "\n".join(lines)


def cmd_holdout(args) -> int:
    from falsify.data.holdout import load_manifest, manifest_text, scans_under
    from falsify.fileio import write_text

    out = check_out_file(args.out)
    sequences = _predict_sequences(args.sequences, args.scans)
    scans = scans_under(args.scans, sequences)
    write_text(out, manifest_text(scans, args.note or ""))
    held = load_manifest(out)
    summary = {"manifest": str(out), "scans": len(held.scans),
               "bytes": sum(s.size for s in held.scans)}
    emit(args, summary, f"{out}: {len(held.scans)} held-out scans, matched by content; pass it "
         "as --holdout to fit-world, train and retrain, or name it in $FALSIFY_HOLDOUT")
    return 0


def cmd_faithfulness(args) -> int:
    from falsify.fileio import write_json
    from falsify.jobs.faithfulness import run_faithfulness
    from falsify.models.runner import load_segmenter
    from falsify.paths import expand_data_path
    from falsify.sensor.lidar import load_sensor

    if args.out:
        check_out_file(args.out)
    if args.instances is not None:
        return _instance_faithfulness(args)
    if args.sequences or args.min_points is not None:
        raise FalsifyError("--sequences and --min-points go with --instances (SemanticKITTI's "
                           "labelled instances)")
    paths = [Path(p) for p in args.dirs] if args.dirs else [
        Path(expand_data_path("${KITTI_OBJECT}", "faithfulness (no DIR given)"))]
    sensor = load_sensor(args.sensor)
    result = run_faithfulness(paths, sensor, load_segmenter(args.model))
    summary = result.as_dict()
    if args.out:
        write_json(args.out, summary)
    emit(args, summary, _faithfulness_text(summary, args.out))
    return 0


def _instance_faithfulness(args) -> int:
    """`faithfulness --instances ROOT`: SemanticKITTI's cars and persons, each against a
    built-in actor of its class inserted in its place."""
    from falsify.fileio import write_json
    from falsify.jobs.instance_faithfulness import MIN_POINTS, run_instance_faithfulness
    from falsify.models.runner import load_segmenter
    from falsify.paths import expand_data_path
    from falsify.sensor.lidar import load_sensor

    if args.dirs:
        raise FalsifyError(f"faithfulness: {args.dirs[0]}: give KITTI object directories or "
                           "--instances, not both")
    min_points = MIN_POINTS if args.min_points is None else args.min_points
    check_range(min_points, "--min-points", 1)
    root = Path(expand_data_path(args.instances, "--instances"))
    result = run_instance_faithfulness([root], args.sequences, load_sensor(args.sensor),
                                       load_segmenter(args.model), min_points)
    summary = result.as_dict()
    if args.out:
        write_json(args.out, summary)
    emit(args, summary, _instance_text(summary, args.out))
    return 0


def _instance_text(s: dict, out: str | None) -> str:
    """Per class: how many instances, both arms' pooled IoU and the mean difference with its
    95 % interval; then what was skipped and why."""
    lines = [f"insertion faithfulness over labelled instances: {s['model']} "
             f"({s['model_hash'][:12]}), sensor {s['sensor']}, {len(s['scans'])} scans, "
             f"instances of at least {s['min_points']} points"]
    for cls, c in s["classes"].items():
        p, d = c["pooled"], c["pooled"]["iou_difference"]
        ci = c["ci95"]
        lines.append(f"{cls:7s} n={p['cars']:3d}  pooled IoU real {_num(p['real']['iou'])}, "
                     f"inserted {_num(p['inserted']['iou'])}; mean inserted - real "
                     f"{_num(d['mean'], '+.3f')}, 95 % interval "
                     + ("-" if ci is None else f"{ci[0]:+.3f} .. {ci[1]:+.3f}"))
    for scan, cls, inst, why in s["skipped"]:
        lines.append(f"skipped {scan} {cls} {inst}: {why}")
    if out:
        lines.append(f"wrote {out}")
    return "\n".join(lines)


def _num(v, spec: str = ".3f") -> str:
    return "-" if v is None else format(v, spec)


def _faithfulness_text(s: dict, out: str | None) -> str:
    """Per car: distance, pixels and car IoU / recall of both arms; then the pooled scores and
    the per-car IoU difference."""
    def f(v, spec: str = "6.3f") -> str:
        return "-".rjust(len(format(0.0, spec))) if v is None else format(v, spec)

    lines = [f"insertion faithfulness: {s['model']} ({s['model_hash'][:12]}), sensor "
             f"{s['sensor']}, {len(s['frames'])} frames, {s['pooled']['cars']} cars; box grown "
             f"{s['margin_m']} m; pose: {s['pose']}",
             f"{'frame':22s} {'box':>3s} {'dist m':>6s} {'model':10s} {'px real':>7s} "
             f"{'px ins':>6s} {'IoU real':>8s} {'IoU ins':>7s} {'rec real':>8s} "
             f"{'rec ins':>7s} {'ins-real':>8s}"]
    for r in s["rows"]:
        lines.append(f"{r['frame']:22s} {r['box']:3d} {r['distance_m']:6.1f} {r['model']:10s} "
                     f"{r['real_points']:7d} {r['inserted_points']:6d} "
                     f"{f(r['real']['iou'], '8.3f')} {f(r['inserted']['iou'], '7.3f')} "
                     f"{f(r['real']['recall'], '8.3f')} {f(r['inserted']['recall'], '7.3f')} "
                     f"{f(r['iou_difference'], '+8.3f')}")
    p = s["pooled"]
    for arm in ("real", "inserted"):
        a = p[arm]
        lines.append(f"pooled {arm:8s}: IoU {f(a['iou'])}  recall {f(a['recall'])}  precision "
                     f"{f(a['precision'])}  (TP {a['tp']}, FP {a['fp']}, FN {a['fn']})")
    d = p["iou_difference"]
    lines.append(f"IoU inserted - real over {d['n']} cars: mean {f(d['mean'], '+.3f')}, std "
                 f"{f(d['std'], '.3f')}, standard error {f(d['sem'], '.3f')}, range "
                 f"{f(d['min'], '+.3f')} .. {f(d['max'], '+.3f')}")
    d = p["recall_difference"]
    lines.append(f"recall inserted - real over {d['n']} cars: mean {f(d['mean'], '+.3f')}, std "
                 f"{f(d['std'], '.3f')}")
    if out:
        lines.append(f"wrote {out}")
    return "\n".join(lines)


def cmd_train(args) -> int:
    from falsify.models.train import main as train_main
    return int(train_main(args.train_args) or 0)


# -- realism --------------------------------------------------------------------------------
def cmd_realism(args) -> int:
    from falsify.data.scansets import load_sets, npy_files
    from falsify.fileio import write_json, write_text
    from falsify.jobs.realism import EncoderFeatures, compare
    from falsify.reports.realism_page import render_realism
    from falsify.sensor.lidar import load_sensor

    if args.scans is not None and args.scans < 1:
        raise UsageError(f"--scans: {args.scans} must be >= 1")
    if args.bootstrap < 0:
        raise UsageError(f"--bootstrap: {args.bootstrap} must be >= 0 (0: no resampling)")
    synthetic: dict[str, list[Path]] = {}
    labels: dict[str, str] = {}
    for d in map(Path, args.synthetic):
        if not d.is_dir():
            raise UsageError(f"{d}: not a folder (expected a `falsify dataset` folder of .npy)")
        files = npy_files(d)[: args.scans]
        if not files:
            raise UsageError(f"{d}: no .npy scans in this folder")
        name = d.name if d.name not in synthetic and d.name else str(d)
        synthetic[name] = files
        # what the label channel holds, as index.json records it; our four classes without one
        try:
            index = json.loads((d / "index.json").read_text(encoding="utf-8"))
        except (OSError, ValueError):
            index = None
        labels[name] = index.get("labels", "kitti4") if isinstance(index, dict) else "kitti4"
    sensor = load_sensor(args.sensor)
    real = load_sets(args.real, sensor, _predict_sequences(args.sequences, args.real))
    reported = (load_sets(args.evaluation, sensor,
                          _predict_sequences(args.evaluation_sequences, args.evaluation))
                if args.evaluation else [])
    result = compare(synthetic, real, EncoderFeatures(args.model),
                     bootstrap_draws=args.bootstrap, labels=labels, reported=reported)
    doc = result.as_dict()
    page = render_realism(doc)
    out = Path(args.out)
    write_json(out / "realism.json", doc)
    write_text(out / "realism.html", page)
    summary = {**doc, "files": [str(out / "realism.json"), str(out / "realism.html")]}
    emit(args, summary, _realism_text(doc, out))
    return 0


def _realism_text(doc: dict, out: Path) -> str:
    """Distances to the pooled real scans, one line per statistic."""
    ref = doc["real_pooled"]
    names = [s["name"] for s in doc["synthetic"]]
    parts = [r["name"] for r in doc["real"] if r["name"] != ref]
    lines = [f"realism against {ref} ({', '.join(parts) or ref}), lower is "
             f"closer; wrote {out / 'realism.json'} and {out / 'realism.html'}",
             f"{'statistic':12s}" + "".join(f"{n[-24:]:>26s}" for n in names)]
    for key in doc["statistics"]:
        lines.append(f"{key:12s}" + "".join(f"{doc['distances'][n][ref][key]:26.4f}"
                                            for n in names))
    floors = [s["frechet_floor"] for s in doc["synthetic"]]
    if all(floors):
        lines.append(f"{'(floor)':12s}" + "".join(f"{f['mean']:26.4f}" for f in floors)
                     + f"  frechet of {floors[0]['scans']} scans of the same set against the "
                     "rest (sampling alone)")
    for key in doc.get("reference_statistics", {}):
        lines.append(f"{key:12s}" + "".join(f"{doc['distances'][n][ref][key]:26.4f}"
                                            for n in names) + "  (reference, not compared)")
    for key in doc.get("diagnostic_statistics", {}):
        values = [doc["distances"][n][ref].get(key) for n in names]
        if any(v is not None for v in values):
            lines.append(f"{key:12s}" + "".join(
                f"{'—':>26s}" if v is None else f"{v:26.4f}" for v in values)
                + "  (SemanticKITTI's 19 classes: total variation; diagnostic, not compared)")
    for r in doc.get("reported", []):
        lines.append(f"{'reported':12s}" + "".join(
            f"{r['name'][-24:]:>26s}" for _ in names) + "  (evaluation data: never compared)")
        for key in doc["statistics"]:
            lines.append(f"{key:12s}" + "".join(f"{doc['distances'][n][r['name']][key]:26.4f}"
                                                for n in names))
    boot = doc.get("bootstrap")
    if boot:
        lo, hi = boot["levels"]
        lines.append(f"resampled {boot['draws']} times (seed {boot['seed']}): {lo:g}-{hi:g} % "
                     "of each distance")
        for key in doc["statistics"]:
            spans = (boot["intervals"][n][key] for n in names)
            lines.append(f"{key:12s}" + "".join(f"{f'{a:.4f}-{b:.4f}':>26s}" for a, b in spans))
    for name, cand in ((doc.get("comparison") or {}).get("candidates") or {}).items():
        k, n = sum(cand["closer"].values()), len(cand["closer"])
        lines.append(f"{name}: closer than {doc['comparison']['baseline']} on {k} of {n} "
                     f"statistics; on every one: {'yes' if k == n else 'no'}")
        if boot:
            share = boot["closer_share"][name]
            lines.append("  closer in this share of the resampled draws: " + ", ".join(
                f"{key} {share[key]:.2f}" for key in doc["statistics"]))
        on = cand["closer_on_real_scans"]
        lines.append(f"  closer against this many of the {cand['real_scans']} real scans, each "
                     "alone: " + ", ".join(f"{key} {v}" for key, v in on.items()))
    return "\n".join(lines)


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
    what = "car IoU" if s.objective is None else (
        "mIoU" if s.objective == "miou" else f"{s.objective} IoU")
    key = next((k for k in low if k != "sample"), "car_iou") if low else "car_iou"
    where = "" if low is None else ", ".join(f"{k}={v}" for k, v in low["sample"].items()
                                             if k in ("x", "y", "yaw", "background",
                                                      "car_model", "actor"))
    lines = [
        f"{s.samples} samples ({s.computed_this_time} computed now, {s.invalid} invalid, "
        f"{s.undefined} undefined) in {s.elapsed_s:.1f} s",
        f"blind spots: {s.blind_spots} of {s.cells} cells below mIoU {s.threshold}",
        f"lowest {what}: {'-' if low is None else low[key]} at {where}",
        f"mean {what}: {s.mean_car_iou if s.objective is None else s.mean_objective}",
        f"retraining set: {s.retraining_samples} scans in {Path(s.run) / 'retrain'}",
    ]
    if s.estimated:
        e = s.estimated
        lines.insert(2, f"estimated map (level-set): {e['scored']} of the grid's "
                     f"{e['grid_samples']} samples scored ({e['scored'] / e['grid_samples']:.0%});"
                     f" {e['undecided_cells']} cells undecided at {e['confidence']:.0%}")
    if s.executors:
        lines.append(f"computed on executors {', then '.join(s.executors)} (resumed on another; "
                     "the rows do not depend on the executor)")
    if s.report:
        lines.append(f"report: {s.report}")
    return "\n".join(lines)


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised like Ctrl-C's KeyboardInterrupt so that a run stops the same clean way."""


@contextlib.contextmanager
def _stop_signals() -> Iterator[None]:
    """For the block: SIGTERM raises Terminated and SIGINT KeyboardInterrupt (each where not
    ignored), once; a second signal during the clean-up that follows is ignored."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def stop(signum: int, frame) -> None:
        for sig in old:
            signal.signal(sig, signal.SIG_IGN)
        raise Terminated() if signum == signal.SIGTERM else KeyboardInterrupt()

    old = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    old = {sig: h for sig, h in old.items() if h in (signal.SIG_DFL, signal.default_int_handler)}
    for sig in old:
        signal.signal(sig, stop)
    try:
        yield
    finally:
        for sig, handler in old.items():
            signal.signal(sig, handler)


def _stop_name(exc: KeyboardInterrupt) -> tuple[str, int]:
    """What stopped the command, and its exit status (128 + the signal's number)."""
    return ("terminated", 143) if isinstance(exc, Terminated) else ("interrupted", 130)


def _stopped_text(argv: list[str], out: Path, stored: int | None, advice: str = "") -> str:
    """What a stopped run keeps (`stored` samples; None: not counted) and the command that goes
    on: the same with --resume where a store is left, else the same again (a fresh run that
    stored nothing is removed)."""
    from falsify.results.store import STORE_NAME
    then = f"{advice}, then " if advice else ""
    if not (out / STORE_NAME).exists():
        again = [a for a in argv if a != "--resume"]
        return (f"nothing was stored in {out}; {then}run it again with: "
                f"{shlex.join(['falsify', *again])}")
    kept = "the finished samples are" if stored is None else f"{stored} samples are"
    again = argv if "--resume" in argv else [*argv, "--resume"]
    return (f"{kept} stored safely in {out}; {then}continue with: "
            f"{shlex.join(['falsify', *again])}")


def _interrupted_text(argv: list[str], out: Path) -> str:
    """`_stopped_text` of a run stopped by a signal, its rows counted in its store."""
    from falsify.results.store import stored_samples
    try:
        stored: int | None = stored_samples(out)
    except FalsifyError:
        stored = None
    return _stopped_text(argv, out, stored)


def _run_folder(argv: list[str]) -> Path | None:
    """The run folder of a grid or search command line, read before the parser is built: its
    --out given as `--out DIR` or `--out=DIR` (None for any other spelling, or command)."""
    if argv[:1] not in (["grid"], ["search"]):
        return None
    out = next((a[len("--out="):] for a in argv if a.startswith("--out=")), None)
    if "--out" in argv[:-1]:
        out = argv[argv.index("--out") + 1]
    return Path(out) if out else None


def _lock_early(out: Path | None, argv: list[str]) -> contextlib.AbstractContextManager:
    """Lock a run folder before the parser is built (its choices import the samplers: seconds),
    so that a second run on a busy folder is refused at once; the run job holds it too."""
    if out is None:
        return contextlib.nullcontext()
    from falsify.results.runlock import RunLock
    return RunLock(out, command=shlex.join(["falsify", *argv]))


def _run(args, command: str, algorithm: str) -> int:
    from falsify.jobs.run import RunRequest, RunStopped, execute

    req = RunRequest(
        config=Path(args.config), out=Path(args.out), command=command, algorithm=algorithm,
        budget=getattr(args, "budget", None), seed=args.seed, model=args.model,
        backend=args.backend, device=args.device, objective=args.objective,
        workers=args.workers, resume=args.resume,
        threshold=args.threshold, fidelity=args.fidelity, report=not args.no_report,
        camera=args.camera, max_samples=args.max_samples, executor=args.executor,
        address=args.address, confidence=getattr(args, "confidence", None),
        inference=args.inference)
    try:
        summary = execute(req, on_progress=None if args.quiet else ProgressBar())
    except RunStopped as exc:
        argv = getattr(args, "argv", sys.argv[1:])
        raise FalsifyError(f"{exc.reason}: {_stopped_text(argv, req.out, exc.stored, exc.advice)}"
                           ) from None
    emit(args, summary.to_json(), summary_text(summary))
    return 0


def cmd_grid(args) -> int:
    return _run(args, "grid", "grid")


def cmd_search(args) -> int:
    if args.budget is not None and args.budget < 1:
        raise UsageError(f"--budget: {args.budget} must be a number of evaluations >= 1")
    if args.budget is None and args.algorithm != "level-set":
        raise UsageError("--budget: a number of evaluations >= 1 is required (only "
                         "--algorithm level-set may run without one: until every cell is "
                         "decided)")
    return _run(args, "search", args.algorithm)


def _run_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("config")
    p.add_argument("--out", required=True, help="run directory (results.sqlite, maps, report)")
    p.add_argument("--model", default=None, help=MODEL_HELP)
    p.add_argument("--backend", choices=["onnx", "torch", "python"], default="onnx",
                   help=BACKEND_HELP)
    p.add_argument("--device", choices=["cpu", "cuda"], default="cpu", help=DEVICE_HELP)
    p.add_argument("--inference", choices=["auto", "worker", "shared"], default="auto",
                   help="where the network runs with several --workers: in each worker, or "
                   "in one shared process that batches all workers' scans (auto: shared on "
                   "cuda, else in each worker)")
    p.add_argument("--objective", default=None, metavar="CLASS",
                   help="what the samplers minimise and the maps show: a class the model "
                        "predicts (car, person, ... SemanticKITTI's names) or miou (default: "
                        "the placed actors' class)")
    p.add_argument("--workers", type=int, default=1,
                   help="local worker processes, or Ray actors with --executor ray")
    p.add_argument("--executor", choices=["process", "ray"], default="process",
                   help="process: worker processes on this machine; ray: warm actors on a Ray "
                   'cluster (pip install "falsify[ray]")')
    p.add_argument("--address", default=None, metavar="HOST:PORT",
                   help="with --executor ray: the head of an existing Ray cluster (HOST:PORT, "
                   "ray://HOST:PORT or auto); default: start a local Ray instance")
    p.add_argument("--seed", type=int, default=None, help="default: the config's seed")
    p.add_argument("--resume", action="store_true", help="continue a killed run")
    p.add_argument("--threshold", type=float, default=None,
                   help="mIoU below which a cell is a blind spot (default: config, 0.65)")
    p.add_argument("--fidelity", default="exact",
                   choices=["fastest", "fast", "balanced", "exact"])
    p.add_argument("--no-report", action="store_true")
    p.add_argument("--max-samples", type=int, default=MAX_SAMPLES,
                   help=f"refuse a grid or budget larger than this (default {MAX_SAMPLES:,})")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    _camera_option(p, "also store the camera images of the retraining set beside its scans")
    p.add_argument("--json", action="store_true")


def _holdout_option(p: argparse.ArgumentParser) -> None:
    p.add_argument("--holdout", action="append", metavar="SPLITS_TOML",
                   help="a split manifest whose held-out scans this command refuses (matched by "
                   "content); also read: $FALSIFY_HOLDOUT, a splits.toml beside the data, and "
                   "a SemanticKITTI root's official split (08, 11-21)")


def _camera_option(p: argparse.ArgumentParser, help_text: str) -> None:
    from falsify.sensor.camera import CAMERA_PRESETS, DEFAULT_CAMERA
    p.add_argument("--camera", nargs="?", const=DEFAULT_CAMERA, default=None, metavar="PRESET",
                   help=f"{help_text} (presets: {', '.join(CAMERA_PRESETS)}; "
                   f"default {DEFAULT_CAMERA})")


# -- bench ----------------------------------------------------------------------------------
# Held-out frames `bench model` compares the variants on unless --samples says otherwise (each
# variant is timed on the first TIMED_FRAMES of them). Each is on a street of its own, built
# first (about 1 s a street): 1,000 frames spent some 12 minutes there alone. 8 frames are one
# batch of onnx-fp32-batch8. Every variant runs a warm-up frame, --repeats timed runs of them
# (default 1) and one for agreement: 17 frames, where torch-bf16 on a CPU without bf16 units is
# emulated at 1.5-3 s a frame on a 2-core EPYC.
MODEL_BENCH_FRAMES = 8
# Each benchmark's space without --config: default runs finish within 2 minutes on a 2-core
# machine (docs/benchmarks.md, "Default runs"); give --config configs/paper.toml for the
# paper's whole space. `bench model` measures held-out frames, not a space.
BENCH_CONFIGS = {"scan": "bench.toml", "pipeline": "bench.toml", "nodes": "bench.toml",
                 "memory": "ci.toml", "search": "yaw.toml", "camera": "paper.toml",
                 "map": "weather.toml"}


def given_options(args, *names: str) -> dict:
    """The named options the user gave (not None): each benchmark's own defaults stand for the
    rest, since one shared parser default cannot suit scans, pipelines and camera images."""
    return {n: getattr(args, n) for n in names if getattr(args, n) is not None}


def pipeline_figures_text(r: dict) -> str:
    """The machine-relative lines of `bench pipeline`: rates, MatMul, FLOPs, ratios, memory."""
    w, rates, mm, net, q = r["rates"]["workers"], r["rates"], r["matmul"], r["network"], r["ratios"]
    crf = "" if net["crf_share"] is None else f" (CRF {net['crf_share']:.1%})"
    mem = r["memory"]
    return "\n".join([
        f"1 thread a worker: inference alone {rates['inference_only_1_worker']} samples/s on 1 "
        f"worker, {rates['inference_only_n_workers']} on {w} at once; end to end "
        f"{rates['e2e_1_worker']} on 1, {rates['e2e_n_workers']} on {w}",
        f"machine: fp32 MatMul {mm['shape']} ({mm['library']}, 1 thread) "
        f"{mm['gflops_1_core']} GFLOP/s on 1 core, {mm['gflops_per_core_all_at_once']} per "
        f"core with {mm['processes']} at once",
        f"network: {net['gflop_per_frame']} GFLOP/frame{crf}, {net['achieved_gflops_1_thread']} "
        f"GFLOP/s on 1 thread",
        f"ratios: end to end {w}/1 workers {q['e2e_n_over_e2e_1']} (goal >= 1.8 for 2), end "
        f"to end / inference alone on {w} {q['e2e_n_over_inference_only_n']} (goal >= 0.9), "
        f"network / MatMul {q['achieved_over_matmul_1_core']} (goal >= 0.5)",
        f"memory of the {w}-worker run, all processes: {_memory_text(mem)}",
        f"streets: {r['streets']['count']}, built in every worker before the clock starts "
        f"(the steady state); each costs a worker {r['streets']['build_ms_each']} ms once",
    ])


def _memory_text(m: dict | None) -> str:
    """Peak RSS (and PSS) of a process tree, and its early and late means when measured."""
    if m is None:
        return "not measured (no /proc)"
    pss = "" if m["peak_pss_mb"] is None else f" ({m['peak_pss_mb']} MB PSS)"
    if m["early_rss_mb"] is None:
        return f"peak {m['peak_rss_mb']} MB RSS{pss}; too short for early and late means"
    return (f"peak {m['peak_rss_mb']} MB RSS{pss}; mean early {m['early_rss_mb']} MB, late "
            f"{m['late_rss_mb']} MB")


def _stderr(line: str) -> None:
    print(line, file=sys.stderr, flush=True)


def model_rates_text(rates: dict) -> str:
    bf16 = rates["bf16"]
    return (f"machine, 1 thread: fp32 {rates['fp32']['gflops_1_core']} GFLOP/s, int8 "
            f"{rates['int8']['gops_1_core']} GOP/s (units: "
            f"{', '.join(rates['cpu_units']['int8']) or 'none'}), bf16 "
            + (f"{bf16['gflops_1_core']} GFLOP/s" if bf16["gflops_1_core"] is not None
               else bf16["note"]))


def _search_timing(r: dict) -> str:
    """A `bench search` row's time: wall seconds, per evaluation, against random's."""
    if r["s_per_evaluation"] is None:
        return "not timed (resumed from an earlier invocation)"
    vs = r["s_per_evaluation_vs_random"]
    return (f"{r['wall_s']:.1f} s, {r['s_per_evaluation'] * 1e3:.1f} ms/evaluation"
            + ("" if vs is None else f" ({vs:.2f}x random)"))


def cmd_bench(args) -> int:
    from falsify.bench.machine import machine
    from falsify.bench.memory import bench_memory
    from falsify.bench.pipeline import bench_pipeline
    from falsify.bench.scan import bench_scan
    from falsify.bench.search import bench_search, over_seeds_text

    check_range(args.samples, "--samples", 1, MAX_SAMPLES)
    check_range(args.workers, "--workers", 1, 64)
    check_range(args.naive_samples, "--naive-samples", 1)
    check_range(args.repeats, "--repeats", 1)
    if not 0 < args.fraction <= 1:
        raise UsageError(f"--fraction: {args.fraction} must be in (0, 1]")
    if args.out:
        check_out_dir(args.out)
    if args.config is None:
        args.config = str(CONFIGS / BENCH_CONFIGS.get(args.what, DEFAULT_CONFIG.name))
    if args.what == "model":
        import numpy as np

        from falsify.bench.model import add_shares, model_bench_rates
        from falsify.data.scansets import npy_files, read_set
        from falsify.data.training import calibration_scans, held_out_scans
        from falsify.models.flops import count_flops
        from falsify.models.runner import BUNDLED_ONNX, WEIGHTS_DIR
        from falsify.models.variants import bench_models
        from falsify.sensor.lidar import load_sensor
        sensor = load_sensor("kitti-hdl64e-front")
        progress = (lambda line: None) if args.json else _stderr

        frames = MODEL_BENCH_FRAMES if args.samples is None else args.samples
        files = npy_files(Path(args.scans))[:frames] if args.scans else []
        if args.scans and not files:
            raise UsageError(f"--scans {args.scans}: no .npy scans there")
        scans = (read_set(args.scans, files, sensor).images if files
                 else held_out_scans(sensor, frames))
        onnx = Path(args.model) if args.model else BUNDLED_ONNX
        rates = model_bench_rates(progress)
        # the bundled network's int8 is its shipped copy (calibrating one anew takes minutes)
        shipped = (onnx.resolve() == BUNDLED_ONNX.resolve()
                   and args.calibration_scans is None)
        rows = bench_models(np.asarray(scans), onnx, repeats=args.repeats,
                            threads=args.threads, on_progress=progress,
                            calibration=None if shipped else calibration_scans(
                                sensor, args.calibration_scans),
                            int8_path=WEIGHTS_DIR / "squeezeseg-int8.onnx" if shipped else None)
        add_shares(rows, count_flops(onnx).total, rates)
        result = {"benchmark": "model", "model": str(onnx), "frames": len(scans),
                  "repeats": args.repeats, "machine": machine(), "matrix_rates": rates,
                  "variants": rows}
        text = "\n".join([model_rates_text(rates), *(
            f"{r['variant']:16s} {r['ms_per_frame']:8.1f} ms/frame {r['fps']:6.1f} fps  car "
            f"IoU diff {r['car_iou_diff']:+.4f}" + ("" if r.get("share_of_matrix_rate") is None
                                                   else f"  {r['share_of_matrix_rate']:.0%} of "
                                                   f"the {r['precision']} matrix rate")
            if "error" not in r else f"{r['variant']:16s} did not run: {r['error']}"
            for r in rows)])
    elif args.what == "pipeline" and (args.device == "cuda" or args.inference == "shared"):
        from falsify.bench.shared import bench_shared
        if args.executor == "ray":
            raise UsageError("--inference shared runs beside local workers, not on Ray")
        result = bench_shared(args.config, workers=args.workers, model=args.model,
                              device=args.device, **given_options(args, "samples"))
        text = (f"shared inference on {args.device}: {result['e2e_samples_per_s']} samples/s "
                f"end to end on {args.workers} workers; the network alone "
                f"{result['network_alone_frames_per_s']} frames/s, the workers' scans alone "
                f"{result['scan_only_samples_per_s']} samples/s: "
                f"{result['e2e_over_lower_ceiling']:.2f} of the lower (goal {result['goal']})")
    elif args.what == "pipeline":
        if args.executor == "ray":
            from falsify.executors.ray import import_ray
            import_ray()
        pipe = bench_pipeline(args.config, workers=args.workers, model=args.model,
                                    executor=args.executor, **given_options(args, "samples"))
        result = pipe.to_json()
        one = result["one_process"]
        text = (f"pipeline: {pipe.samples_per_s} samples/s on {pipe.workers} workers; one "
                f"process {one['samples_per_s']} samples/s against "
                f"{one['inference_only_samples_per_s']} for inference alone (overhead "
                f"{pipe.overhead:.1%}); store {result['driver_store_rows_per_s']} rows/s")
        if result["network"] is not None:   # a plug-in has no ONNX graph to rate
            text += "\n" + pipeline_figures_text(result)
        else:
            text += (f"\nend to end {result['rates']['e2e_1_worker']} samples/s on 1 worker, "
                     f"{result['rates']['e2e_n_workers']} on {pipe.workers}")
        if pipe.ray is not None:
            r = pipe.ray
            text += (f"\nray: {r['samples_per_s']} samples/s on {r['actors']} actors "
                     f"({r['against_processes']:.2f}x the processes); per task "
                     f"{r['task_round_trip_ms']} ms round trip, {r['driver_ms_per_task']} ms "
                     "pipelined")
    elif args.what == "memory":
        if args.samples is not None:
            raise UsageError("--samples: bench memory runs the config's whole grid, as "
                             "`falsify grid` does")
        result = bench_memory(args.config, workers=args.workers, model=args.model).to_json()
        m = result["memory"]
        text = (f"{result['command']}: {result['samples']} samples in {result['seconds']} s; "
                + f"all processes together: {_memory_text(m)}")
    elif args.what == "nodes":
        from falsify.bench.nodes import bench_nodes

        result = bench_nodes(args.config, nodes=args.nodes, model=args.model,
                             on_progress=None if args.json else _stderr,
                             **given_options(args, "samples")).to_json()
        text = "\n".join(f"{r['nodes']} node(s): {r['samples_per_s']} samples/s, "
                         f"{r['over_1_node']}x one node (ideal here {r['ideal_on_this_machine']})"
                         for r in result["nodes"]) + "\n" + result["note"]
    elif args.what == "search":
        if not args.out:
            raise UsageError("bench search needs --out DIR (its runs are resumable there)")
        result = bench_search(args.config, args.out, workers=args.workers,
                                    model=args.model, fraction=args.fraction, seeds=args.seeds)
        text = "\n".join(
            f"{r['algorithm']:12s} lowest {r['lowest']} after {r['evaluations']} evaluations; "
            f"within 0.02 of the grid's {result['grid_lowest']} after "
            f"{r['evaluations_to_target']}; {_search_timing(r)}" for r in result["algorithms"])
        text += f"\n{result['per_evaluation_goal']}; on {args.workers} workers"
        text += "\n" + over_seeds_text(result)
    elif args.what == "map":
        from falsify.bench.map import BUDGETS, bench_map, map_text
        if not args.out:
            raise UsageError("bench map needs --out DIR (its grid run is resumable there)")
        try:
            budgets = BUDGETS if args.budgets is None else tuple(
                float(b) for b in args.budgets.split(",") if b.strip())
        except ValueError:
            raise UsageError(f"--budgets {args.budgets!r}: shares of the grid such as "
                             "0.1,0.2,0.3") from None
        result = bench_map(args.config, args.out, budgets, seeds=args.seeds, model=args.model,
                           threshold=args.threshold, confidence=args.confidence,
                           workers=args.workers, timed=args.timed)
        text = map_text(result)
    elif args.what == "scan":
        sb = bench_scan(args.config, workers=args.workers,
                              **given_options(args, "samples", "naive_samples"))
        result = sb.to_json()
        text = (f"scan: {round(sb.fast_n, 1)} scans/s on {sb.workers} processes "
                f"({round(sb.fast_1, 1)} on 1), naive {round(sb.naive, 3)} scans/s: "
                f"{round(sb.fast_n / sb.naive, 1)}x")
    elif args.what == "camera":
        from falsify.cli.camera import bench_camera_text
        result, text = bench_camera_text(args.config, args.camera_preset,
                                         **given_options(args, "samples", "naive_samples"))
    else:
        raise UsageError(f"bench {args.what}: not available")
    emit(args, result, text)
    return 0


# -- retrain --------------------------------------------------------------------------------
def cmd_retrain(args) -> int:
    from falsify.jobs.retrain import RetrainJob, RetrainRequest, parse_ids, result_text
    from falsify.models.runner import resolve_model

    model = resolve_model(args.model)   # a path, or a bundled name such as squeezeseg-drive
    req = RetrainRequest(
        config=config_path(args.config), model=model, train_data=Path(args.train_data),
        out=Path(args.out), validation=parse_ids(args.validation_backgrounds,
                                                 "--validation-backgrounds"),
        retraining=parse_ids(args.retraining_backgrounds, "--retraining-backgrounds"),
        threshold=args.threshold, epochs=args.epochs, time_limit_min=args.time_limit_min,
        precision=args.precision, batch=args.batch, lr=args.lr, seed=args.seed,
        oversample=args.oversample, train_scans=args.train_scans,
        held_out_scans=args.held_out_scans,
        kitti=Path(args.kitti) if args.kitti else None,
        holdout=tuple(Path(h) for h in args.holdout or ()),
        workers=args.workers, resume=args.resume, selection=args.selection)
    result = RetrainJob(req, on_progress=None if args.json else ProgressBar()).run()
    emit(args, result.to_json(), result_text(result))
    return 0


# -- report, gate and tradeoff ----------------------------------------------------------------
def cmd_report(args) -> int:
    from falsify.jobs.report import write_report

    retrain = None
    if args.retrain:
        from falsify.jobs.retrain import read_summary
        if not args.compare:
            raise UsageError("--retrain needs --compare RUN_BEFORE (the run before retraining)")
        retrain = read_summary(Path(args.retrain), "--retrain")
    if args.out:
        check_out_file(args.out)
    out = write_report(Path(args.run), Path(args.out) if args.out else None,
                       Path(args.compare) if args.compare else None,
                       predict=not args.no_predict, retrain=retrain, device=args.device)
    size = out.stat().st_size
    summary = {"run": args.run, "out": str(out), "bytes": size, "compare": args.compare}
    emit(args, summary, f"wrote {out} ({size / 1024:.0f} KiB)")
    return 0


def cmd_gate(args) -> int:
    from falsify.jobs.gate import format_text, judge, write_junit

    result = judge(args.run, threshold=args.threshold,
                      max_blind_spots=args.max_blind_spots, baseline=args.baseline)
    if args.junit:
        write_junit(result, args.junit)
    if args.json:
        print(json.dumps(result.to_json(), indent=2))
    else:
        print(format_text(result))
    return result.exit_code


def cmd_explain(args) -> int:
    from falsify.jobs.explain import explain_run, format_text

    result = explain_run(args.run, threshold=args.threshold, depth=args.depth,
                         rules=args.rules, clusters=args.clusters, seed=args.seed)
    emit(args, result.as_dict(), format_text(result))
    return 0


def cmd_tradeoff(args) -> int:
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


def cmd_agreement(args) -> int:
    from falsify.jobs.agreement import format_text, run_agreement

    result = run_agreement(args.world_run, args.real_run, threshold=args.threshold,
                           fp_samples=args.fp_samples)
    emit(args, result.to_json(), format_text(result))
    return 0


def cmd_robustness(args) -> int:
    from falsify.jobs.robustness import robustness, robustness_text

    result = robustness(args.run, args.reference, args.column)
    emit(args, result.to_json(), robustness_text(result))
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = Parser(prog="falsify", description=__doc__)
    sub = p.add_subparsers(dest="command", required=True, parser_class=Parser)

    s = sub.add_parser("scan", help="ray-cast one sample of a space into a labelled scan")
    s.add_argument("config")
    s.add_argument("--out", required=True)
    s.add_argument("--set", action="append", metavar="KEY=VALUE",
                   help="fix a dimension (repeatable); other dims take their first value")
    _camera_option(s, "also render the camera: image.png, class.png/.npy, instance.npy, "
                   "depth.npy and overlay.png")
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
    d.add_argument("--ray-drop", type=float, default=None,
                   help="extra probability that a return is dropped, on top of the sensor's "
                   f"return model (default: 0 with a fitted return model, else {UNIFORM_RAY_DROP})")
    d.add_argument("--range-noise", type=float, default=0.02, help="range noise sigma, m")
    from falsify.data.training import TRAFFIC_KINDS
    d.add_argument("--traffic", choices=TRAFFIC_KINDS, default="scattered",
                   help="scattered: cars anywhere on the road; drive: lane-following traffic "
                   "like a driving log")
    d.add_argument("--world", default=None, metavar="PROFILE",
                   help="draw each scene's sensor pitch, height and car count from a world "
                   "profile (`falsify fit-world`); scattered traffic only")
    d.add_argument("--labels", choices=["kitti4", "semantickitti"], default="kitti4",
                   help="npy label channel: our four classes or SemanticKITTI's train ids")
    d.add_argument("--workers", type=int, default=1, help="processes writing scans (npy)")
    d.add_argument("--format", choices=["npy", "kitti-object", "semantickitti"], default="npy",
                   help="npy: range images; kitti-object: velodyne, image_2, calib, label_2; "
                   "semantickitti: sequences/00/velodyne/*.bin, labels/*.label (raw ids)")
    d.add_argument("--camera", default="kitti-centre", metavar="PRESET",
                   help="kitti-object: the camera preset (kitti-centre or kitti-rig)")
    d.add_argument("--json", action="store_true")
    d.set_defaults(func=cmd_dataset)

    fw = sub.add_parser("fit-world", help="fit a world profile (the sensor's pitch and height "
                        "over the road, cars in view, parked cars kept) on labelled real fit "
                        "scans")
    fw.add_argument("scans", nargs="+", help="SemanticKITTI roots, sequence folders or .bin "
                    "scans with their .label (fit data only: held-out scans are refused)")
    _holdout_option(fw)
    fw.add_argument("--sequences", default=None, metavar="SS,SS",
                    help="only these sequences of a SemanticKITTI root")
    fw.add_argument("--out", required=True, help="the profile's JSON file")
    fw.add_argument("--name", default="semantickitti-fit", help="the profile's name")
    fw.add_argument("--config", default=str(DEFAULT_CONFIG),
                    help="a space config whose sensor renders the world's own scenes")
    from falsify.jobs.fit_world import BASE_SCANS
    fw.add_argument("--base-scans", type=int, default=BASE_SCANS,
                    help="training scenes of the world rendered to measure its own pose")
    from falsify.world.profile import PARKED_KEEP_GRID
    fw.add_argument("--parked-keep", default=",".join(f"{k:g}" for k in PARKED_KEEP_GRID),
                    metavar="K,K", help="shares of the streets' parked cars to try; the one "
                    "whose cars in view and car share come nearest the fit scans' is kept")
    fw.add_argument("--compare", action="append", metavar="PATH",
                    help="also describe this labelled set (a `dataset --format semantickitti` "
                    "folder, or real scans, per sequence) against the fit scans: reported only")
    fw.add_argument("--json", action="store_true")
    fw.set_defaults(func=cmd_fit_world)

    ho = sub.add_parser("holdout", help="write a split manifest: scans that fit-world, train "
                        "and retrain refuse (matched by content, wherever they are)")
    ho.add_argument("scans", nargs="+", help=".bin or .npy scans, folders of them, SemanticKITTI "
                    "roots or sequence folders")
    ho.add_argument("--sequences", default=None, metavar="SS,SS",
                    help="only these sequences of a SemanticKITTI root")
    ho.add_argument("--out", required=True, help="the manifest (TOML), e.g. DATA/splits.toml")
    ho.add_argument("--note", default=None, help="a comment line for the manifest's head")
    ho.add_argument("--json", action="store_true")
    ho.set_defaults(func=cmd_holdout)

    pr = sub.add_parser("predict", help="run the network on scans; IoU, precision, recall per set "
                        "and range band where labelled")
    pr.add_argument("scans", nargs="+",
                    help=".npy range images, KITTI .bin scans (labels: x.label beside or "
                    "../labels/x.label), folders of .npy / .bin, a SemanticKITTI root, its "
                    "sequences/ folder or one sequence folder (one set per sequence), or a KITTI "
                    "object directory (velodyne/, label_2/, calib/: labelled from its 3D "
                    "boxes); scores are pooled per folder or sequence, and over all")
    pr.add_argument("--sequences", default=None, metavar="SS,SS",
                    help="only these SemanticKITTI sequences of a root or sequences/ folder, "
                    "e.g. 00,03,06,08")
    pr.add_argument("--model", default=None, help=MODEL_HELP)
    pr.add_argument("--backend", choices=["onnx", "torch", "python"], default="onnx",
                    help=BACKEND_HELP)
    pr.add_argument("--device", choices=["cpu", "cuda"], default="cpu", help=DEVICE_HELP)
    pr.add_argument("--sensor", default="kitti-hdl64e-front",
                    help="preset used to project .bin scans")
    pr.add_argument("--out", required=True)
    pr.add_argument("--json", action="store_true")
    pr.set_defaults(func=cmd_predict)

    fa = sub.add_parser("faithfulness", help="car IoU on each real KITTI object car against a "
                        "synthetic car inserted in its place (the real car's points removed)")
    fa.add_argument("dirs", nargs="*", metavar="DIR",
                    help="KITTI object directories (velodyne/, label_2/, calib/); every Car box "
                    "with a 3D extent is scored (default: $KITTI_OBJECT)")
    fa.add_argument("--instances", default=None, metavar="ROOT",
                    help="instead: SemanticKITTI's labelled cars and persons under ROOT (a root "
                    "or sequence folder), each against a built-in actor of its class")
    fa.add_argument("--sequences", nargs="+", default=None, metavar="SS",
                    help="with --instances: only these sequences")
    fa.add_argument("--min-points", type=int, default=None, metavar="N",
                    help="with --instances: instances of at least N points (default 30)")
    fa.add_argument("--model", default=None, help=MODEL_HELP)
    fa.add_argument("--sensor", default="kitti-hdl64e-front",
                    help="preset the frames are projected and the cars cast with")
    fa.add_argument("--out", default=None, metavar="FILE", help="also write the JSON summary here")
    fa.add_argument("--json", action="store_true")
    fa.set_defaults(func=cmd_faithfulness)

    re_ = sub.add_parser("realism", help="compare synthetic scans with real KITTI scans: "
                         "statistics, distances, encoder-feature Frechet distance; JSON + HTML")
    re_.add_argument("synthetic", nargs="+",
                     help="`falsify dataset` folders of .npy scans (the first is the baseline "
                     "the others are compared with)")
    re_.add_argument("--out", required=True, help="folder for realism.json and realism.html")
    re_.add_argument("--real", nargs="+", required=True, metavar="PATH",
                     help="the real reference: scans as for predict (a SemanticKITTI root, "
                     "sequence folders, .bin or .npy scans), pooled")
    re_.add_argument("--sequences", default=None, metavar="SS,SS",
                     help="only these sequences of --real's SemanticKITTI roots")
    re_.add_argument("--evaluation", nargs="+", default=None, metavar="PATH",
                     help="held-out real scans: each synthetic set's distances to them, per "
                     "set, reported only, never pooled or compared")
    re_.add_argument("--evaluation-sequences", default=None, metavar="SS,SS",
                     help="only these sequences of --evaluation's SemanticKITTI roots")
    re_.add_argument("--scans", type=int, default=None,
                     help="use the first N scans of each synthetic folder")
    re_.add_argument("--model", default=None,
                     help="SqueezeSeg ONNX model whose fire9 features are compared "
                     "(default: bundled)")
    re_.add_argument("--sensor", default="kitti-hdl64e-front",
                     help="preset used to project real .bin scans")
    re_.add_argument("--bootstrap", type=int, default=0, metavar="DRAWS",
                     help="also resample the scans DRAWS times (seeded): a 5-95 %% interval per "
                     "distance and, per later set, the share of draws in which it is closer "
                     "than the first (200 draws of two 200-scan sets: about a minute)")
    re_.add_argument("--json", action="store_true")
    re_.set_defaults(func=cmd_realism)

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
                    metavar="NAME", help="random, sobol, cross-entropy, level-set (which cells "
                    "are blind, with few evaluations), bo (Bayesian "
                    "optimisation, Optuna's TPE: pip install \"falsify[bo]\"), or an NLopt "
                    "algorithm: " + ", ".join(a for a in ALGORITHMS if a not in (
                        "grid", "random", "sobol", "cross-entropy", "level-set", "bo")))
    se.add_argument("--budget", type=int, default=None,
                    help="number of evaluations (level-set: at most; without it, until every "
                    "cell is decided)")
    se.add_argument("--confidence", type=float, default=None, metavar="P",
                    help="level-set: a cell is decided once its P interval excludes the "
                    "threshold (default 0.95)")
    se.set_defaults(func=cmd_search)

    from falsify.bench.tradeoff import KNOBS
    b = sub.add_parser("bench", help="measure a fast path beside its naive path")
    b.add_argument("what", choices=["scan", "model", "pipeline", "search", "map", "camera",
                                     "memory", "nodes"],
                   help="memory: peak memory of a whole `falsify grid --config ... --workers N` "
                   "run, all processes together; nodes: Ray on local clusters of 1..--nodes "
                   "one-CPU nodes; map: the level-set sampler's map against the full grid's "
                   "at each --budgets")
    b.add_argument("--config", default=None,
                   help="the space (default: each benchmark's own: configs/bench.toml for scan, "
                   "pipeline and nodes, configs/ci.toml for memory, configs/yaw.toml for "
                   "search, configs/weather.toml for map, configs/paper.toml for camera)")
    b.add_argument("--samples", type=int, default=None,
                   help="how many samples (default: each benchmark's own)")
    b.add_argument("--naive-samples", type=int, default=None,
                   help="samples through the naive path (default: each benchmark's own)")
    b.add_argument("--workers", type=int, default=2)
    b.add_argument("--executor", choices=["process", "ray"], default="process",
                   help="bench pipeline: also measure Ray actors against the processes")
    b.add_argument("--device", choices=["cpu", "cuda"], default="cpu",
                   help="bench pipeline: where the network runs (cuda: one shared inference "
                   "process on the GPU, against the network alone there and the workers' "
                   "scan rate)")
    b.add_argument("--inference", choices=["auto", "shared"], default="auto",
                   help="bench pipeline: shared measures one inference process fed by the "
                   "workers (the default on cuda)")
    b.add_argument("--model", default=None,
                   help="bench model, pipeline, memory: an ONNX model (default bundled)")
    b.add_argument("--scans", default=None,
                   help="bench model: a folder of labelled .npy scans (default: generated)")
    b.add_argument("--repeats", type=int, default=1,
                   help="bench model: timed runs of each variant over its frames, the best kept "
                   "(default 1)")
    b.add_argument("--calibration-scans", type=int, default=None, choices=range(1, 1025),
                   metavar="N", help="bench model: synthetic scenes to calibrate int8 on "
                   "(default: the export's 64; the bundled network's shipped int8 copy is "
                   "measured unless this is given)")
    b.add_argument("--threads", type=int, default=2, choices=range(1, 65), metavar="N",
                   help="bench model: inference threads (a grid worker uses 1)")
    b.add_argument("--out", default=None, help="bench search, map: where their runs go")
    b.add_argument("--budgets", default=None, metavar="F,F,...",
                   help="bench map: budgets as shares of the grid's evaluations (default "
                   "0.1,0.2,0.3; a run without a budget is always added)")
    b.add_argument("--threshold", type=float, default=None, metavar="T",
                   help="bench map: the blind-cell threshold (default the config's)")
    b.add_argument("--confidence", type=float, default=None, metavar="P",
                   help="bench map: the level-set sampler's confidence (default 0.95)")
    b.add_argument("--timed", action="store_true",
                   help="bench map: also run the level-set search for real and time it "
                   "against the grid")
    b.add_argument("--fraction", type=float, default=0.2,
                   help="bench search: budget as a fraction of the dense grid")
    b.add_argument("--seeds", type=int, default=3,
                   help="bench search, map: runs of each algorithm, from the config's seed on")
    b.add_argument("--nodes", type=int, default=2, choices=range(1, 17), metavar="N",
                   help="bench nodes: the largest local cluster, in one-CPU worker nodes "
                   "(default 2)")
    b.add_argument("--camera-preset", default="kitti-centre",
                   help="bench camera: the camera preset")
    b.add_argument("--json", action="store_true")
    b.set_defaults(func=cmd_bench)

    r = sub.add_parser("report", help="write a self-contained HTML report of a run")
    r.add_argument("run", help="run directory (holding results.sqlite)")
    r.add_argument("--compare", metavar="RUN_BEFORE",
                   help="an earlier run (e.g. before retraining): adds the difference map")
    r.add_argument("--retrain", metavar="SUMMARY_JSON",
                   help="a `falsify retrain` summary.json: adds the experiment's section")
    r.add_argument("--out", metavar="FILE", help="output file (default RUN/report.html)")
    r.add_argument("--no-predict", action="store_true",
                   help="show label-only previews (do not load the model)")
    r.add_argument("--device", choices=["cpu", "cuda"], default="cpu",
                   help="where the run's model predicts the previews")
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

    x = sub.add_parser("explain", help="what a run's failing samples have in common: rules over "
                       "the dims, each dim's share of the IoU variance, clusters",
                       description="Read a run (read-only) and describe its samples below the "
                       "threshold as readable rules, e.g. 'y >= 16 and |x| >= 3: 33 of 33 "
                       "samples below 0.65'.")
    x.add_argument("run", help="run directory (holding results.sqlite)")
    x.add_argument("--threshold", type=float, metavar="T",
                   help="per-sample car IoU below which a sample fails (default: the run's)")
    x.add_argument("--depth", type=int, default=2, help="conditions per rule, at most (1-4)")
    x.add_argument("--rules", type=int, default=5, help="rules to find, at most")
    x.add_argument("--clusters", type=int, default=4, help="clusters of failing samples")
    x.add_argument("--seed", type=int, default=0, help="seed of the clustering")
    x.add_argument("--json", action="store_true")
    x.set_defaults(func=cmd_explain)

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
    t.add_argument("--threads", type=int, default=1, choices=range(1, 65), metavar="N",
                   help="inference threads while timing (default 1: what each --workers "
                   "process of a run uses)")
    t.add_argument("--json", action="store_true")
    t.set_defaults(func=cmd_tradeoff)

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
    rt.add_argument("--kitti", default=None, metavar="DIR",
                    help="a folder of real KITTI sets to check on before and after (squeezeseg/"
                    " .npy scans, semantickitti/ .bin scans, the held-out scans of "
                    "semantickitti-mini/); the checks are skipped without it")
    _holdout_option(rt)
    rt.add_argument("--workers", type=int, default=2)
    rt.add_argument("--selection", default="blind",
                    choices=["blind", "control", "rules", "random"],
                    help="blind: R's scans at V's blind cells (the paper); control: at as many "
                    "random cells that are not blind, to tell the blind scans' effect from "
                    "more training's; rules: R's samples under the rules explain finds on V; "
                    "random: as many of R's samples as rules takes, from anywhere (its control)")
    rt.add_argument("--json", action="store_true")
    rt.set_defaults(func=cmd_retrain)

    ag = sub.add_parser("agreement", help="compare a run on our streets with a run of the same "
                        "positions on real scans: how alike the network fails in both")
    ag.add_argument("world_run", help="run directory of the world (our streets)")
    ag.add_argument("real_run", help="run directory of the same positions on real scans")
    ag.add_argument("--threshold", type=float, metavar="T",
                    help="mIoU below which a cell is blind (default: the real run's)")
    ag.add_argument("--fp-samples", type=int, default=0, metavar="N",
                    help="replay N rows of each run to count false-positive car points by "
                    "the class they lie on (default 0: skip)")
    ag.add_argument("--json", action="store_true")
    ag.set_defaults(func=cmd_agreement)

    ro = sub.add_parser("robustness", help="per effect and severity the network's score, and "
                        "mCE / mRR against a reference network (Robo3D's terms)")
    ro.add_argument("run", nargs="+", help="run directories of spaces with effect dims (0 "
                    "among each's values: the clean rows); several runs, one effect each, pool "
                    "their clean rows")
    ro.add_argument("--reference", metavar="RUN", nargs="+",
                    help="runs of the same spaces, in the same order, with the reference "
                    "network (for CE, mCE)")
    ro.add_argument("--column", default=None,
                    help="the score (default: inserted_iou on real backgrounds, else the "
                    "run's objective)")
    ro.add_argument("--json", action="store_true")
    ro.set_defaults(func=cmd_robustness)

    from falsify.cli.camera import register as register_camera
    register_camera(sub)
    return p


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv[:1] == ["train"]:   # training parses its own options (and its --help)
        from falsify.models.train import main as train_main
        return int(train_main(argv[1:]) or 0)
    run = argv[:1] in (["grid"], ["search"])
    out = _run_folder(argv)
    try:
        with _stop_signals() if run else contextlib.nullcontext(), _lock_early(out, argv):
            parser = build_parser()
            args = parser.parse_args(argv)
            args.argv = argv   # as typed: a stopped run's message repeats it to continue
            return int(args.func(args) or 0)
    except FalsifyError as exc:
        print(f"falsify: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as exc:
        what, code = _stop_name(exc)
        bar = "\n" if run and sys.stderr.isatty() else ""   # end the progress bar's line
        print(f"{bar}falsify: {what}" + (f": {_interrupted_text(argv, out)}" if out else ""),
              file=sys.stderr)
        return code
