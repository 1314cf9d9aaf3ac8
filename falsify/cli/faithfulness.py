"""`falsify faithfulness`: real cars against synthetic cars inserted in their place."""

from __future__ import annotations

import argparse
from pathlib import Path

from falsify.checks import check_out_file, check_range
from falsify.cli.common import MODEL_HELP, emit, predict_sequences
from falsify.errors import FalsifyError


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("dirs", nargs="*", metavar="DIR",
                   help="KITTI object directories (velodyne/, label_2/, calib/); every Car box "
                   "with a 3D extent is scored (default: $KITTI_OBJECT)")
    p.add_argument("--instances", default=None, metavar="ROOT",
                   help="instead: SemanticKITTI's labelled cars and persons under ROOT (a root "
                   "or sequence folder), each against a built-in actor of its class")
    p.add_argument("--sequences", nargs="+", default=None, metavar="SS,SS",
                   help="with --instances: only these sequences, e.g. 04,05 (as elsewhere; "
                   "04 05 is read the same)")
    p.add_argument("--min-points", type=int, default=None, metavar="N",
                   help="with --instances: instances of at least N points (default 30)")
    p.add_argument("--model", default=None, help=MODEL_HELP)
    p.add_argument("--sensor", default="kitti-hdl64e-front",
                   help="preset the frames are projected and the cars cast with")
    p.add_argument("--out", default=None, metavar="FILE", help="also write the JSON summary here")
    p.add_argument("--json", action="store_true")


def run(args) -> int:
    from falsify.fileio import write_json
    from falsify.jobs.faithfulness import run_faithfulness
    from falsify.models.runners import load_segmenter
    from falsify.paths import expand_data_path
    from falsify.sensor.lidar import load_sensor

    if args.out:
        check_out_file(args.out, suffixes=(".json",))
    if args.instances is not None:
        return _instance_faithfulness(args)
    if args.sequences or args.min_points is not None:
        raise FalsifyError("--sequences and --min-points go with --instances (SemanticKITTI's "
                           "labelled instances)")
    paths = [Path(p) for p in args.dirs] if args.dirs else [
        Path(expand_data_path("${KITTI_OBJECT}", "faithfulness (no DIR given)"))]
    sensor = load_sensor(args.sensor)
    result = run_faithfulness(paths, sensor, load_segmenter(args.model))
    summary = result.to_json()
    if args.out:
        write_json(args.out, summary)
    emit(args, summary, _faithfulness_text(summary, args.out))
    return 0


def _instance_faithfulness(args) -> int:
    """`faithfulness --instances ROOT`: SemanticKITTI's cars and persons, each against a
    built-in actor of its class inserted in its place."""
    from falsify.fileio import write_json
    from falsify.jobs.instance_faithfulness import MIN_POINTS, run_instance_faithfulness
    from falsify.models.runners import load_segmenter
    from falsify.paths import expand_data_path
    from falsify.sensor.lidar import load_sensor

    if args.dirs:
        raise FalsifyError(f"faithfulness: {args.dirs[0]}: give KITTI object directories or "
                           "--instances, not both")
    min_points = MIN_POINTS if args.min_points is None else args.min_points
    check_range(min_points, "--min-points", 1)
    root = Path(expand_data_path(args.instances, "--instances"))
    sequences = (None if args.sequences is None
                 else predict_sequences(",".join(args.sequences), [str(root)]))
    result = run_instance_faithfulness([root], sequences, load_sensor(args.sensor),
                                       load_segmenter(args.model), min_points)
    summary = result.to_json()
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
