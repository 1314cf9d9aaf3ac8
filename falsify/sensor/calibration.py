"""LiDAR-to-camera calibration: the paper's closed formula and the general pinhole projection.

Frames. The LiDAR (sensor) frame is x forward, y left, z up, as in falsify.sensor.lidar and KITTI's
Velodyne frame. The camera's optical frame is x right, y down, z forward (KITTI, OpenCV).

Pixel coordinates. Here pixel (col, row) spans u in [col, col + 1), v in [row, row + 1), so its
centre is (col + 0.5, row + 0.5) and the image spans [0, W] x [0, H], as in the paper's formula
(i runs from 0 to R_m). KITTI's P matrices put pixel centres on integers; `KittiCalib` keeps that
convention for its own files and converts with `KITTI_PIXEL_SHIFT` where the two meet.

The paper's formula (Yue et al., ICMR 2018, "Automatic Calibration Method") maps a ray with
angles (phi, theta) to pixel (i, j) for a camera whose centre is the LiDAR's and whose optical
axis is the LiDAR's x axis:

    i = (R_m / m) * (f * tan(gamma) * m / n - f / cos(theta) * tan(phi))
    j = (R_n / n) * (f * tan(gamma) + f * tan(theta))

It is exact, and equal to the pinhole projection, when theta is the ray's angle below the
optical axis measured in the vertical plane through that axis (theta = atan2(-z, x); the zenith
angle in that plane is 90 deg + theta) and phi is the ray's angle out of that vertical plane,
positive to the left (phi = atan2(y, hypot(x, z))): then f * tan(theta) = -f z / x and
f * tan(phi) / cos(theta) = f y / x. `paper_angles` computes exactly these. Feeding it the
LiDAR's own azimuth and ring elevation instead is only right on the image's centre lines.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

# LiDAR axes (x fwd, y left, z up) to optical axes (x right, y down, z fwd): rows are the
# optical axes written in LiDAR coordinates.
LIDAR_TO_OPTICAL = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
# u_here = u_kitti + 0.5: KITTI puts the centre of pixel k at k, this module at k + 0.5.
KITTI_PIXEL_SHIFT = 0.5
MIN_DEPTH = 1e-6  # metres in front of the camera below which a point has no pixel


# -- the paper's formula ---------------------------------------------------------------------
@dataclass(frozen=True)
class PaperSetup:
    """The paper's symbols: focal distance f, near plane m x n (same unit as f), resolution
    R_m x R_n pixels and gamma, half the vertical field of view (radians)."""

    f: float
    m: float
    n: float
    res_m: int
    res_n: int

    @property
    def gamma(self) -> float:
        return math.atan(self.n / 2 / self.f)


def paper_pixel(phi: np.ndarray, theta: np.ndarray, s: PaperSetup) -> tuple[np.ndarray,
                                                                               np.ndarray]:
    """The paper's i (column) and j (row), implemented as written."""
    f, m, n, gamma = s.f, s.m, s.n, s.gamma
    i = (s.res_m / m) * (f * np.tan(gamma) * m / n - f / np.cos(theta) * np.tan(phi))
    j = (s.res_n / n) * (f * np.tan(gamma) + f * np.tan(theta))
    return i, j


def paper_angles(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(phi, theta) of LiDAR-frame points for the paper's formula (see the module docstring)."""
    p = np.asarray(points, dtype=np.float64)
    x, y, z = p[..., 0], p[..., 1], p[..., 2]
    return np.arctan2(y, np.hypot(x, z)), np.arctan2(-z, x)


# -- general pinhole with an extrinsic transform ----------------------------------------------
@dataclass(frozen=True)
class Pinhole:
    """Intrinsics in pixels (this module's convention: pixel k spans [k, k + 1))."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    def paper_setup(self, f: float = 1.0) -> PaperSetup:
        """The paper's symbols for this camera; only valid with square pixels and the principal
        point at the image centre (the paper's set-up)."""
        if abs(self.fx - self.fy) > 1e-9 * self.fx or abs(self.cx - self.width / 2) > 1e-9 \
                or abs(self.cy - self.height / 2) > 1e-9:
            raise ValueError("the paper's formula needs square pixels and a centred principal "
                             "point")
        return PaperSetup(f=f, m=f * self.width / self.fx, n=f * self.height / self.fy,
                          res_m=self.width, res_n=self.height)

    def project(self, p_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Optical-frame points to (u, v, depth); points with depth <= MIN_DEPTH get NaN."""
        p = np.asarray(p_cam, dtype=np.float64)
        z = p[..., 2]
        front = z > MIN_DEPTH
        safe = np.where(front, z, 1.0)
        u = np.where(front, self.fx * p[..., 0] / safe + self.cx, np.nan)
        v = np.where(front, self.fy * p[..., 1] / safe + self.cy, np.nan)
        return u, v, z

    def rays(self) -> np.ndarray:
        """(H, W, 3) unit optical-frame directions through the pixel centres."""
        u = np.arange(self.width) + 0.5
        v = np.arange(self.height) + 0.5
        x = (u[None, :] - self.cx) / self.fx
        y = (v[:, None] - self.cy) / self.fy
        d = np.stack(np.broadcast_arrays(x, y, np.ones_like(x * y)), axis=-1)
        return d / np.linalg.norm(d, axis=-1, keepdims=True)


@dataclass(frozen=True, eq=False)
class Extrinsic:
    """p_cam = rotation @ p_lidar + translation (rotation includes LIDAR_TO_OPTICAL and, for a
    rectified KITTI camera, R0_rect)."""

    rotation: np.ndarray  # (3, 3)
    translation: np.ndarray  # (3,)

    @classmethod
    def shared_centre(cls) -> Extrinsic:
        """The paper's set-up: camera centre at the LiDAR's, optical axis along LiDAR x."""
        return cls(LIDAR_TO_OPTICAL.copy(), np.zeros(3))

    def to_camera(self, points: np.ndarray) -> np.ndarray:
        return np.asarray(points, dtype=np.float64) @ self.rotation.T + self.translation

    @property
    def centre(self) -> np.ndarray:
        """The camera centre in the LiDAR frame."""
        return -self.rotation.T @ self.translation


def project_points(points: np.ndarray, intr: Pinhole, ext: Extrinsic
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """LiDAR-frame points to (u, v, depth) with this module's pixel convention."""
    return intr.project(ext.to_camera(points))


def pixel_index(u: np.ndarray, v: np.ndarray, intr: Pinhole
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(col, row, inside) of continuous coordinates; NaN and outside coordinates are not inside."""
    ok = np.isfinite(u) & np.isfinite(v)
    col = np.floor(np.where(ok, u, -1.0)).astype(np.int64)
    row = np.floor(np.where(ok, v, -1.0)).astype(np.int64)
    inside = ok & (col >= 0) & (col < intr.width) & (row >= 0) & (row < intr.height)
    return col, row, inside


# -- KITTI's calibration files ----------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class KittiCalib:
    """One KITTI object calib file: P0..P3 (3x4), R0_rect (3x3), Tr_velo_to_cam (3x4).

    A Velodyne point X projects as P2 · R0_rect · Tr_velo_to_cam · X (KITTI pixel convention)."""

    P: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]
    R0_rect: np.ndarray
    Tr_velo_to_cam: np.ndarray
    Tr_imu_to_velo: np.ndarray | None = None

    @property
    def P2(self) -> np.ndarray:
        return self.P[2]

    def velo_to_rect(self, points: np.ndarray) -> np.ndarray:
        """Velodyne points to the rectified camera-0 frame (where label_2's boxes live)."""
        p = np.asarray(points, dtype=np.float64)[:, :3]
        return (p @ self.Tr_velo_to_cam[:, :3].T + self.Tr_velo_to_cam[:, 3]) @ self.R0_rect.T

    def rect_to_image(self, p_rect: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Rectified points to KITTI pixel coordinates (u, v) and depth; NaN behind camera 2."""
        h = np.asarray(p_rect, dtype=np.float64) @ self.P2[:, :3].T + self.P2[:, 3]
        w = h[:, 2]
        front = w > MIN_DEPTH
        safe = np.where(front, w, 1.0)
        return (np.where(front, h[:, 0] / safe, np.nan), np.where(front, h[:, 1] / safe, np.nan),
                w)

    def camera2(self, width: int, height: int) -> tuple[Pinhole, Extrinsic]:
        """Camera 2 as intrinsics (this module's pixel convention) and a Velodyne extrinsic."""
        k = self.P2[:, :3]
        if abs(k[1, 0]) > 1e-9 or abs(k[2, 0]) > 1e-9 or abs(k[2, 1]) > 1e-9 \
                or abs(k[2, 2] - 1) > 1e-9:
            raise ValueError("P2 is not K [I | t] with an upper-triangular K")
        t2 = np.linalg.solve(k, self.P2[:, 3])
        intr = Pinhole(width, height, float(k[0, 0]), float(k[1, 1]),
                       float(k[0, 2]) + KITTI_PIXEL_SHIFT, float(k[1, 2]) + KITTI_PIXEL_SHIFT)
        rot = self.R0_rect @ self.Tr_velo_to_cam[:, :3]
        trans = self.R0_rect @ self.Tr_velo_to_cam[:, 3] + t2
        return intr, Extrinsic(rot, trans)

    @classmethod
    def for_camera(cls, intr: Pinhole, ext: Extrinsic) -> KittiCalib:
        """A calib file for our camera: rectification identity, camera 2 = camera 0."""
        k = np.array([[intr.fx, 0.0, intr.cx - KITTI_PIXEL_SHIFT, 0.0],
                      [0.0, intr.fy, intr.cy - KITTI_PIXEL_SHIFT, 0.0], [0.0, 0.0, 1.0, 0.0]])
        tr = np.concatenate([ext.rotation, ext.translation[:, None]], axis=1)
        return cls((k, k.copy(), k.copy(), k.copy()), np.eye(3), tr, None)
