"""`falsify predict`: run the network on scans; IoU, precision and recall where labelled."""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
from pathlib import Path

from falsify.checks import check_out_dir
from falsify.cli.common import (
    BACKEND_HELP,
    DEVICE_HELP,
    MODEL_HELP,
    UsageError,
    check_backend,
    emit,
    predict_sequences,
)
from falsify.cli.progress import ScanCounter

DEFAULT_SENSOR = "kitti-hdl64e-front"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("scans", nargs="+",
                   help=".npy range images, KITTI .bin scans (labels: x.label beside or "
                   "../labels/x.label), folders of .npy / .bin, a SemanticKITTI root, its "
                   "sequences/ folder or one sequence folder (one set per sequence), or a KITTI "
                   "object directory (velodyne/, label_2/, calib/, image_2/: labelled from its "
                   "3D boxes, points outside the camera's image ignored); scores are pooled per "
                   "folder or sequence, and over all; each scan once")
    p.add_argument("--sequences", default=None, metavar="SS,SS",
                   help="only these SemanticKITTI sequences of a root or sequences/ folder, "
                   "e.g. 00,03,06,08")
    p.add_argument("--model", default=None, help=MODEL_HELP)
    p.add_argument("--backend", choices=["onnx", "torch", "python"], default=None,
                   help=BACKEND_HELP + " (default: onnx)")
    p.add_argument("--device", choices=["cpu", "cuda"], default="cpu", help=DEVICE_HELP)
    p.add_argument("--sensor", default=None,
                   help=f"preset used to project .bin scans and KITTI object frames (default: "
                   f"{DEFAULT_SENSOR}); refused when every scan is a .npy range image")
    p.add_argument("--score", choices=["pixels", "points"], default="pixels",
                   help="what is scored: 'pixels' (default), the range image's pixels, each "
                   "holding its nearest point; 'points', every point of a .bin scan that has a "
                   "pixel, with that pixel's prediction, against its own label and at its own "
                   "range (SemanticKITTI's leaderboard protocol; .npy range images refused: "
                   "they hold no points)")
    p.add_argument("--out", required=True,
                   help="folder for each scan's prediction (X.pred.npy) and its picture (X.png), "
                   "named for the scan")
    p.add_argument("--json", action="store_true")


def run(args) -> int:
    from falsify.data.scansets import NPY_HAS_NO_POINTS, plan_name, plan_sets
    from falsify.fileio import write_bytes, write_npy
    from falsify.images.png import encode_png
    from falsify.images.scan_pictures import prediction_picture
    from falsify.jobs.predict import evaluate_plans
    from falsify.models.runners import backend_for, load_segmenter
    from falsify.sensor.lidar import load_sensor

    check_out_dir(args.out)
    backend = backend_for(args.model, check_backend(args.backend, args.model))
    sequences = predict_sequences(args.sequences, args.scans)
    plans = plan_sets(args.scans, sequences)
    projects = any(p.projects for p in plans)
    if args.sensor is not None and not projects:
        raise UsageError(f"--sensor {args.sensor}: projects .bin scans and KITTI object frames "
                         "only; every scan named is a .npy range image, already projected")
    if args.score == "points":
        npy = next((f for p in plans for f in p.files if f.suffix == ".npy"), None)
        if npy is not None:
            raise UsageError(f"--score points: {npy}: {NPY_HAS_NO_POINTS}")
    sensor = load_sensor(args.sensor or DEFAULT_SENSOR)
    # Open the model before any scan is read: one that does not fit the sensor fails at once.
    model = load_segmenter(args.model, backend=backend, device=args.device)
    if projects:
        model.spec.check_fits(sensor, args.model or "bundled")
    out = Path(args.out)
    targets = output_stems([(plan_name(p), tuple(map(str, p.files))) for p in plans], out)
    check_prediction_targets(out, targets)
    made = sorted({d for stems in targets for stem in stems
                   for d in (stem.parent, *stem.parent.parents) if not d.exists()},
                  key=lambda d: len(d.parts), reverse=True)   # the folders writing makes
    written = [0] * len(plans)
    counter = ScanCounter("predict", sum(len(p.files) for p in plans))

    def write(k: int, scans, r) -> None:
        """A part's predictions and pictures, as it is evaluated: the scans are not kept."""
        labelled = scans.labelled()
        stems = targets[k][written[k]:written[k] + len(scans)]
        for j, (stem, cls) in enumerate(zip(stems, r.predictions, strict=True)):
            write_npy(stem.with_name(f"{stem.name}{PRED_SUFFIX}"), cls)
            picture = prediction_picture(scans.images[j], cls, labelled=bool(labelled[j]))
            write_bytes(stem.with_name(f"{stem.name}.png"), encode_png(picture))
        written[k] += len(scans)
        counter(len(scans))

    remove_predictions(out, targets)   # a stop while writing leaves none of the last run's
    try:
        result = evaluate_plans(model, plans, sensor, score=args.score, on_part=write)
    except BaseException:   # a bad scan, a stop: none of this run's files stay half written
        remove_predictions(out, targets)
        for d in made:
            with contextlib.suppress(OSError):
                d.rmdir()
        raise
    finally:
        counter.close()
    for s in result.sets:   # once every scan is read: a bad one is the only line it prints
        for source in s.unlabelled:
            print(f"falsify: warning: no labels for {source} (looked for {Path(source).stem}"
                  ".label beside it and in ../labels/)", file=sys.stderr)
        for label in s.orphan_labels:
            print(f"falsify: warning: {label}: labels without a scan (no "
                  f"{Path(label).stem}.bin among the set's scans); not scored", file=sys.stderr)
    summary = {**result.to_json(), "backend": backend, "out": str(out)}
    labelled = result.labelled_sets > 0
    if not labelled:
        summary = {k: v for k, v in summary.items() if k not in ("pooled", "bands", "sets")}
    emit(args, summary, _predict_text(result, backend, out, labelled))
    return 0


PRED_SUFFIX = ".pred.npy"


def check_prediction_targets(out: Path, targets: list[list[Path]]) -> None:
    """Refuse, before the network runs, a picture this run would write over that no earlier
    prediction wrote (no X.pred.npy beside X.png): a user's image, or a KITTI object
    directory's own image_2/ given as --out."""
    for stem in (stem for stems in targets for stem in stems):
        picture = stem.with_name(f"{stem.name}.png")
        if (picture.exists() or picture.is_symlink()) and \
                not stem.with_name(f"{stem.name}{PRED_SUFFIX}").is_file():
            raise UsageError(f"--out {out}: {picture} is there and no prediction wrote it (no "
                             f"{stem.name}{PRED_SUFFIX} beside it); it would be overwritten: "
                             "move it or give another --out")


def remove_predictions(out: Path, targets: list[list[Path]]) -> None:
    """Remove an earlier run's outputs from `out`: every X.pred.npy under it with the X.png
    beside it (the picture first, so that no picture outlives the file that marks it ours), and
    the two files of each scan this run writes. Other files stay."""
    stems = [stem for stems in targets for stem in stems]
    for folder, _, names in os.walk(out):   # links to other folders are not followed
        stems += [Path(folder) / n[:-len(PRED_SUFFIX)] for n in names if n.endswith(PRED_SUFFIX)]
    for stem in stems:
        stem.with_name(f"{stem.name}.png").unlink(missing_ok=True)
        stem.with_name(f"{stem.name}{PRED_SUFFIX}").unlink(missing_ok=True)


def output_stems(sets: list[tuple[str, tuple[str, ...]]], out: Path) -> list[list[Path]]:
    """Per set (its name and its scans' sources), per scan: the path its .pred.npy and .png are
    named from (under --out, in a folder per set when there are several); FalsifyError naming
    both scans where two would write the same files (x.npy beside x.bin, or sets of the same
    name)."""
    taken: dict[Path, str] = {}
    stems = []
    for name, sources in sets:
        parts = [q for q in Path(name).parts if q not in (Path(name).anchor, ".", "..")]
        folder = out.joinpath(*parts) if len(sets) > 1 else out
        stems.append([folder / Path(src).stem for src in sources])
        for stem, src in zip(stems[-1], sources, strict=True):
            first = taken.setdefault(stem, src)
            if first != src:
                raise UsageError(f"{first} and {src}: both would be predicted into "
                                 f"{stem}.pred.npy / .png; rename one or predict them apart")
    return stems


def _predict_text(result, backend: str, out: Path, labelled: bool) -> str:
    """Per set: pooled scores per class, then car IoU, precision and recall per range band; the
    same pooled over every set when several are labelled."""
    def f(v):
        return "   -  " if v is None else f"{v:6.3f}"

    unit = result.score   # "pixels" or "points": what TP, FP and FN count

    def scores(pooled, bands) -> list[str]:
        lines = [f"class        IoU    precision  recall   (TP, FP, FN of {unit}, pooled over "
                 "scans)"]
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
             f"into {out} (.pred.npy classes and .png pictures per scan)",
             "scored per point (--score points): every point of a .bin that has a pixel, "
             "against its own label (a points network answers each point, a range-image "
             "network's pixel answers its points), SemanticKITTI's protocol"
             if result.score == "points" else
             "scored per pixel (--score pixels): each pixel holds its nearest point; "
             "--score points scores every point"]
    if result.unlabelled:
        lines.append(f"{len(result.unlabelled)} scans without labels (named above): predicted, "
                     "left out of every score")
    if result.orphan_labels:
        lines.append(f"{len(result.orphan_labels)} labels without a scan (named above): not "
                     "scored")
    if not labelled:
        return "\n".join(lines)
    for s in result.sets:
        lines.append(f"\n{s.name}: {len(s.sources)} scans"
                     + (f", {len(s.unlabelled)} without labels, not scored" if s.unlabelled
                        else "")
                     + (f", {len(s.orphan_labels)} labels without a scan" if s.orphan_labels
                        else "")
                     + (f", {s.ignored_pixels} pixels ignored" if s.ignored_pixels
                        and s.score == "pixels" else "")
                     + (f", {s.ignored_points} points ignored" if s.ignored_points else "")
                     + (f", {s.points_outside_image} points outside the sensor's image (not "
                        "scored)" if s.score == "points" else ""))
        if s.scored:
            lines += scores(s.pooled, s.bands)
    if result.labelled_sets > 1:
        scored = sum(s.scored for s in result.sets)
        lines.append(f"\nall {result.labelled_sets} labelled sets pooled: {scored} scans"
                     + (f", {result.points_outside_image} points outside the sensor's image "
                        "(not scored)" if result.score == "points" else ""))
        lines += scores(result.pooled, result.bands)
    return "\n".join(lines)
