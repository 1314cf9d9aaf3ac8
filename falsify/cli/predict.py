"""`falsify predict`: run the network on scans; IoU, precision and recall where labelled."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from falsify.checks import check_out_dir
from falsify.cli.common import BACKEND_HELP, DEVICE_HELP, MODEL_HELP, emit, predict_sequences


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("scans", nargs="+",
                   help=".npy range images, KITTI .bin scans (labels: x.label beside or "
                   "../labels/x.label), folders of .npy / .bin, a SemanticKITTI root, its "
                   "sequences/ folder or one sequence folder (one set per sequence), or a KITTI "
                   "object directory (velodyne/, label_2/, calib/: labelled from its 3D "
                   "boxes); scores are pooled per folder or sequence, and over all")
    p.add_argument("--sequences", default=None, metavar="SS,SS",
                   help="only these SemanticKITTI sequences of a root or sequences/ folder, "
                   "e.g. 00,03,06,08")
    p.add_argument("--model", default=None, help=MODEL_HELP)
    p.add_argument("--backend", choices=["onnx", "torch", "python"], default="onnx",
                   help=BACKEND_HELP)
    p.add_argument("--device", choices=["cpu", "cuda"], default="cpu", help=DEVICE_HELP)
    p.add_argument("--sensor", default="kitti-hdl64e-front",
                   help="preset used to project .bin scans")
    p.add_argument("--out", required=True)
    p.add_argument("--json", action="store_true")


def run(args) -> int:
    from falsify.data.scansets import load_sets
    from falsify.fileio import write_bytes, write_npy
    from falsify.images.png import encode_png
    from falsify.images.scan_pictures import prediction_picture
    from falsify.jobs.predict import evaluate
    from falsify.models.runners import backend_for, load_segmenter
    from falsify.sensor.lidar import load_sensor

    check_out_dir(args.out)
    sequences = predict_sequences(args.sequences, args.scans)
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
    summary = {**result.to_json(), "backend": args.backend, "out": str(out)}
    labelled = result.labelled_sets > 0
    if not labelled:
        summary = {k: v for k, v in summary.items() if k not in ("pooled", "bands", "sets")}
    emit(args, summary, _predict_text(result, args.backend, out, labelled))
    return 0


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
