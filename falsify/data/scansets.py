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
from falsify.data.kitti_object import frames, read_velodyne
from falsify.data.range_npy import load_scan_npy, npy_files
from falsify.data.velodyne import kitti_rows, read_kitti, read_kitti_points
from falsify.errors import FalsifyError
from falsify.sensor.lidar import Sensor
from falsify.sensor.scan import point_pixels
from falsify.world.real_scans import (
    available_sequences,
    is_object_dir,
    is_sequence_dir,
    label_file,
    sequence_dirs,
    sequence_files,
)

OBJECT_LAYOUT = "velodyne/, label_2/, calib/, image_2/"   # image_2/: the camera's field of view
NPY_HAS_NO_POINTS = ("a .npy range image holds one point per pixel, not the scan's points, so "
                     "it cannot be scored per point; give its .bin scan or use --score pixels")


@dataclass(frozen=True)
class ScanPoints:
    """One scan's points that have a pixel in the sensor's image, for point-wise scoring
    (SemanticKITTI's protocol): each takes its pixel's prediction and counts with its own label
    at its own range; `outside` counts the points that have no pixel, never scored."""

    pixel: np.ndarray                # (N,) int64 flat index row * W + col into the range image
    range: np.ndarray                # (N,) float32 metres
    label: np.ndarray                # (N,) uint8 four-class id
    ignore: np.ndarray               # (N,) bool: counts for no class (an ignored box's point)
    semantic: np.ndarray | None      # (N,) uint16 raw SemanticKITTI id, where a .label was read
    outside: int                     # points outside the image (field of view or range) or
    #                                  not finite: no pixel, no prediction
    xyzi: np.ndarray | None = None   # (N, 4) float32 x, y, z, remission: what a points
    #                                  network is fed (`point_rows`)
    held: np.ndarray | None = None   # (H * W,) int64 the point each pixel holds (the nearest,
    #                                  as the range image keeps it), -1 for an empty pixel


def scan_points(sensor: Sensor, xyz: np.ndarray, label: np.ndarray, ignore: np.ndarray,
                semantic: np.ndarray | None, dropped: int = 0,
                rows: np.ndarray | None = None,
                remission: np.ndarray | None = None) -> ScanPoints:
    """The points of one scan at the pixels the range image put them in (the same projection,
    laser rings included: `rows`, `kitti_rows` when not given), those without a pixel counted
    in `outside` with `dropped`; with `remission`, the points themselves and which one each
    pixel holds (the nearest wins, ties to the later point, as `image_from_points` decides)."""
    if rows is None:
        rows = kitti_rows(sensor, xyz)
    row, col, inside = point_pixels(sensor, xyz, rows)
    p = np.asarray(xyz, np.float64)
    pixel = row[inside] * sensor.shape[1] + col[inside]
    ranges = np.linalg.norm(p[inside], axis=1)
    xyzi = held = None
    if remission is not None:
        xyzi = np.ascontiguousarray(np.column_stack(
            [np.asarray(xyz, np.float32)[inside], np.asarray(remission, np.float32)[inside]]))
        order = np.argsort(-ranges, kind="stable")   # far first, so near points overwrite
        held = np.full(sensor.shape[0] * sensor.shape[1], -1, np.int64)
        held[pixel[order]] = order
    return ScanPoints(pixel, ranges.astype(np.float32),
                      np.asarray(label, np.uint8)[inside], np.asarray(ignore, bool)[inside],
                      None if semantic is None else np.asarray(semantic, np.uint16)[inside],
                      dropped + int((~inside).sum()), xyzi, held)


def point_rows(s: ScanSet) -> ScanSet:
    """`s` with each scan's points that have a pixel laid out as one row of pixels, (B, 1, N,
    6) x, y, z, remission, range, label in the scan file's order (shorter scans padded with
    empty pixels), each point at its own pixel: a points network is fed every one of them and
    each is scored with its own answer (SemanticKITTI's point-wise protocol), not with the
    answer of the nearer point that won its range-image pixel."""
    if s.points is None or any(p.xyzi is None for p in s.points):
        raise ValueError(f"set {s.name}: read without its points (load_sets(points=True))")
    n = max([len(p.pixel) for p in s.points] + [1])
    images = np.zeros((len(s), 1, n, 6), np.float32)
    ignore = np.zeros((len(s), 1, n), bool)
    semantic = None if s.semantic is None else np.zeros((len(s), 1, n), np.uint16)
    for k, p in enumerate(s.points):
        m = len(p.pixel)
        images[k, 0, :m, :4] = p.xyzi
        images[k, 0, :m, 4] = p.range
        images[k, 0, :m, 5] = p.label
        ignore[k, 0, :m] = p.ignore
        if semantic is not None and p.semantic is not None:
            semantic[k, 0, :m] = p.semantic
    points = tuple(replace(p, pixel=np.arange(len(p.pixel), dtype=np.int64), held=None)
                   for p in s.points)
    return replace(s, images=images, ignore=ignore, semantic=semantic, points=points)


def pixel_classes(points: ScanPoints, answers: np.ndarray, shape: tuple[int, int]
                  ) -> np.ndarray:
    """Per-point classes (N,) back onto the range image (H, W): each pixel takes the class of
    the point it holds, 0 where it holds none (the picture of a `point_rows` prediction)."""
    if points.held is None:
        raise ValueError("points read without remission: no pixel holds a known point")
    out = np.zeros(shape[0] * shape[1], np.asarray(answers).dtype)
    m = points.held >= 0
    out[m] = np.asarray(answers)[points.held[m]]
    return out.reshape(shape)


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
    points: tuple[ScanPoints, ...] | None = None   # one per scan, when read for point scoring

    def __len__(self) -> int:
        return len(self.images)

    def labelled(self) -> np.ndarray:
        """(B,) bool: the scans whose labels were read, the only ones a score may count."""
        missing = set(self.unlabelled)
        return np.array([s not in missing for s in self.sources], bool)


def read_set(name: str, paths: list[Path], sensor: Sensor, points: bool = False) -> ScanSet:
    """One set from .npy range images and KITTI .bin scans; a .bin's labels are read from
    x.label beside it or ../labels/x.label, and a .bin with neither is listed as unlabelled.
    With `points`, each .bin's points are kept too (a .npy is refused: it has none)."""
    images, sources, unlabelled, semantic, kept = [], [], [], [], []
    for p in paths:
        if p.suffix == ".bin":
            label = label_file(p)
            if label is None:
                unlabelled.append(str(p))
            if points:
                read = read_kitti_points(p, label)
                rows = kitti_rows(sensor, read.xyz)   # once, for the image and the points
                scan = read.project(sensor, rows)
                kept.append(scan_points(sensor, read.xyz, read.cls,
                                        np.zeros(len(read.cls), bool), read.semantic,
                                        read.dropped, rows, read.remission))
            else:
                scan = read_kitti(p, label, sensor)
            images.append(scan.image)
            semantic.append(scan.semantic if label is not None else None)
        elif p.suffix == ".npy" and points:
            raise FalsifyError(f"{p}: {NPY_HAS_NO_POINTS}")
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
                  unlabelled, sem, tuple(kept) if points else None)


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


def read_object_set(root: Path, paths: list[Path], sensor: Sensor,
                    points: bool = False) -> ScanSet:
    """The frames `paths` (velodyne/*.bin) of a KITTI object directory, labelled from their
    boxes (with `points`, each point with its class from the same boxes)."""
    images, ignore, kept = [], [], []
    for p in paths:
        f = read_object_frame(root, p.stem, sensor)
        images.append(f.scan.image)
        ignore.append(f.ignore)
        if points:
            kept.append(scan_points(sensor, f.xyz, f.point_class, f.point_ignore, None,
                                    remission=read_velodyne(p)[:, 3]))
    return _stack(root.name, images, ignore, list(map(str, paths)),
                  points=tuple(kept) if points else None)


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


@dataclass(frozen=True)
class SetPlan:
    """One set to read: its name, its files, and how they are read."""

    name: str
    files: tuple[Path, ...]
    object_root: Path | None = None   # a KITTI object directory, labelled from its boxes
    scan_dir: Path | None = None      # the folder whose whole .bin list the set is (orphans)

    @property
    def projects(self) -> bool:
        """Whether a sensor projects any of its scans (a .bin scan or an object frame)."""
        return any(f.suffix == ".bin" for f in self.files)


def plan_sets(paths: list[str], sequences: list[str] | None = None) -> list[SetPlan]:
    """The sets the command-line paths name, in the order first named, without reading a scan:
    one per object directory, SemanticKITTI sequence (only `sequences`' ids of a root or
    sequences/ folder, when given) or folder of .npy / .bin scans, and loose files grouped by
    their folder. FalsifyError names a scan named twice or a path that holds no scans."""
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
    plans = []
    for folder, files in groups.items():
        name = _set_name(folder)
        if names.count(name) > 1:
            name = str(folder)
        plans.append(SetPlan(name, tuple(files), folder if folder in objects else None,
                             scan_dirs.get(folder)))
    return plans


def read_sets(plans: list[SetPlan], sensor: Sensor, points: bool = False) -> list[ScanSet]:
    """Read the planned sets (with `points`, each .bin's points too, for point-wise scoring);
    a whole folder's labels without a scan are listed in its set."""
    sets = []
    for plan in plans:
        if plan.object_root is not None:
            sets.append(read_object_set(plan.object_root, list(plan.files), sensor, points))
            continue
        orphans = labels_without_scans(plan.scan_dir) if plan.scan_dir is not None else []
        sets.append(replace(read_set(plan.name, list(plan.files), sensor, points),
                            orphan_labels=tuple(map(str, orphans))))
    shapes = {s.images.shape[1:] for s in sets}
    if len(shapes) > 1:
        raise FalsifyError(f"scans have different shapes: {sorted(shapes)}")
    return sets


def read_part(plan: SetPlan, files: list[Path], sensor: Sensor, points: bool = False
              ) -> ScanSet:
    """Some of a planned set's scans, read as `read_sets` reads the whole set (its labels
    without a scan are the plan's, `plan_orphans`)."""
    if plan.object_root is not None:
        return read_object_set(plan.object_root, files, sensor, points)
    return read_set(plan.name, files, sensor, points)


def plan_name(plan: SetPlan) -> str:
    """The name `read_sets` gives a planned set."""
    return plan.object_root.name if plan.object_root is not None else plan.name


def plan_unlabelled(plan: SetPlan) -> tuple[str, ...]:
    """The planned set's .bin scans that no label file goes with, as reading lists them."""
    if plan.object_root is not None:
        return ()
    return tuple(str(p) for p in plan.files if p.suffix == ".bin" and label_file(p) is None)


def plan_orphans(plan: SetPlan) -> tuple[str, ...]:
    """The labels of the planned set's folder whose .bin is missing (`labels_without_scans`)."""
    if plan.object_root is not None or plan.scan_dir is None:
        return ()
    return tuple(map(str, labels_without_scans(plan.scan_dir)))


def plan_semantic(plan: SetPlan) -> bool:
    """Whether the whole set, read, carries SemanticKITTI labels (`ScanSet.semantic`): every
    scan a .bin, and at least one with its .label."""
    return (plan.object_root is None and all(p.suffix == ".bin" for p in plan.files)
            and len(plan_unlabelled(plan)) < len(plan.files))


def load_sets(paths: list[str], sensor: Sensor, sequences: list[str] | None = None,
              points: bool = False) -> list[ScanSet]:
    """Named sets from command-line paths (`plan_sets`), read (`read_sets`)."""
    return read_sets(plan_sets(paths, sequences), sensor, points)


def _set_name(folder: Path) -> str:
    """A folder's set name: its own, or its sequence's for a velodyne/ folder."""
    if folder.name == "velodyne" and folder.parent.name:
        return folder.parent.name
    return folder.name or str(folder)


def _stack(name: str, images: list[np.ndarray], ignore: list[np.ndarray],
           sources: list[str], unlabelled: list[str] | None = None,
           semantic: list[np.ndarray] | None = None,
           points: tuple[ScanPoints, ...] | None = None) -> ScanSet:
    shapes = {im.shape for im in images}
    if len(shapes) > 1:
        raise FalsifyError(f"set {name}: scans have different shapes: {sorted(shapes)}")
    return ScanSet(name, np.stack(images), np.stack(ignore), tuple(sources),
                   tuple(unlabelled or ()), None if semantic is None else np.stack(semantic),
                   points=points)
