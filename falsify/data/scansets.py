"""Sets of labelled scans read from disk: our .npy range images, KITTI .bin (+ .label) scans,
SemanticKITTI's layout and KITTI object frame directories, grouped into named sets for pooled
evaluation and realism.

Files are grouped by the folder they sit in (one set per folder); a KITTI object directory
(velodyne/, label_2/, calib/) is one set whose points are labelled from its 3D boxes; each
SemanticKITTI sequence (SS/velodyne/*.bin, SS/labels/*.label) is one set named by its id. A .bin
whose labels are not found is still read (it can be predicted) but marked unlabelled, so no score
counts it: the caller says so.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from falsify.data.kitti_frames import read_object_frame
from falsify.data.kitti_object import frames
from falsify.data.range_npy import load_scan_npy
from falsify.data.velodyne import read_kitti
from falsify.errors import FalsifyError
from falsify.sensor.lidar import Sensor
from falsify.world.real_scans import (
    available_sequences,
    is_object_dir,
    is_sequence_dir,
    label_file,
    sequence_dirs,
    sequence_files,
)


@dataclass(frozen=True)
class ScanSet:
    """Labelled range images (B, H, W, 6) with a per-pixel mask of pixels left out of scores."""

    name: str
    images: np.ndarray
    ignore: np.ndarray          # (B, H, W) bool
    sources: tuple[str, ...]    # one per scan: the file (or object frame) it came from
    unlabelled: tuple[str, ...] = ()   # the sources whose labels were not found: never scored
    semantic: np.ndarray | None = None   # (B, H, W) uint16 raw SemanticKITTI ids, where every
    #                                      scan came from a .bin with a .label

    def __len__(self) -> int:
        return len(self.images)

    def labelled(self) -> np.ndarray:
        """(B,) bool: the scans whose labels were read, the only ones a score may count."""
        missing = set(self.unlabelled)
        return np.array([s not in missing for s in self.sources], bool)


def read_set(name: str, paths: list[Path], sensor: Sensor) -> ScanSet:
    """One set from .npy range images and KITTI .bin scans; a .bin's labels are read from
    x.label beside it or ../labels/x.label, and a .bin with neither is listed as unlabelled."""
    images, sources, unlabelled, semantic = [], [], [], []
    for p in paths:
        if p.suffix == ".bin":
            label = label_file(p)
            if label is None:
                unlabelled.append(str(p))
            scan = read_kitti(p, label, sensor)
            images.append(scan.image)
            semantic.append(scan.semantic if label is not None else None)
        elif p.suffix == ".npy":
            images.append(load_scan_npy(p))
            semantic.append(None)
        else:
            raise FalsifyError(f"{p}: expected a .npy range image, a KITTI .bin scan or a "
                               "KITTI object directory (velodyne/, label_2/, calib/)")
        sources.append(str(p))
    labelled = [m for m in semantic if m is not None]
    both = bool(labelled) and len(labelled) == len(images) - len(unlabelled)
    sem = ([m if m is not None else np.zeros(im.shape[:2], np.uint16)
            for m, im in zip(semantic, images, strict=True)] if both else None)
    return _stack(name, images, [np.zeros(im.shape[:2], bool) for im in images], sources,
                  unlabelled, sem)


def read_object_set(root: Path, sensor: Sensor) -> ScanSet:
    """All frames of a KITTI object directory, labelled from their boxes."""
    names = frames(root)
    read = [read_object_frame(root, n, sensor) for n in names]
    return _stack(root.name, [f.scan.image for f in read], [f.ignore for f in read],
                  [str(root / "velodyne" / f"{n}.bin") for n in names])


def npy_files(folder: Path) -> list[Path]:
    """The .npy range images of a folder (a `falsify dataset` directory), sorted."""
    return sorted(p for p in folder.glob("*.npy") if not p.name.endswith(".pred.npy"))


def load_sets(paths: list[str], sensor: Sensor,
              sequences: list[str] | None = None) -> list[ScanSet]:
    """Named sets from command-line paths, in the order first named: one per object directory,
    SemanticKITTI sequence (only `sequences`' ids of a root or sequences/ folder, when given) or
    folder of .npy / .bin scans, and loose files grouped by their folder."""
    groups: dict[Path, list[Path]] = {}
    objects: dict[Path, None] = {}
    if sequences is not None:
        allowed = available_sequences(paths)
        unknown = [q for q in sequences if q not in allowed]
        if unknown or not sequences:
            raise FalsifyError(f"sequences {', '.join(unknown) or '(none)'}: not among the "
                               f"SemanticKITTI sequences named ({', '.join(allowed) or 'none'})")
    for p in map(Path, paths):
        if p.is_dir():
            if is_object_dir(p):
                objects[p] = None
                groups.setdefault(p, [])
                continue
            if is_sequence_dir(p):
                groups.setdefault(p, []).extend(sequence_files(p))
                continue
            found = sequence_dirs(p)
            if found is not None:
                for sid, d in found.items():
                    if sequences is None or sid in sequences:
                        groups.setdefault(d, []).extend(sequence_files(d))
                continue
            files = sorted([*npy_files(p), *p.glob("*.bin")])
            if not files:
                raise FalsifyError(f"{p}: no .npy or .bin scans here, and not a SemanticKITTI "
                                   "root, sequences/ or sequence folder (SS/velodyne/*.bin) nor "
                                   "a KITTI object directory (velodyne/, label_2/, calib/)")
            groups.setdefault(p, []).extend(files)
        elif not p.exists():
            raise FalsifyError(f"{p}: no such file")
        else:
            groups.setdefault(p.parent, []).append(p)
    names = [_set_name(g) for g in groups]
    sets = []
    for folder, files in groups.items():
        name = _set_name(folder)
        if names.count(name) > 1:
            name = str(folder)
        sets.append(read_object_set(folder, sensor) if folder in objects
                    else read_set(name, files, sensor))
    shapes = {s.images.shape[1:] for s in sets}
    if len(shapes) > 1:
        raise FalsifyError(f"scans have different shapes: {sorted(shapes)}")
    return sets


def _set_name(folder: Path) -> str:
    """A folder's set name: its own, or its sequence's for a velodyne/ folder."""
    if folder.name == "velodyne" and folder.parent.name:
        return folder.parent.name
    return folder.name or str(folder)


def _stack(name: str, images: list[np.ndarray], ignore: list[np.ndarray],
           sources: list[str], unlabelled: list[str] | None = None,
           semantic: list[np.ndarray] | None = None) -> ScanSet:
    shapes = {im.shape for im in images}
    if len(shapes) > 1:
        raise FalsifyError(f"set {name}: scans have different shapes: {sorted(shapes)}")
    return ScanSet(name, np.stack(images), np.stack(ignore), tuple(sources),
                   tuple(unlabelled or ()), None if semantic is None else np.stack(semantic))
