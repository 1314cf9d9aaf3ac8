"""A labelled LiDAR scan in SqueezeSeg's range-image layout, and its KITTI file formats.

The range image is H×W×6 float32 with channels x, y, z, intensity, range, label (sensor frame,
empty pixels zero): exactly the layout of SqueezeSeg's KITTI `.npy` files. KITTI `.bin` holds
N×4 float32 (x, y, z, remission); a SemanticKITTI `.label` holds uint32 (instance << 16 | class).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from falsify.errors import FalsifyError
from falsify.sensor import Sensor

CHANNELS = ("x", "y", "z", "intensity", "range", "label")
# Our classes as SemanticKITTI ids when writing .label files (unknown -> 0 "unlabeled").
TO_SEMANTICKITTI = np.array([0, 10, 30, 31], dtype=np.uint32)
# SemanticKITTI ids read as our classes (moving variants too); anything else is unknown.
FROM_SEMANTICKITTI = {10: 1, 252: 1, 30: 2, 254: 2, 31: 3, 253: 3, 32: 3, 255: 3}


@dataclass(frozen=True)
class Scan:
    """One scan: the H×W×6 range image plus the per-pixel instance id."""

    image: np.ndarray      # (H, W, 6) float32
    instance: np.ndarray   # (H, W) int32, 0 where no instance

    @property
    def valid(self) -> np.ndarray:
        return self.image[..., 4] > 0

    @property
    def label(self) -> np.ndarray:
        return self.image[..., 5].astype(np.uint8)

    @property
    def points(self) -> np.ndarray:
        """(N, 7) float32 rows x, y, z, intensity, range, class, instance of valid pixels."""
        m = self.valid
        return np.concatenate([self.image[m], self.instance[m][:, None].astype(np.float32)], 1)

    def count(self, cls: int) -> int:
        return int((self.valid & (self.image[..., 5] == cls)).sum())

    def to_kitti(self, bin_path: str | Path, label_path: str | Path) -> None:
        """Write the valid points as KITTI .bin and SemanticKITTI-style .label."""
        m = self.valid
        self.image[m][:, :4].astype(np.float32).tofile(bin_path)
        cls = self.image[m][:, 5].astype(np.int64)
        inst = self.instance[m].astype(np.uint32) & 0xFFFF
        ((inst << 16) | TO_SEMANTICKITTI[cls]).astype(np.uint32).tofile(label_path)


def image_from_points(sensor: Sensor, points: np.ndarray, cls: np.ndarray,
                      instance: np.ndarray, intensity: np.ndarray | None = None) -> Scan:
    """Project sensor-frame points into the sensor's range image; the nearest point wins a pixel."""
    points = np.asarray(points, dtype=np.float64)
    rng = np.linalg.norm(points, axis=1)
    row, col, inside = sensor.pixel_of(points)
    inside &= rng <= sensor.max_range
    order = np.argsort(-rng[inside], kind="stable")  # far first, so near points overwrite
    idx = np.flatnonzero(inside)[order]
    image = np.zeros((*sensor.shape, 6), dtype=np.float32)
    inst = np.zeros(sensor.shape, dtype=np.int32)
    r, c = row[idx], col[idx]
    image[r, c, 0:3] = points[idx]
    image[r, c, 3] = 0.0 if intensity is None else intensity[idx]
    image[r, c, 4] = rng[idx]
    image[r, c, 5] = cls[idx]
    inst[r, c] = instance[idx]
    return Scan(image, inst)


def read_kitti(bin_path: str | Path, label_path: str | Path | None,
               sensor: Sensor) -> Scan:
    """Read a KITTI .bin (+ SemanticKITTI .label) and project it with `sensor`'s layout."""
    bin_path = Path(bin_path)
    try:
        raw = np.fromfile(bin_path, dtype=np.float32)
    except OSError as exc:
        raise FalsifyError(f"{bin_path}: cannot read ({exc.strerror})") from None
    if raw.size % 4:
        raise FalsifyError(f"{bin_path}: size is not a multiple of 4 float32 (x, y, z, remission)")
    pts = raw.reshape(-1, 4)
    cls = np.zeros(len(pts), dtype=np.uint8)
    inst = np.zeros(len(pts), dtype=np.int32)
    if label_path is not None:
        label_path = Path(label_path)
        try:
            lab = np.fromfile(label_path, dtype=np.uint32)
        except OSError as exc:
            raise FalsifyError(f"{label_path}: cannot read ({exc.strerror})") from None
        if len(lab) != len(pts):
            raise FalsifyError(f"{label_path}: {len(lab)} labels for {len(pts)} points in "
                               f"{bin_path.name}")
        sem = lab & 0xFFFF
        lut = np.zeros(max(int(sem.max(initial=0)) + 1, 256), dtype=np.uint8)
        for k, v in FROM_SEMANTICKITTI.items():
            lut[k] = v
        cls = lut[sem]
        inst = (lab >> 16).astype(np.int32)
    finite = np.isfinite(pts).all(axis=1)
    return image_from_points(sensor, pts[finite, :3], cls[finite], inst[finite],
                             intensity=pts[finite, 3])


def load_scan_npy(path: str | Path) -> np.ndarray:
    """Load an H×W×6 range image (ours or SqueezeSeg's KITTI files), checking shape and values."""
    path = Path(path)
    try:
        arr = np.load(path, allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise FalsifyError(f"{path}: not a readable .npy range image ({exc})") from None
    if arr.ndim != 3 or arr.shape[2] != 6:
        raise FalsifyError(f"{path}: shape {arr.shape}, expected (H, W, 6) with channels "
                           f"{', '.join(CHANNELS)}")
    arr = arr.astype(np.float32, copy=False)
    if not np.isfinite(arr).all():
        raise FalsifyError(f"{path}: contains NaN or inf")
    return arr
