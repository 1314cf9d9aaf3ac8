"""Fit the HDL-64E's ring geometry on the geometry of KITTI's object frames.

Run: ``falsify fit-rings $KITTI_OBJECT/velodyne/*.bin --json``. Only
the points are used (never labels), and only the object frames: the SqueezeSeg-layout and
SemanticKITTI scans are evaluation data.

A real HDL-64E's lasers do not fire from the Velodyne frame's origin: ring k fires from dz_k above
it at elevation theta_k, so a return at horizontal range r has z = dz_k + r tan(theta_k) exactly,
and is seen from the origin about dz_k / r above theta_k. Per ring, over every point beyond
MIN_RANGE_M of all frames (rings from KITTI's storage order, `falsify.kitti.kitti_rows`), least
squares of z on r gives theta_k and dz_k; the residual of the elevation seen from the origin
says how well one origin per ring explains the points. These are the `elevations_deg` and
`ring_offsets_m` of a sensor preset.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from falsify.data.velodyne import KITTI_RINGS, kitti_rows, read_bin
from falsify.errors import FalsifyError
from falsify.sensor.lidar import load_sensor

MIN_RANGE_M = 2.0     # nearer points are the ego car's body and its shadow's edge
MIN_POINTS = 50       # a ring needs this many points for a fit
MIN_SPREAD_M = 0.5    # and their horizontal ranges this far apart (else dz and theta trade)


@dataclass(frozen=True)
class RingFit:
    """One ring: elevation theta (deg), origin height dz (m), residual sd (deg), points."""

    ring: int
    theta_deg: float
    dz_m: float
    residual_deg: float
    points: int


def fit_rings(points: np.ndarray, rings: np.ndarray, n_rings: int) -> list[RingFit]:
    """Per ring, theta and dz from (N, 3) sensor-frame points and each point's ring."""
    r = np.hypot(points[:, 0], points[:, 1]).astype(np.float64)
    z = points[:, 2].astype(np.float64)
    out = []
    for k in range(n_rings):
        m = (rings == k) & (r > MIN_RANGE_M) & np.isfinite(z)
        if m.sum() < MIN_POINTS:
            raise FalsifyError(f"ring {k}: {int(m.sum())} points beyond {MIN_RANGE_M:g} m, "
                               f"fewer than the {MIN_POINTS} a fit needs")
        if np.ptp(r[m]) < MIN_SPREAD_M:
            raise FalsifyError(f"ring {k}: its points span {np.ptp(r[m]):.2f} m of range; the "
                               "fit needs them at different ranges")
        a = np.c_[np.ones(int(m.sum())), r[m]]
        (dz, slope), *_ = np.linalg.lstsq(a, z[m], rcond=None)
        resid = np.arctan2(z[m], r[m]) - np.arctan2(a @ [dz, slope], r[m])
        out.append(RingFit(k, round(float(np.degrees(np.arctan(slope))), 4), round(float(dz), 4),
                           round(float(np.degrees(resid.std())), 5), int(m.sum())))
    return out


def fit(paths: list[Path]) -> list[RingFit]:
    """The ring fit over KITTI .bin frames (each must hold KITTI's ring order)."""
    sensor = load_sensor("kitti-hdl64e-360")
    pts, rings = [], []
    for path in paths:
        p = read_bin(path)
        p = p[np.isfinite(p).all(axis=1)]
        ring = kitti_rows(sensor, p)
        if ring is None:
            raise FalsifyError(f"{path}: not in KITTI's ring order; the fit needs each point's "
                               "laser ring")
        pts.append(p[:, :3])
        rings.append(ring)
    return fit_rings(np.concatenate(pts), np.concatenate(rings), KITTI_RINGS)
