"""The camera's commands: `falsify calib`, and the camera parts of scan, dataset and bench."""

from __future__ import annotations

import argparse
from pathlib import Path

from falsify.checks import check_out_dir
from falsify.cli.common import int_in
from falsify.errors import FalsifyError


def scan_camera_files(sim, camera, sample, scan) -> tuple[dict[str, bytes], dict]:
    """The camera files of one scanned sample (with overlay.png) and their summary."""
    from falsify.images.png import encode_png
    from falsify.jobs.calib import car_points_on_car_pixels
    from falsify.sensor.camera import camera_files, overlay_picture
    from falsify.sensor.render import CameraRenderer

    image = CameraRenderer(sim, camera).render_sample(sample)
    pts = scan.points
    car = pts[pts[:, 5] == 1, :3]
    files = camera_files(image)
    files["overlay.png"] = encode_png(overlay_picture(image, camera, car))
    n, inside, on = car_points_on_car_pixels(pts[:, :3], pts[:, 5], camera, image.cls)
    return files, {"preset": camera.name, "shape": list(camera.shape), "car_points": n,
                   "car_points_in_image": inside, "car_points_on_car_pixels": on,
                   "fraction": None if inside == 0 else round(on / inside, 5)}


def dataset_kitti_object(sensor, camera: str, out: Path, frames: int, seed: int, opts
                         ) -> tuple[dict, str]:
    from falsify.data.kitti_export import write_kitti_object
    from falsify.sensor.camera import camera_preset

    cam = camera_preset(camera)
    res = write_kitti_object(sensor, cam, out, frames, seed=seed, opts=opts)
    summary = {"format": "kitti-object", "out": res.out, "frames": res.frames,
               "written": res.written, "objects": res.objects, "camera": res.camera,
               "sensor": res.sensor}
    return summary, (f"wrote {res.written} KITTI object frames to {res.out} ({res.frames} in the "
                     f"set, camera {res.camera}); labelled objects {res.objects}")


def bench_camera_text(config: str, camera: str, **options) -> tuple[dict, str]:
    """`bench camera`'s result and its line; `options` (samples, naive_samples) as given."""
    from falsify.bench.camera import bench_camera

    r = bench_camera(config, camera, **options)
    return r, (f"camera {r['image']}: {r['ms_per_image_cold']} ms/image cold, "
               f"{r['ms_per_image_warm']} ms warm; naive {r['naive_ms_per_image']} ms: "
               f"{r['speedup_cold']}x cold, {r['speedup_warm']}x warm")


def add_arguments(p: argparse.ArgumentParser) -> None:
    """`falsify calib`'s options."""
    from falsify.sensor.camera import CAMERA_PRESETS, DEFAULT_CAMERA

    p.add_argument("directory", nargs="?", default=None,
                   help="a KITTI object directory (velodyne, image_2, calib, label_2)")
    p.add_argument("--out", default=None,
                   help="a folder for one overlay PNG per frame (none are written without it)")
    p.add_argument("--scenes", default=None, metavar="CONFIG",
                   help="instead: score car points on car pixels over samples of a space")
    p.add_argument("--samples", type=int_in(1, 1_000_000), default=None,
                   help="--scenes: samples of the grid (default 100)")
    p.add_argument("--camera", default=None, choices=CAMERA_PRESETS,
                   help=f"--scenes: the camera preset (default {DEFAULT_CAMERA})")
    p.add_argument("--json", action="store_true")


def run(args) -> int:
    """`falsify calib`: a KITTI object directory's calibration, or our scenes'."""
    import json

    from falsify.jobs.calib import check_kitti_dir, scene_agreement
    from falsify.sensor.camera import DEFAULT_CAMERA

    if (args.directory is None) == (args.scenes is None):
        raise FalsifyError("calib: give a KITTI object DIRECTORY or --scenes CONFIG (not both)")
    if args.scenes is not None:
        if args.out is not None:
            raise FalsifyError("calib --out: overlays are written for a KITTI object DIRECTORY "
                               "only, not with --scenes")
        res = scene_agreement(args.scenes, samples=args.samples or 100,
                              camera=args.camera or DEFAULT_CAMERA)
        summary = res.to_json()
        text = (f"car points on car pixels ({res.camera}, {res.scored} of {res.samples} samples "
                f"scored): median {res.median}, minimum {res.minimum}, pooled {res.pooled}")
    else:
        for flag, value in (("--samples", args.samples), ("--camera", args.camera)):
            if value is not None:
                raise FalsifyError(f"calib {flag}: used with --scenes only; a KITTI object "
                                   "DIRECTORY is read with its own calib files")
        if not Path(args.directory).is_dir():
            raise FalsifyError(f"{args.directory}: not a directory")
        if args.out is not None:
            check_out_dir(args.out)
        report = check_kitti_dir(args.directory, args.out)
        summary = report.to_json()
        p = summary["pooled"]
        lines = [f"{p['inside_2d']} of {p['points_in_boxes']} in-box points inside their 2D boxes "
                 f"({p['fraction']}) over {p['objects']} objects in {len(report.frames)} frames"]
        for t, v in summary["by_type"].items():
            lines.append(f"  {t:12s} {v['inside_2d']:6d} / {v['points_in_boxes']:6d}  "
                         f"{v['fraction']}")
        if args.out is not None:
            lines.append(f"overlays: {args.out}")
        text = "\n".join(lines)
    if args.json:
        print(json.dumps(summary, indent=2, sort_keys=True, default=str))
    else:
        print(text)
    return 0
