"""KITTI's 3D object layout: calib, label_2 and velodyne files, read and written, and the export
of our scenes as `velodyne/*.bin`, `image_2/*.png`, `calib/*.txt`, `label_2/*.txt`.

Label boxes live in the rectified camera-0 frame (x right, y down, z forward): `location` is the
bottom centre of the box, `rotation_y` turns the box's length axis about y (0 = along x). 2D
boxes and P matrices use KITTI's pixel convention (pixel centres on integers).

Box geometry lives here too: which Velodyne points lie inside a label's 3D box (tested in the
rectified frame, through `KittiCalib.velo_to_rect`) and which project into an image rectangle.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from falsify.data.velodyne import read_bin
from falsify.errors import FalsifyError
from falsify.fileio import read_text
from falsify.sensor.calibration import KITTI_PIXEL_SHIFT, KittiCalib

TYPES = ("Car", "Van", "Truck", "Pedestrian", "Person_sitting", "Cyclist", "Tram", "Misc",
         "DontCare")
CLASS_TYPE = {1: "Car", 2: "Pedestrian", 3: "Cyclist"}
_CALIB_KEYS = ("P0", "P1", "P2", "P3", "R0_rect", "Tr_velo_to_cam")


# -- calib ------------------------------------------------------------------------------------
def read_calib(path: str | Path) -> KittiCalib:
    """Parse a KITTI object calib file; a missing or malformed entry names the key and file."""
    text = read_text(path, "calib")
    rows: dict[str, np.ndarray] = {}
    for line in text.splitlines():
        if ":" not in line:
            continue
        key, _, values = line.partition(":")
        try:
            rows[key.strip()] = np.array([float(v) for v in values.split()])
        except ValueError:
            raise FalsifyError(f"{path}: {key.strip()}: not a list of numbers") from None
    sizes = {"R0_rect": 9, "Tr_velo_to_cam": 12}
    for key in _CALIB_KEYS:
        want = sizes.get(key, 12)
        if key not in rows:
            raise FalsifyError(f"{path}: missing {key}; a KITTI object calib holds "
                               f"{', '.join(_CALIB_KEYS)}")
        if rows[key].size != want or not np.isfinite(rows[key]).all():
            raise FalsifyError(f"{path}: {key} has {rows[key].size} values, expected {want} "
                               "finite numbers")
    imu = rows.get("Tr_imu_to_velo")
    return KittiCalib(tuple(rows[f"P{k}"].reshape(3, 4) for k in range(4)),
                      rows["R0_rect"].reshape(3, 3), rows["Tr_velo_to_cam"].reshape(3, 4),
                      None if imu is None or imu.size != 12 else imu.reshape(3, 4))


def format_calib(calib: KittiCalib) -> str:
    """A KITTI object calib file (the devkit's P0..P3, R0_rect, Tr_velo_to_cam, Tr_imu_to_velo
    lines, %e numbers), with 17 significant digits so read_calib gets the very float64 back:
    KITTI's own 7 digits, or the 13 written before, moved kitti-rig's Tr by up to 5e-14."""
    def row(a: np.ndarray) -> str:
        return " ".join(f"{v:.16e}" for v in np.asarray(a, dtype=np.float64).ravel())
    lines = [f"P{k}: {row(calib.P[k])}" for k in range(4)]
    lines += [f"R0_rect: {row(calib.R0_rect)}", f"Tr_velo_to_cam: {row(calib.Tr_velo_to_cam)}"]
    imu = calib.Tr_imu_to_velo if calib.Tr_imu_to_velo is not None else np.eye(3, 4)
    lines.append(f"Tr_imu_to_velo: {row(imu)}")
    return "\n".join(lines) + "\n"


# -- labels -----------------------------------------------------------------------------------
@dataclass(frozen=True)
class KittiObject:
    """One label_2 line."""

    type: str
    truncated: float
    occluded: int
    alpha: float
    box2d: tuple[float, float, float, float]  # left, top, right, bottom (pixels)
    dimensions: tuple[float, float, float]    # height, width, length (m)
    location: tuple[float, float, float]      # bottom centre, rectified camera frame (m)
    rotation_y: float

    @property
    def has_3d(self) -> bool:
        """False for DontCare lines, whose dimensions are -1: only an image region."""
        return min(self.dimensions) > 0

    def line(self) -> str:
        b, d, p = self.box2d, self.dimensions, self.location
        return (f"{self.type} {self.truncated:.2f} {self.occluded:d} {self.alpha:.2f} "
                f"{b[0]:.2f} {b[1]:.2f} {b[2]:.2f} {b[3]:.2f} {d[0]:.2f} {d[1]:.2f} {d[2]:.2f} "
                f"{p[0]:.2f} {p[1]:.2f} {p[2]:.2f} {self.rotation_y:.2f}")

    def corners(self) -> np.ndarray:
        """(8, 3) box corners in the rectified camera frame."""
        h, w, length = self.dimensions
        x = np.array([1, 1, -1, -1, 1, 1, -1, -1]) * length / 2
        y = np.array([0, 0, 0, 0, -1, -1, -1, -1]) * h
        z = np.array([1, -1, -1, 1, 1, -1, -1, 1]) * w / 2
        return np.stack([x, y, z], 1) @ rot_y(self.rotation_y).T + np.asarray(self.location)

    def contains(self, p_rect: np.ndarray) -> np.ndarray:
        """Which rectified-frame points lie inside the 3D box (boundary included)."""
        h, w, length = self.dimensions
        local = (np.asarray(p_rect) - np.asarray(self.location)) @ rot_y(self.rotation_y)
        return ((np.abs(local[:, 0]) <= length / 2) & (local[:, 1] <= 0)
                & (local[:, 1] >= -h) & (np.abs(local[:, 2]) <= w / 2))


def rot_y(ry: float) -> np.ndarray:
    """KITTI's rotation about the camera's y axis."""
    c, s = math.cos(ry), math.sin(ry)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def in_rect(u: np.ndarray, v: np.ndarray, rect: tuple[float, float, float, float]
            ) -> np.ndarray:
    """Which pixel coordinates lie in a (left, top, right, bottom) rectangle, edges included;
    NaN (a point behind the camera) lies in none."""
    left, top, right, bottom = rect
    return (u >= left) & (u <= right) & (v >= top) & (v <= bottom)


def points_in_box(points: np.ndarray, obj: KittiObject, calib: KittiCalib) -> np.ndarray:
    """Bool per Velodyne-frame point: inside the label's 3D box (boundary included)."""
    return obj.contains(calib.velo_to_rect(points))


def points_in_rect(points: np.ndarray, rect: tuple[float, float, float, float],
                   calib: KittiCalib) -> np.ndarray:
    """Bool per Velodyne-frame point: in front of camera 2 and projected (P2) into `rect`; how a
    DontCare region, which has no 3D extent, selects points."""
    u, v, _ = calib.rect_to_image(calib.velo_to_rect(points))
    return in_rect(u, v, rect)


def read_labels(path: str | Path) -> list[KittiObject]:
    """Parse a label_2 file; a bad line names the file, its number and the allowed types."""
    lines = read_text(path, "labels").splitlines()
    out = []
    for k, line in enumerate(lines, 1):
        f = line.split()
        if not f:
            continue
        if f[0] not in TYPES:
            raise FalsifyError(f"{path}:{k}: unknown type {f[0]!r}; allowed: {', '.join(TYPES)}")
        if len(f) not in (15, 16):
            raise FalsifyError(f"{path}:{k}: {len(f)} fields, expected 15 (or 16 with a score)")
        try:
            v = [float(x) for x in f[1:15]]
        except ValueError:
            raise FalsifyError(f"{path}:{k}: fields 2-15 must be numbers") from None
        out.append(KittiObject(f[0], v[0], int(v[1]), v[2], (v[3], v[4], v[5], v[6]),
                               (v[7], v[8], v[9]), (v[10], v[11], v[12]), v[13]))
    return out


def read_velodyne(path: str | Path) -> np.ndarray:
    """(N, 4) float32 x, y, z, reflectance; non-finite rows dropped."""
    pts = read_bin(path)
    return pts[np.isfinite(pts).all(axis=1)]


_FILES = (("velodyne", "bin"), ("calib", "txt"), ("label_2", "txt"), ("image_2", "png"))


def frames(directory: Path) -> list[str]:
    """Frame ids of a KITTI object directory (its velodyne/*.bin), sorted; FalsifyError naming
    the folder or file when one is missing: every frame needs all four files."""
    missing = [d for d, _ in _FILES if not (directory / d).is_dir()]
    if missing:
        raise FalsifyError(f"{directory}: not a KITTI object directory (missing "
                           f"{', '.join(missing)}/; expected velodyne, image_2, calib, label_2)")
    ids = sorted(p.stem for p in (directory / "velodyne").glob("*.bin"))
    if not ids:
        raise FalsifyError(f"{directory}: no velodyne/*.bin frames in this KITTI object "
                           "directory")
    for i in ids:
        for d, ext in _FILES:
            if not (directory / d / f"{i}.{ext}").is_file():
                raise FalsifyError(f"{directory / d / f'{i}.{ext}'}: missing (a KITTI object "
                                   "frame needs velodyne/, calib/, label_2/ and image_2/ files "
                                   "of the same name)")
    check_labels_have_scans(directory)
    return ids


def check_labels_have_scans(directory: Path) -> None:
    """FalsifyError naming the label_2/*.txt of an object directory whose velodyne/*.bin is
    missing: their boxes would silently go unscored."""
    orphans = sorted(p for p in (directory / "label_2").glob("*.txt")
                     if not (directory / "velodyne" / f"{p.stem}.bin").is_file())
    if orphans:
        more = f" and {len(orphans) - 3} more" if len(orphans) > 3 else ""
        raise FalsifyError(f"{', '.join(map(str, orphans[:3]))}{more}: labels without a scan "
                           f"(no velodyne/{orphans[0].stem}.bin); every labelled frame needs "
                           "its velodyne/ .bin of the same name")


# -- our scenes as KITTI objects ---------------------------------------------------------------
@dataclass(frozen=True)
class Box3D:
    """An object's box in the LiDAR frame: bottom centre, size and heading (rad, from +x)."""

    cls: int
    instance: int
    centre: np.ndarray   # (3,) bottom centre
    length: float
    width: float
    height: float
    heading: float


def object_label(box: Box3D, calib: KittiCalib, visible: tuple[int, int, int, int] | None,
                 visible_px: int, unoccluded_px: int, size: tuple[int, int]) -> KittiObject:
    """A label_2 line for a box seen through `calib` (which must have R0_rect = I, i.e. ours).

    `visible` is the (col0, row0, col1, row1) pixel range the object covers in the image."""
    tr = calib.Tr_velo_to_cam
    loc = tr[:, :3] @ box.centre + tr[:, 3]
    fwd = tr[:, :3] @ np.array([math.cos(box.heading), math.sin(box.heading), 0.0])
    ry = math.atan2(-fwd[2], fwd[0])
    alpha = math.remainder(ry - math.atan2(loc[0], loc[2]), 2 * math.pi)
    obj = KittiObject(CLASS_TYPE[box.cls], 0.0, 0, alpha, (0, 0, 0, 0),
                      (box.height, box.width, box.length), tuple(float(v) for v in loc),
                      math.remainder(ry, 2 * math.pi))
    w, h = size
    u, v, _ = calib.rect_to_image(obj.corners())
    truncated = 0.0
    if np.isfinite(u).all():
        area = max((u.max() - u.min()) * (v.max() - v.min()), 1e-9)
        cu = np.clip(u, -0.5, w - 0.5)
        cv = np.clip(v, -0.5, h - 0.5)
        truncated = float(np.clip(1 - (cu.max() - cu.min()) * (cv.max() - cv.min()) / area,
                                  0, 1))
    else:
        truncated = 1.0
    hidden = 1.0 - visible_px / max(unoccluded_px, 1)
    occluded = 0 if hidden < 0.1 else (1 if hidden < 0.5 else 2)
    c0, r0, c1, r1 = visible if visible is not None else (0, 0, -1, -1)
    # the pixels' outer edges, clipped to the image as the devkit's 0-based pixel indices:
    # KITTI's labels keep boxes within [0, W - 1] x [0, H - 1] (a truncated car's left is 0.00,
    # its bottom 374.00), never -0.50 or 1241.50
    box2d = (max(c0 - KITTI_PIXEL_SHIFT, 0.0), max(r0 - KITTI_PIXEL_SHIFT, 0.0),
             min(c1 + KITTI_PIXEL_SHIFT, w - 1.0), min(r1 + KITTI_PIXEL_SHIFT, h - 1.0))
    return KittiObject(obj.type, round(truncated, 2), occluded, alpha, box2d, obj.dimensions,
                       obj.location, obj.rotation_y)


def oriented_box(vertices: np.ndarray, heading: float | None = None
                 ) -> tuple[np.ndarray, float, float, float, float]:
    """Bottom centre, length, width, height and heading of an object's vertices: along
    `heading` (rad, where the object faces) when known, else along the footprint's principal
    axis, whose sign is arbitrary (a box alike, but rotation_y and alpha off by 180 degrees)."""
    xy = vertices[:, :2]
    c = xy.mean(axis=0)
    d = xy - c
    if heading is None:
        _, vec = np.linalg.eigh(d.T @ d)
        ax = vec[:, 1]
    else:
        ax = np.array([math.cos(heading), math.sin(heading)])
    perp = np.array([-ax[1], ax[0]])
    a, b = d @ ax, d @ perp
    centre = c + (a.max() + a.min()) / 2 * ax + (b.max() + b.min()) / 2 * perp
    z0, z1 = float(vertices[:, 2].min()), float(vertices[:, 2].max())
    return (np.array([centre[0], centre[1], z0]), float(a.max() - a.min()),
            float(b.max() - b.min()), z1 - z0, math.atan2(ax[1], ax[0]))
