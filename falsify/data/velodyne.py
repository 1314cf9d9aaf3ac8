"""KITTI's Velodyne files: a .bin of N×4 float32 (x, y, z, remission) and a SemanticKITTI
.label of uint32 (instance << 16 | raw semantic id), read into and written from Scans.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from falsify.errors import FalsifyError
from falsify.fileio import read_bytes, write_bytes
from falsify.semantic import join_label, kitti4, split_label
from falsify.sensor.lidar import Sensor
from falsify.sensor.scan import Scan, image_from_points

# Our classes as SemanticKITTI ids when writing .label files of scans without semantic ids
# (unknown -> 0 "unlabeled"). Reading maps raw ids back with falsify.semantic.kitti4.
TO_SEMANTICKITTI = np.array([0, 10, 30, 31], dtype=np.uint32)
# The sequence our SemanticKITTI-layout sets are written as (dataset --format semantickitti,
# a run's retraining set with --retrain-format semantickitti).
SEMANTICKITTI_SEQUENCE = "00"


def kitti_arrays(scan: Scan) -> tuple[np.ndarray, np.ndarray]:
    """The valid points as a KITTI .bin holds them ((N, 4) float32 x, y, z, remission) and their
    SemanticKITTI .label values ((N,) uint32): the scan's raw semantic ids where it has them,
    else its classes as SemanticKITTI ids."""
    m = scan.valid
    points = scan.image[m][:, :4].astype(np.float32)
    inst = label_instances(scan.instance[m])
    if scan.semantic is not None:
        sem = scan.semantic[m].astype(np.uint32)
    else:
        sem = TO_SEMANTICKITTI[scan.image[m][:, 5].astype(np.int64)]
    return points, join_label(sem, inst).astype(np.uint32)


def label_instances(instance: np.ndarray) -> np.ndarray:
    """Instance ids as a .label's upper 16 bits hold them (uint32, 0..65535): ids that fit are
    kept; each id above 65535 (inserted cars are 65536 + k, real_backgrounds.INSERTED_INSTANCE)
    gets its own id unused by the scan, the first free ones above the largest kept id, so no
    instance is cut to 0 ("none") or merged with another, as masking the high bits did
    (SemanticKITTI: label = instance << 16 | semantic id, semantic-kitti-api's laserscan.py)."""
    inst = np.asarray(instance).astype(np.int64)
    big = inst > 0xFFFF
    if not big.any():
        return np.clip(inst, 0, None).astype(np.uint32)
    used = np.unique(inst[(inst > 0) & ~big])
    wide = np.unique(inst[big])
    free = np.setdiff1d(np.arange(1, 0x10000), used)
    top = used.max() if len(used) else 0
    free = np.concatenate([free[free > top], free[free <= top]])
    if len(free) < len(wide):
        raise FalsifyError(f"{len(used) + len(wide)} instances in one scan: a SemanticKITTI "
                           ".label holds at most 65535 (16 bits)")
    out = np.clip(inst, 0, None)
    out[big] = free[np.searchsorted(wide, inst[big])]
    return out.astype(np.uint32)


def semantickitti_paths(out: Path, index: int) -> tuple[Path, Path]:
    """Scan `index`'s .bin and .label in SemanticKITTI's layout under `out`:
    sequences/00/velodyne/NNNNNN.bin (float32 x, y, z, remission) and
    sequences/00/labels/NNNNNN.label (uint32 instance << 16 | raw semantic id)."""
    seq = out / "sequences" / SEMANTICKITTI_SEQUENCE
    return seq / "velodyne" / f"{index:06d}.bin", seq / "labels" / f"{index:06d}.label"


def write_kitti(scan: Scan, bin_path: str | Path, label_path: str | Path) -> None:
    """Write the valid points as KITTI .bin and SemanticKITTI .label (`kitti_arrays`), each
    through a temporary file renamed over the path, so no reader takes a cut file for whole."""
    points, labels = kitti_arrays(scan)
    write_bytes(bin_path, points.tobytes())   # atomic: a killed write leaves no short file
    write_bytes(label_path, labels.tobytes())


def fit_frames(paths: list[str | Path], holdout: Sequence[str | Path] = (),
               what: str = "the fit's frames") -> list[Path]:
    """The KITTI .bin frames the paths name (files, or folders of them such as an object
    directory's velodyne/), for the sensor's fits: each readable, non-empty and once only;
    a held-out one (the manifests, $FALSIFY_HOLDOUT, a splits.toml beside the data) is refused."""
    from falsify.data.holdout import check_each_once, check_not_held_out

    out: list[Path] = []
    for p in map(Path, paths):
        folder = p / "velodyne" if (p / "velodyne").is_dir() else p
        if folder.is_dir():
            found = sorted(folder.glob("*.bin"))
            if not found:
                raise FalsifyError(f"{p}: no .bin frames here (give KITTI .bin files, a "
                                   "velodyne/ folder or an object directory)")
            out += found
        elif not p.is_file():
            raise FalsifyError(f"{p}: no such file or folder")
        elif p.suffix != ".bin":
            raise FalsifyError(f"{p}: not a KITTI .bin frame (x, y, z, remission float32)")
        else:
            out.append(p)
    for p in out:
        size = p.stat().st_size
        if size == 0 or size % 16:
            raise FalsifyError(f"{p}: {size} bytes, not N x 4 float32 (x, y, z, remission)")
    check_each_once(out, what)
    check_not_held_out(out, holdout, what)
    return out


def read_bin(path: str | Path) -> np.ndarray:
    """(N, 4) float32 x, y, z, remission of a KITTI .bin as stored (read-only; non-finite rows
    kept, so a .label's rows still line up); FalsifyError naming the file when it is not N x 4."""
    data = read_bytes(path)
    if len(data) % 16:
        raise FalsifyError(f"{path}: size is not a multiple of 4 float32 (x, y, z, remission)")
    return np.frombuffer(data, np.float32).reshape(-1, 4)


KITTI_RINGS = 64
MIN_RING_POINTS = 200  # a ring with fewer points means the file is not in KITTI's ring order


def kitti_rows(sensor: Sensor, points: np.ndarray) -> np.ndarray | None:
    """Each point's laser ring, from KITTI's storage order, for a sensor whose rows are those
    rings (`kitti_rings`); None otherwise, or when the file does not hold that order.

    KITTI stores a scan ring by ring, top laser first, each ring sweeping azimuth upward from the
    front (0°) through the back (±180°) to the front again: 64 wraps from +180° to -180°. So a
    point's ring is the number of wraps before it, less one for the half ring behind the wrap
    (azimuth below 0). A scan cut at the back instead (63 wraps) has its rings between the
    wraps. Azimuths jitter at ±180°: a wrap straight back counts -1. Why not the elevation: a
    laser sits some 0.1-0.2 m off the sensor's origin, so its points' elevation seen from the
    origin moves by up to a degree or two at short range, more than the 0.33° between the upper
    rings; binning by elevation scrambles neighbouring rings (on KITTI's object frames 10-23 %
    of the upper rows' pixels came out empty and as many held two points)."""
    if (not sensor.kitti_rings or sensor.projection != "rings" or sensor.rows != KITTI_RINGS
            or len(points) < 2):
        return None
    p = np.asarray(points, dtype=np.float64)
    az = np.degrees(np.arctan2(p[:, 1], p[:, 0]))
    d = np.diff(az)
    wraps = np.concatenate([[0], np.cumsum((d < -180.0).astype(np.int64)
                                           - (d > 180.0).astype(np.int64))])
    if wraps[-1] == KITTI_RINGS:  # cut at the front (KITTI): each ring wraps once inside
        ring = np.clip(wraps - (az < 0.0), 0, KITTI_RINGS - 1)  # the cut's points either side
    elif wraps[-1] == KITTI_RINGS - 1:  # cut at the back: rings end where they wrap
        ring = wraps
    else:
        return None
    if np.bincount(ring, minlength=KITTI_RINGS).min() < MIN_RING_POINTS:
        return None
    return ring


@dataclass(frozen=True)
class KittiPoints:
    """A .bin's finite points and each one's labels as `read_kitti` projects them: the one
    reading shared by the range image and point-wise scoring."""

    xyz: np.ndarray               # (N, 3) float32, sensor frame
    remission: np.ndarray         # (N,) float32
    cls: np.ndarray               # (N,) uint8 four-class id (falsify.semantic.kitti4)
    instance: np.ndarray          # (N,) int32
    semantic: np.ndarray | None   # (N,) uint16 raw SemanticKITTI ids, None without a .label
    dropped: int = 0              # rows of the file with a non-finite value: never projected

    def project(self, sensor: Sensor, rows: np.ndarray | None = None) -> Scan:
        """The points in `sensor`'s image (`rows`: their laser rings, `kitti_rows`)."""
        return image_from_points(sensor, self.xyz, self.cls, self.instance,
                                 intensity=self.remission, rows=rows, semantic=self.semantic)


def read_kitti_points(bin_path: str | Path, label_path: str | Path | None) -> KittiPoints:
    """The finite points of a KITTI .bin with their SemanticKITTI labels (a .label's lower 16
    bits, its upper 16 the instance); FalsifyError naming a file that does not fit."""
    bin_path = Path(bin_path)
    pts = read_bin(bin_path)
    if len(pts) == 0:
        raise FalsifyError(f"{bin_path}: empty scan (no points)")
    cls = np.zeros(len(pts), dtype=np.uint8)
    inst = np.zeros(len(pts), dtype=np.int32)
    sem = None
    if label_path is not None:
        data = read_bytes(label_path)
        if len(data) % 4:
            raise FalsifyError(f"{label_path}: size is not a multiple of 4 bytes (uint32 "
                               "labels)")
        lab = np.frombuffer(data, np.uint32)
        if len(lab) != len(pts):
            raise FalsifyError(f"{label_path}: {len(lab)} labels for {len(pts)} points in "
                               f"{bin_path.name}")
        sem, high = split_label(lab)
        cls = kitti4(sem)
        inst = high.astype(np.int32)
    finite = np.isfinite(pts).all(axis=1)
    if not finite.any():
        raise FalsifyError(f"{bin_path}: no point with finite x, y, z and remission")
    return KittiPoints(pts[finite, :3], pts[finite, 3], cls[finite], inst[finite],
                       None if sem is None else sem[finite], int((~finite).sum()))


def read_kitti(bin_path: str | Path, label_path: str | Path | None,
               sensor: Sensor) -> Scan:
    """Read a KITTI .bin (+ SemanticKITTI .label) and project it with `sensor`'s layout (rows
    by laser ring where the sensor's rows are KITTI's rings: `kitti_rows`; a spherical sensor
    gives RangeNet++'s projection of the scan, as the SemanticKITTI networks read it)."""
    points = read_kitti_points(bin_path, label_path)
    return points.project(sensor, kitti_rows(sensor, points.xyz))
