"""Sets of labelled scans read from disk: our .npy range images, KITTI .bin (+ .label) scans and
KITTI object frame directories, grouped into named sets for pooled evaluation and realism.

Files are grouped by the folder they sit in (one set per folder); a KITTI object directory
(velodyne/, label_2/, calib/) is one set whose points are labelled from its 3D boxes.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from falsify.data.kitti_frames import read_object_frame
from falsify.data.kitti_object import frames, is_object_dir
from falsify.data.range_npy import load_scan_npy
from falsify.data.velodyne import read_kitti
from falsify.errors import FalsifyError
from falsify.sensor.lidar import Sensor

ROOT = Path(__file__).resolve().parents[2]   # the source checkout
# The shared real KITTI data beside the repository (evaluation only; never copied in).
KITTI_DIR = ROOT.parent / "shared" / "data" / "kitti"


@dataclass(frozen=True)
class ScanSet:
    """Labelled range images (B, H, W, 6) with a per-pixel mask of pixels left out of scores."""

    name: str
    images: np.ndarray
    ignore: np.ndarray          # (B, H, W) bool
    sources: tuple[str, ...]    # one per scan: the file (or object frame) it came from

    def __len__(self) -> int:
        return len(self.images)


def read_set(name: str, paths: list[Path], sensor: Sensor) -> ScanSet:
    """One set from .npy range images and KITTI .bin scans (a .label beside a .bin is read)."""
    images, sources = [], []
    for p in paths:
        if p.suffix == ".bin":
            label = p.with_suffix(".label")
            images.append(read_kitti(p, label if label.exists() else None, sensor).image)
        elif p.suffix == ".npy":
            images.append(load_scan_npy(p))
        else:
            raise FalsifyError(f"{p}: expected a .npy range image, a KITTI .bin scan or a "
                               "KITTI object directory (velodyne/, label_2/, calib/)")
        sources.append(str(p))
    return _stack(name, images, [np.zeros(im.shape[:2], bool) for im in images], sources)


def read_object_set(root: Path, sensor: Sensor) -> ScanSet:
    """All frames of a KITTI object directory, labelled from their boxes."""
    names = frames(root)
    read = [read_object_frame(root, n, sensor) for n in names]
    return _stack(root.name, [f.scan.image for f in read], [f.ignore for f in read],
                  [str(root / "velodyne" / f"{n}.bin") for n in names])


def npy_files(folder: Path) -> list[Path]:
    """The .npy range images of a folder (a `falsify dataset` directory), sorted."""
    return sorted(p for p in folder.glob("*.npy") if not p.name.endswith(".pred.npy"))


def load_sets(paths: list[str], sensor: Sensor) -> list[ScanSet]:
    """Named sets from command-line paths: one per object directory or folder of .npy scans,
    and loose files grouped by their folder, in the order first named."""
    groups: dict[Path, list[Path]] = {}
    objects: dict[Path, None] = {}
    for p in map(Path, paths):
        if p.is_dir():
            if is_object_dir(p):
                objects[p] = None
                groups.setdefault(p, [])
                continue
            files = npy_files(p)
            if not files:
                raise FalsifyError(f"{p}: a folder with no .npy scans and not a KITTI object "
                                   "directory (velodyne/, label_2/, calib/)")
            groups.setdefault(p, []).extend(files)
        elif not p.exists():
            raise FalsifyError(f"{p}: no such file")
        else:
            groups.setdefault(p.parent, []).append(p)
    names = [g.name or str(g) for g in groups]
    sets = []
    for folder, files in groups.items():
        name = folder.name or str(folder)
        if names.count(name) > 1:
            name = str(folder)
        sets.append(read_object_set(folder, sensor) if folder in objects
                    else read_set(name, files, sensor))
    shapes = {s.images.shape[1:] for s in sets}
    if len(shapes) > 1:
        raise FalsifyError(f"scans have different shapes: {sorted(shapes)}")
    return sets


def real_sets(sensor: Sensor, root: Path = KITTI_DIR) -> list[ScanSet]:
    """The two real evaluation sets: SqueezeSeg's four KITTI scans and three SemanticKITTI
    scans projected with `sensor`; FalsifyError naming the folder when it is absent."""
    squeeze = sorted((root / "squeezeseg").glob("*.npy"))
    semantic = sorted((root / "semantickitti").glob("*.bin"))
    if not squeeze or not semantic:
        raise FalsifyError(f"{root}: real KITTI scans not found (expected squeezeseg/*.npy and "
                           "semantickitti/*.bin; see shared/data/README.md)")
    return [read_set("squeezeseg", squeeze, sensor), read_set("semantickitti", semantic, sensor)]


def _stack(name: str, images: list[np.ndarray], ignore: list[np.ndarray],
           sources: list[str]) -> ScanSet:
    shapes = {im.shape for im in images}
    if len(shapes) > 1:
        raise FalsifyError(f"set {name}: scans have different shapes: {sorted(shapes)}")
    return ScanSet(name, np.stack(images), np.stack(ignore), tuple(sources))
