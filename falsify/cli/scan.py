"""`falsify scan`: ray-cast one sample of a space into a labelled scan."""

from __future__ import annotations

import argparse

from falsify.checks import check_out_dir
from falsify.cli.common import UsageError, camera_option, emit
from falsify.errors import FalsifyError
from falsify.owned_files import FileList


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("config")
    p.add_argument("--out", required=True,
                   help="folder for scan.npy (the range image), scan.png (its picture) and "
                   "scan.bin/.label (its points, KITTI's layout); with --camera, the images")
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


SCAN_FILES = ("scan.npy", "scan.png", "scan.bin", "scan.label")
# The files a `scan --out` wrote into its folder (name -> SHA-256): the next scan into it
# replaces or removes those, and refuses to overwrite a file of the same name it did not write.
WRITTEN = FileList("scan-files.json", "files", "falsify scan")


def _names(camera: bool) -> tuple[str, ...]:
    """The files this scan writes into --out."""
    from falsify.sensor.camera import CAMERA_FILES
    return (*SCAN_FILES, *CAMERA_FILES, "overlay.png") if camera else SCAN_FILES


def run(args) -> int:
    import numpy as np

    from falsify.data.real_backgrounds import scanner_for
    from falsify.data.velodyne import kitti_arrays
    from falsify.fileio import npy_bytes
    from falsify.images.png import encode_png
    from falsify.images.scan_pictures import scan_picture
    from falsify.results.samples import sample_seed
    from falsify.sensor.lidar import load_sensor
    from falsify.sensor.look import check_looks
    from falsify.sensor.simulator import InvalidSample
    from falsify.world.space import load_space

    out = check_out_dir(args.out)
    listed = WRITTEN.read(out)   # a broken list is refused before anything is cast
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
    WRITTEN.check_targets(out, _names(camera is not None), listed)
    try:   # with the sample's own seed, so its ray drop and noise are the ones a run scores
        scan = sim.scan(sample, rng=np.random.default_rng(sample_seed(space, sample)))
    except InvalidSample as exc:
        raise FalsifyError(f"invalid sample: {exc}") from None
    summary = {
        "sample": sample.as_dict(), "sensor": sensor.name, "shape": list(scan.image.shape),
        "points": int(scan.valid.sum()), "car_points": scan.count(1),
        "placed_points": int((scan.valid & sim.placed_pixels(scan)).sum()),
        "files": [str(out / name) for name in SCAN_FILES],
    }
    extra: dict[str, bytes] = {}
    if camera is not None:
        from falsify.cli.camera import scan_camera_files
        extra, summary["camera"] = scan_camera_files(sim, camera, sample, scan)
    png = encode_png(scan_picture(scan.image))
    points, labels = kitti_arrays(scan)   # SemanticKITTI's own files: x, y, z, remission; labels
    files = dict(zip(SCAN_FILES, (npy_bytes(scan.image), png, points.tobytes(),
                                  labels.tobytes()), strict=True))
    WRITTEN.replace(out, {**files, **extra}, listed)   # no file of the last sample stays
    summary["files"] += [str(out / name) for name in extra]
    camera_text = f"; the camera's {', '.join(extra)}" if extra else ""
    emit(args, summary, f"wrote {out / 'scan.npy'}, .png, .bin and .label{camera_text}: "
         f"{summary['points']} points, {summary['car_points']} on cars, "
         f"{summary['placed_points']} on the placed {', '.join(c.model for c in sample.cars)}")
    return 0
