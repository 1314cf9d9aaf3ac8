"""`falsify scan`: ray-cast one sample of a space into a labelled scan."""

from __future__ import annotations

import argparse
from pathlib import Path

from falsify.checks import check_out_dir
from falsify.cli.common import UsageError, camera_option, emit
from falsify.errors import FalsifyError


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("config")
    p.add_argument("--out", required=True)
    p.add_argument("--set", action="append", metavar="KEY=VALUE",
                   help="fix a dimension (repeatable); other dims take their first value")
    camera_option(p, "also render the camera: image.png, class.png/.npy, instance.npy, "
                  "depth.npy and overlay.png")
    p.add_argument("--json", action="store_true")


def _set_pairs(pairs: list[str]) -> dict[str, str]:
    """--set's KEY=VALUE pairs; a key given twice is an error, not the last one winning."""
    out: dict[str, str] = {}
    for item in pairs:
        if "=" not in item:
            raise UsageError(f"--set {item!r}: expected KEY=VALUE, e.g. --set x=2.5")
        key, value = (part.strip() for part in item.split("=", 1))
        if key in out:
            raise UsageError(f"--set {key}: given twice ({out[key]} and {value}); give it once")
        out[key] = value
    return out


def _check_active(space, sample, pairs: dict[str, str]) -> None:
    """A --set dim of a car the sample does not hold (beyond its count) would be pinned to its
    first value without a word: an error naming the count that would use it."""
    count = int(sample.as_dict().get("count", 1))
    for key in pairs:
        if not space.active(key, count):
            raise UsageError(f"--set {key}: a dim of a car beyond the sample's count ({count}); "
                             "also set count to hold that car")


def output_names() -> tuple[str, ...]:
    """Every file `falsify scan` writes into --out, with the camera's."""
    from falsify.sensor.camera import CAMERA_FILES
    return (*(f"scan.{e}" for e in ("npy", "png", "bin", "label")), *CAMERA_FILES,
            "overlay.png")


def run(args) -> int:
    import numpy as np

    from falsify.data.real_backgrounds import scanner_for
    from falsify.data.velodyne import kitti_arrays
    from falsify.fileio import write_bytes, write_npy
    from falsify.images.png import encode_png
    from falsify.images.scan_pictures import scan_picture
    from falsify.results.samples import sample_seed
    from falsify.sensor.lidar import load_sensor
    from falsify.sensor.look import check_looks
    from falsify.sensor.simulator import InvalidSample
    from falsify.world.space import load_space

    check_out_dir(args.out)
    space = load_space(args.config)
    check_looks(space)
    pairs = _set_pairs(args.set or [])
    sample = space.make(pairs)
    _check_active(space, sample, pairs)
    sensor = load_sensor(space.sensor)
    sim = scanner_for(space, sensor)
    camera = None
    if args.camera is not None:
        space.require_streets("--camera")
        from falsify.sensor.camera import camera_preset
        from falsify.sensor.look import look_of
        camera = camera_preset(args.camera)
        look_of(sample)  # a value the camera cannot render fails before anything is written
    try:   # with the sample's own seed, so its ray drop and noise are the ones a run scores
        scan = sim.scan(sample, rng=np.random.default_rng(sample_seed(space, sample)))
    except InvalidSample as exc:
        raise FalsifyError(f"invalid sample: {exc}") from None
    out = Path(args.out)
    summary = {
        "sample": sample.as_dict(), "sensor": sensor.name, "shape": list(scan.image.shape),
        "points": int(scan.valid.sum()), "car_points": scan.count(1),
        "placed_points": int((scan.valid & sim.placed_pixels(scan)).sum()),
        "files": [str(out / f"scan.{e}") for e in ("npy", "png", "bin", "label")],
    }
    extra: dict[str, bytes] = {}
    if camera is not None:
        from falsify.cli.camera import scan_camera_files
        extra, summary["camera"] = scan_camera_files(sim, camera, sample, scan)
    png = encode_png(scan_picture(scan.image))
    points, labels = kitti_arrays(scan)   # SemanticKITTI's own files: x, y, z, remission; labels
    for name in output_names():   # a stop between files must not leave the last sample's
        (out / name).unlink(missing_ok=True)
    write_npy(out / "scan.npy", scan.image)
    write_bytes(out / "scan.png", png)
    write_bytes(out / "scan.bin", points.tobytes())
    write_bytes(out / "scan.label", labels.tobytes())
    for name, data in extra.items():
        write_bytes(out / name, data)
        summary["files"].append(str(out / name))
    camera_text = f"; the camera's {', '.join(extra)}" if extra else ""
    emit(args, summary, f"wrote {out / 'scan.npy'}, .png, .bin and .label{camera_text}: "
         f"{summary['points']} points, {summary['car_points']} on cars, "
         f"{summary['placed_points']} on the placed {', '.join(c.model for c in sample.cars)}")
    return 0
