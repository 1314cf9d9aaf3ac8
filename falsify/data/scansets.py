"""Sets of labelled scans read from disk: our .npy range images, KITTI .bin (+ .label) scans,
SemanticKITTI's layout and KITTI object frame directories, grouped into named sets for pooled
evaluation and realism.

Files are grouped by the folder they sit in (one set per folder); a KITTI object directory
(velodyne/, label_2/, calib/, image_2/) is one set whose points are labelled from its 3D boxes;
each SemanticKITTI sequence (SS/velodyne/*.bin, SS/labels/*.label) is one set named by its id. A
.bin whose labels are not found is still read (it can be predicted) but marked unlabelled, so no
score counts it, and a folder's .label whose .bin is missing is listed too: the caller says so.
A file named twice (by the same or another path) is refused: it would count twice in a pooled
score.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from falsify.classes import CLASSES
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

OBJECT_LAYOUT = "velodyne/, label_2/, calib/, image_2/"   # image_2/: the camera's field of view


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
    orphan_labels: tuple[str, ...] = ()  # .label files of the set's folder whose .bin is missing

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
            images.append(checked_labels(load_scan_npy(p), p))
            semantic.append(None)
        else:
            raise FalsifyError(f"{p}: expected a .npy range image, a KITTI .bin scan or a "
                               f"KITTI object directory ({OBJECT_LAYOUT})")
        sources.append(str(p))
    labelled = [m for m in semantic if m is not None]
    both = bool(labelled) and len(labelled) == len(images) - len(unlabelled)
    sem = ([m if m is not None else np.zeros(im.shape[:2], np.uint16)
            for m, im in zip(semantic, images, strict=True)] if both else None)
    return _stack(name, images, [np.zeros(im.shape[:2], bool) for im in images], sources,
                  unlabelled, sem)


def checked_labels(image: np.ndarray, path: Path) -> np.ndarray:
    """`image` when its label channel holds only class ids (0..3); else FalsifyError naming the
    file and the allowed ids, before a score would fail on them."""
    label = image[..., 5]
    bad = (label < 0) | (label >= len(CLASSES)) | (label != np.round(label))
    if bad.any():
        raise FalsifyError(f"{path}: label channel holds {label[bad][0]:g} at "
                           f"{int(bad.sum())} pixels; allowed class ids 0..{len(CLASSES) - 1} "
                           f"({', '.join(CLASSES)})")
    return image


def read_object_set(root: Path, paths: list[Path], sensor: Sensor) -> ScanSet:
    """The frames `paths` (velodyne/*.bin) of a KITTI object directory, labelled from their
    boxes."""
    read = [read_object_frame(root, p.stem, sensor) for p in paths]
    return _stack(root.name, [f.scan.image for f in read], [f.ignore for f in read],
                  list(map(str, paths)))


def check_named_once(paths: list[Path]) -> None:
    """FalsifyError naming a file that `paths` hold twice (the same file by any path, a symlink
    included): it would count twice in a pooled score and write its outputs twice."""
    seen: dict[Path, Path] = {}
    for p in paths:
        first = seen.setdefault(p.resolve(), p)
        if first is not p:
            again = "" if first == p else f" (also as {first})"
            raise FalsifyError(f"{p}: given twice{again}; each scan is taken once")


def labels_without_scans(folder: Path) -> list[Path]:
    """The .label files a folder of .bin scans would read (beside them, or ../labels/ of a
    velodyne/ folder) whose .bin is missing, sorted: labels no scan is scored against."""
    dirs = [folder, *([folder.parent / "labels"] if folder.name == "velodyne" else [])]
    return sorted(lab for d in dirs for lab in d.glob("*.label")
                  if not (folder / f"{lab.stem}.bin").is_file())


def npy_files(folder: Path) -> list[Path]:
    """The .npy range images of a folder (a `falsify dataset` directory), sorted."""
    return sorted(p for p in folder.glob("*.npy") if not p.name.endswith(".pred.npy"))


def load_sets(paths: list[str], sensor: Sensor,
              sequences: list[str] | None = None) -> list[ScanSet]:
    """Named sets from command-line paths, in the order first named: one per object directory,
    SemanticKITTI sequence (only `sequences`' ids of a root or sequences/ folder, when given) or
    folder of .npy / .bin scans, and loose files grouped by their folder. FalsifyError names a
    scan named twice; a whole folder's labels without a scan are listed in its set."""
    groups: dict[Path, list[Path]] = {}
    objects: dict[Path, None] = {}
    scan_dirs: dict[Path, Path] = {}   # a set's folder -> the folder its whole .bin list is in
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
                groups.setdefault(p, []).extend(p / "velodyne" / f"{n}.bin" for n in frames(p))
                continue
            if is_sequence_dir(p):
                groups.setdefault(p, []).extend(sequence_files(p))
                scan_dirs[p] = p / "velodyne"
                continue
            found = sequence_dirs(p)
            if found is not None:
                for sid, d in found.items():
                    if sequences is None or sid in sequences:
                        groups.setdefault(d, []).extend(sequence_files(d))
                        scan_dirs[d] = d / "velodyne"
                continue
            files = sorted([*npy_files(p), *p.glob("*.bin")])
            if not files:
                raise FalsifyError(f"{p}: no .npy or .bin scans here, and not a SemanticKITTI "
                                   "root, sequences/ or sequence folder (SS/velodyne/*.bin) nor "
                                   f"a KITTI object directory ({OBJECT_LAYOUT})")
            groups.setdefault(p, []).extend(files)
            scan_dirs[p] = p
        elif not p.exists():
            raise FalsifyError(f"{p}: no such file")
        else:
            groups.setdefault(p.parent, []).append(p)
    check_named_once([f for files in groups.values() for f in files])
    names = [_set_name(g) for g in groups]
    sets = []
    for folder, files in groups.items():
        name = _set_name(folder)
        if names.count(name) > 1:
            name = str(folder)
        if folder in objects:
            sets.append(read_object_set(folder, files, sensor))
            continue
        orphans = labels_without_scans(scan_dirs[folder]) if folder in scan_dirs else []
        sets.append(replace(read_set(name, files, sensor),
                            orphan_labels=tuple(map(str, orphans))))
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
