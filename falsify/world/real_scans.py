"""Which files real scans are: KITTI .bin scans, SemanticKITTI's layout (SS/velodyne/*.bin with
SS/labels/*.label) and KITTI object directories (velodyne/, label_2/, calib/), found on disk
without reading them, so a space can name real scans as its backgrounds.
"""

from __future__ import annotations

import re
from pathlib import Path

from falsify.errors import FalsifyError


def label_file(bin_path: str | Path) -> Path | None:
    """The SemanticKITTI .label of a .bin scan: beside it (x.label) or in ../labels/ (the
    dataset's own layout, SS/velodyne/x.bin with SS/labels/x.label); None when neither exists."""
    p = Path(bin_path)
    for candidate in (p.with_suffix(".label"), p.parent.parent / "labels" / f"{p.stem}.label"):
        if candidate.is_file():
            return candidate
    return None


def is_object_dir(path: Path) -> bool:
    """A folder laid out as KITTI's objects (velodyne/ and label_2/ beside each other)."""
    return (path / "velodyne").is_dir() and (path / "label_2").is_dir()


SEQUENCE_ID = re.compile(r"\d\d")   # SemanticKITTI's sequence folders: 00 .. 21


def is_sequence_dir(path: Path) -> bool:
    """A SemanticKITTI sequence folder (SS/ holding velodyne/; labels/ when labelled)."""
    return (path / "velodyne").is_dir() and not is_object_dir(path)


def sequence_label(bin_path: str | Path) -> Path | None:
    """Where a SemanticKITTI sequence keeps a .bin's labels (SS/labels/x.label) when the scan
    sits in one (SS/velodyne/x.bin, SS a two-digit id or holding labels/); None for a scan
    outside any sequence, which may be unlabelled (a bare KITTI .bin)."""
    p = Path(bin_path)
    folder = p.parent.parent
    if p.parent.name != "velodyne" or is_object_dir(folder):
        return None
    if SEQUENCE_ID.fullmatch(folder.name) or (folder / "labels").is_dir():
        return folder / "labels" / f"{p.stem}.label"
    return None


def sequence_dirs(path: Path) -> dict[str, Path] | None:
    """id -> folder of the sequences under a SemanticKITTI root (holding sequences/) or a
    sequences/ folder, sorted by id; None when `path` is neither."""
    if not path.is_dir():
        return None
    folder = path / "sequences" if (path / "sequences").is_dir() else path
    found = {d.name: d for d in sorted(folder.iterdir())
             if d.is_dir() and SEQUENCE_ID.fullmatch(d.name) and is_sequence_dir(d)}
    return found or None


def available_sequences(paths: list[str]) -> list[str]:
    """The sequence ids found under the SemanticKITTI roots and sequences/ folders named."""
    ids: set[str] = set()
    for p in map(Path, paths):
        if not is_sequence_dir(p):
            ids.update(sequence_dirs(p) or {})
    return sorted(ids)


def real_scans(paths: list[str], sequences: list[str] | None = None
               ) -> list[tuple[str, Path, Path | None, str]]:
    """(name, .bin, labels, kind) of every KITTI scan the paths name, in order: .bin files, folders
    of them, SemanticKITTI sequence folders and roots (only `sequences`' ids, when given) and KITTI
    object directories. kind is "semantickitti" (labels: its .label), "object" (labels: its
    label_2 boxes) or "none"; FalsifyError names a path that holds no scan, a file whose size is
    not a KITTI scan's and a .label that does not hold one label a point."""
    for p in map(Path, paths):
        if not p.exists():
            raise FalsifyError(f"{p}: no such file or folder")
    if sequences is not None:
        allowed = available_sequences(paths)
        unknown = [q for q in sequences if q not in allowed]
        if unknown:
            raise FalsifyError(f"sequences {', '.join(unknown)}: not among the SemanticKITTI "
                               f"sequences named ({', '.join(allowed) or 'none'})")
    out: list[tuple[str, Path, Path | None, str]] = []
    for p in map(Path, paths):
        if p.is_file():
            if p.suffix != ".bin":
                raise FalsifyError(f"{p}: expected a KITTI .bin scan (N x 4 float32)")
            out.append(_real_scan(p))
        elif is_object_dir(p):
            bins = sorted((p / "velodyne").glob("*.bin"))
            if not bins:
                raise FalsifyError(f"{p / 'velodyne'}: no .bin frames in this KITTI object "
                                   "directory")
            out.extend(_real_scan(f) for f in bins)
        elif is_sequence_dir(p):
            out.extend(_real_scan(f) for f in sequence_files(p))
        elif (found := sequence_dirs(p)) is not None:
            for sid, d in found.items():
                if sequences is None or sid in sequences:
                    out.extend(_real_scan(f) for f in sequence_files(d))
        else:
            files = sorted(p.glob("*.bin"))
            if not files:
                raise FalsifyError(f"{p}: no .bin scans here, and not a SemanticKITTI root, "
                                   "sequences/ or sequence folder nor a KITTI object directory")
            out.extend(_real_scan(f) for f in files)
    return out


def _real_scan(path: Path) -> tuple[str, Path, Path | None, str]:
    """A .bin's name (sequence/stem, or folder/stem) and its labels: a SemanticKITTI .label beside
    it or in ../labels/, else the label_2 boxes of the object directory it sits in, else none."""
    folder = path.parent.parent if path.parent.name == "velodyne" else path.parent
    name = f"{folder.name}/{path.stem}" if folder.name else path.stem
    size = path.stat().st_size
    if size == 0 or size % 16:
        raise FalsifyError(f"{path}: {size} bytes is not a KITTI scan (N x 4 float32: x, y, z, "
                           "remission; N > 0)")
    label = label_file(path)
    if label is not None:
        if label.stat().st_size != size // 4:
            raise FalsifyError(f"{label}: {label.stat().st_size // 4} labels for {size // 16} "
                               f"points in {path.name} (a .label holds one uint32 a point)")
        return name, path, label, "semantickitti"
    if path.parent.name == "velodyne" and is_object_dir(folder):
        for need in (folder / "label_2" / f"{path.stem}.txt",
                     folder / "calib" / f"{path.stem}.txt"):
            if not need.is_file():
                raise FalsifyError(f"{need}: missing (a KITTI object frame's boxes need its "
                                   "label_2/ and calib/ files of the same name)")
        return name, path, folder / "label_2" / f"{path.stem}.txt", "object"
    return name, path, None, "none"


def sequence_files(folder: Path) -> list[Path]:
    """A sequence's .bin scans, sorted; FalsifyError naming its velodyne/ when it holds none."""
    files = sorted((folder / "velodyne").glob("*.bin"))
    if not files:
        raise FalsifyError(f"{folder / 'velodyne'}: no .bin scans in this sequence")
    return files


def scans_per_folder(found: list[tuple[str, Path, Path | None, str]]) -> dict[Path, int]:
    """How many of the scans found each folder of scans (a sequence's velodyne/, say) holds."""
    counts: dict[Path, int] = {}
    for _, path, _, _ in found:
        counts[path.parent] = counts.get(path.parent, 0) + 1
    return counts


def evenly_per_folder(found: list[tuple[str, Path, Path | None, str]], k: int
                      ) -> list[tuple[str, Path, Path | None, str]]:
    """At most `k` scans of each folder (a sequence's velodyne/, say), evenly spaced from its
    first to its last in file order, so a config can name a whole data set and stay small."""
    by_folder: dict[Path, list[int]] = {}
    for i, (_, path, _, _) in enumerate(found):
        by_folder.setdefault(path.parent, []).append(i)
    keep: set[int] = set()
    for idx in by_folder.values():
        n = len(idx)
        picks = {idx[0]} if k == 1 else {idx[round(j * (n - 1) / (k - 1))] for j in range(k)}
        keep.update(idx if n <= k else picks)
    return [f for i, f in enumerate(found) if i in keep]
