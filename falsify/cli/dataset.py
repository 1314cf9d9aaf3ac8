"""`falsify dataset`: write training scans from random auto-driving scenes."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from falsify.checks import check_out_dir, check_seed
from falsify.cli.common import UsageError, emit
from falsify.fileio import write_json

# `dataset`'s drop for sensors without a fitted return model: real sensors lose some returns.
UNIFORM_RAY_DROP = 0.05


# Scan and frame files are NNNNNN (KITTI's and SemanticKITTI's 6 digits): a 7th digit would sort
# 1000000 before 100001, out of index (and poses.txt) order.
MAX_SCANS = 1_000_000

# index.json's keys and the options (or config) that set them, for a resume that differs
INDEX_OPTIONS = {"seed": "--seed", "sensor": "the config's sensor",
                 "sensor_file": "the content of the config's sensor file", "camera": "--camera",
                 "first_background": "--first-background", "backgrounds": "--backgrounds",
                 "max_cars": "--max-cars", "ray_drop": "--ray-drop",
                 "range_noise": "--range-noise", "traffic": "--traffic", "world": "--world",
                 "effects": "the config's effect dims", "labels": "--labels",
                 "format": "--format", "sequence": "--format"}
# what a key missing from index.json means (the index leaves defaults out)
INDEX_DEFAULTS = {"format": "npy", "labels": "kitti4", "traffic": "scattered"}


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("config", help="a space config: its sensor is used, not its dims")
    p.add_argument("--scans", type=int, required=True, help="how many scans to write")
    p.add_argument("--out", required=True,
                   help="a new or empty folder; or one this command wrote, to resume or extend "
                   "it with the same options (--scans at least the set's)")
    p.add_argument("--seed", type=int, default=0, help="fixes every scene (default 0)")
    p.add_argument("--first-background", type=int, default=1000,
                   help="the first street id drawn from (default 1000: the configs' "
                   "spaces use lower ids, so training and test streets differ)")
    p.add_argument("--backgrounds", type=int, default=1000,
                   help="distinct streets to draw from (default 1000)")
    p.add_argument("--max-cars", type=int, default=12,
                   help="the most cars placed in a scene (default 12)")
    p.add_argument("--ray-drop", type=float, default=None,
                   help="extra probability that a return is dropped, on top of the sensor's "
                   f"return model (default: 0 with a fitted return model, else {UNIFORM_RAY_DROP})")
    p.add_argument("--range-noise", type=float, default=0.02, help="range noise sigma, m")
    from falsify.data.training import TRAFFIC_KINDS
    p.add_argument("--traffic", choices=TRAFFIC_KINDS, default="scattered",
                   help="scattered: cars anywhere on the road; drive: lane-following traffic "
                   "like a driving log")
    p.add_argument("--world", default=None, metavar="PROFILE",
                   help="draw each scene's sensor pitch, height and car count from a world "
                   "profile (`falsify fit-world`; one with places builds every street for one "
                   "of them); scattered traffic only. The config's [dims.background] world is "
                   "not applied: training scenes take only the world named here")
    p.add_argument("--labels", choices=["kitti4", "semantickitti"], default="kitti4",
                   help="npy label channel: our four classes or SemanticKITTI's train ids")
    p.add_argument("--workers", type=int, default=1, help="processes writing scans (npy)")
    p.add_argument("--format", choices=["npy", "kitti-object", "semantickitti"], default="npy",
                   help="npy: range images; kitti-object: velodyne, image_2, calib, label_2; "
                   "semantickitti: sequences/00/velodyne/*.bin, labels/*.label (raw ids)")
    p.add_argument("--camera", default=None, metavar="PRESET",
                   help="kitti-object: the camera preset (kitti-centre, the default, or "
                   "kitti-rig); no other format renders the camera")
    p.add_argument("--json", action="store_true")


def run(args) -> int:
    from falsify.data.training import (
        TrafficOptions,
        dataset_index,
        write_dataset,
        write_dataset_parallel,
    )
    from falsify.sensor.lidar import load_sensor
    from falsify.world.space import load_space

    check_out_dir(args.out)
    check_seed(args.seed)
    space = load_space(args.config)
    if not 0 < args.scans <= MAX_SCANS:
        raise UsageError(f"--scans: {args.scans} must be in 1..{MAX_SCANS} (scans are named "
                         "000000 to 999999, 6 digits as KITTI's, so names sort as indices)")
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
    if args.camera is not None and args.format != "kitti-object":
        raise UsageError(f"--camera {args.camera}: only --format kitti-object renders the "
                         f"camera (--format {args.format} writes LiDAR scans alone)")
    # before any branch: an option the chosen format does not use is refused, not ignored
    if args.workers < 1 or args.workers > 64:
        raise UsageError(f"--workers: {args.workers} must be in 1..64")
    if args.workers > 1 and args.format != "npy":
        raise UsageError(f"--workers {args.workers}: only --format npy writes in parallel")
    if args.labels != "kitti4" and args.format != "npy":
        raise UsageError(f"--labels {args.labels}: only --format npy holds labels in channel 5 "
                         "(semantickitti and kitti-object files carry their own labels)")
    if args.format == "kitti-object":
        args.camera = args.camera or "kitti-centre"
        from falsify.data.kitti_export import kitti_object_index
        from falsify.sensor.camera import camera_preset
        check_resumable(Path(args.out), kitti_object_index(
            sensor, camera_preset(args.camera).name, args.scans, args.seed, opts))
        from falsify.cli.camera import dataset_kitti_object
        summary, text = dataset_kitti_object(sensor, args.camera, Path(args.out), args.scans,
                                             args.seed, opts)
        emit(args, summary, text)
        return 0
    def progress(done: int, total: int) -> None:
        print(f"  {done}/{total} scans", flush=True)

    kwargs = dict(seed=args.seed, opts=opts, weather=space, fmt=args.format, labels=args.labels)
    check_resumable(Path(args.out), dataset_index(sensor, args.scans, **kwargs))
    if args.workers > 1:
        summary = write_dataset_parallel(args.workers, sensor, Path(args.out), args.scans,
                                         **kwargs)
    else:
        summary = write_dataset(sensor, Path(args.out), args.scans,
                                on_progress=None if args.json else progress, **kwargs)
    summary = {"out": str(args.out), "format": args.format, **summary}   # as every format says
    emit(args, summary, f"wrote {summary['written']} scans to {args.out} "
         f"({summary['scans']} in the set); points per class {summary['points_per_class']}")
    return 0


def check_resumable(out: Path, index: dict) -> None:
    """--out new or empty, or a set this command wrote with the same options and no more scans
    than asked for (a resume or an extension: every scan depends on (seed, index) alone); then
    index.json is written before any scan, so a killed run can be resumed and checked too."""
    count = "frames" if "frames" in index else "scans"
    if out.is_dir() and any(out.iterdir()):
        path = out / "index.json"
        try:
            old = json.loads(path.read_text(encoding="utf-8"))
        except FileNotFoundError:
            raise UsageError(f"--out {out}: not empty and holds no dataset (no index.json); "
                             "choose a new or empty folder") from None
        except (OSError, ValueError) as exc:
            raise UsageError(f"--out {out}: cannot read {path} ({exc}); choose a new or empty "
                             "folder") from None
        if not isinstance(old, dict):
            raise UsageError(f"--out {out}: {path} is not a dataset index; choose a new or "
                             "empty folder")
        for key in sorted((set(old) | set(index)) - {count}, key=lambda k: (k != "format", k)):
            there, now = (d.get(key, INDEX_DEFAULTS.get(key)) for d in (old, index))
            if there != now:
                option = INDEX_OPTIONS.get(key, key)
                was = "not recorded there (an older set)" if key not in old else \
                    f"{there!r} there"
                raise UsageError(f"--out {out} holds a dataset made with other options: {key} "
                                 f"({option}) is {was}, {now!r} now; "
                                 "give the same options to resume or extend it, or choose "
                                 "another --out")
        if not isinstance(old.get(count), int) or index[count] < old[count]:
            raise UsageError(f"--scans {index[count]}: --out {out} already holds a set of "
                             f"{old.get(count)} scans; give --scans {old.get(count)} or more to "
                             "resume or extend it, or choose another --out")
        return
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / "index.json", index)
