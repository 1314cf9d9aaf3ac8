"""A labelled LiDAR scan in SqueezeSeg's range-image layout, and points projected into one.

The range image is H×W×6 float32 with channels x, y, z, intensity, range, label (sensor frame,
empty pixels zero): exactly the layout of SqueezeSeg's KITTI `.npy` files. Casting a scene into
a scan is scene.py's; reading and writing the files is kitti.py's.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from falsify.sensor.lidar import Sensor

CHANNELS = ("x", "y", "z", "intensity", "range", "label")


@dataclass(frozen=True)
class Scan:
    """One scan: the H×W×6 range image, the per-pixel instance id and, where known, the raw
    SemanticKITTI id per pixel (falsify.semantic; the label channel is its four-class view)."""

    image: np.ndarray      # (H, W, 6) float32
    instance: np.ndarray   # (H, W) int32, 0 where no instance
    semantic: np.ndarray | None = None   # (H, W) uint16 raw SemanticKITTI ids, 0 where empty

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



def image_from_points(sensor: Sensor, points: np.ndarray, cls: np.ndarray,
                      instance: np.ndarray, intensity: np.ndarray | None = None,
                      rows: np.ndarray | None = None,
                      semantic: np.ndarray | None = None) -> Scan:
    """Project sensor-frame points into the sensor's range image; the nearest point wins a pixel.
    `rows` gives each point's row (a laser ring) instead of its elevation's; `semantic` (raw
    SemanticKITTI ids per point) fills the scan's semantic image."""
    points = np.asarray(points, dtype=np.float64)
    ranges = np.linalg.norm(points, axis=1)
    row, col, inside = point_pixels(sensor, points, rows)
    order = np.argsort(-ranges[inside], kind="stable")  # far first, so near points overwrite
    idx = np.flatnonzero(inside)[order]
    image = np.zeros((*sensor.shape, 6), dtype=np.float32)
    inst = np.zeros(sensor.shape, dtype=np.int32)
    r, c = row[idx], col[idx]
    image[r, c, 0:3] = points[idx]
    image[r, c, 3] = 0.0 if intensity is None else intensity[idx]
    image[r, c, 4] = ranges[idx]
    image[r, c, 5] = cls[idx]
    inst[r, c] = instance[idx]
    sem = None
    if semantic is not None:
        sem = np.zeros(sensor.shape, dtype=np.uint16)
        sem[r, c] = np.asarray(semantic)[idx]
    return Scan(image, inst, sem)


def point_pixels(sensor: Sensor, points: np.ndarray, rows: np.ndarray | None = None
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(row, col, inside) of each sensor-frame point in the sensor's image: the pixel
    `image_from_points` may give it, so point-wise scoring reads the prediction there; outside
    the field of view or past the sensor's range a point has none."""
    p = np.asarray(points, dtype=np.float64)
    row, col, inside = sensor.pixel_of(p, rows)
    inside &= np.linalg.norm(p, axis=1) <= sensor.max_range
    return row, col, inside


def project_scan(sensor: Sensor, scan: Scan) -> Scan:
    """A scan cast on `sensor`'s ray grid, stored in its image layout: unchanged for the ring
    layout; for a spherical sensor its valid points re-projected (RangeNet++'s projection, the
    nearest point winning a pixel), so a simulated scan reads as a real one does."""
    if sensor.projection != "spherical":
        return scan
    m = scan.valid
    px = scan.image[m]
    return image_from_points(sensor, px[:, 0:3], px[:, 5], scan.instance[m], intensity=px[:, 3],
                             semantic=None if scan.semantic is None else scan.semantic[m])
