"""Plausible range images without a scene: a road, walls and car-like blobs drawn straight into
a 64-row image. Enough for parity tests, int8 calibration and speed figures; not training data."""

from __future__ import annotations

import numpy as np


def plausible_scans(n: int, H: int = 64, W: int = 512, seed: int = 0) -> np.ndarray:
    """Random but plausible front-view scans (n,H,W,6): ground plane, side walls, box cars.

    Rows span +2 to -24.9 degrees, columns +45 (left) to -45 degrees, like the KITTI layout.
    Used for parity tests, calibration and benchmarks; not a substitute for `falsify dataset`.
    """
    rng = np.random.default_rng(seed)
    elev = np.deg2rad(np.linspace(2.0, -24.9, H))[:, None]
    az = np.deg2rad(45.0 - (np.arange(W) + 0.5) * 90.0 / W)[None, :]
    d = np.stack(np.broadcast_arrays(np.cos(elev) * np.cos(az), np.cos(elev) * np.sin(az),
                                     np.sin(elev) + 0 * az), axis=-1)
    out = np.zeros((n, H, W, 6), np.float32)
    for k in range(n):
        h = 1.73 + rng.normal(0, 0.03)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.where(d[..., 2] < 0, -h / d[..., 2], np.inf)
            for side in (-1, 1):
                wy = side * rng.uniform(6, 15)
                tw = np.where(d[..., 1] * side > 0, wy / d[..., 1], np.inf)
                tw = np.where(tw * d[..., 2] < 6 - h, tw, np.inf)  # walls 6 m high
                t = np.minimum(t, tw)
            label = np.zeros((H, W), np.float32)
            for _ in range(rng.integers(1, 5)):
                c = np.array([rng.uniform(5, 30), rng.uniform(-8, 8), -h + 0.8])
                half = np.array([2.1, 0.9, 0.8]) if rng.random() < 0.5 else np.array(
                    [0.9, 2.1, 0.8])
                t1, t2 = (c - half) / d, (c + half) / d
                tmin = np.nanmax(np.minimum(t1, t2), axis=-1)
                tmax = np.nanmin(np.maximum(t1, t2), axis=-1)
                hit = (tmax >= tmin) & (tmin > 0) & (tmin < t)
                t = np.where(hit, tmin, t)
                label = np.where(hit, 1.0, label)
        t = t * (1 + rng.normal(0, 0.002, t.shape))
        valid = np.isfinite(t) & (t < 80) & (rng.random(t.shape) > 0.02)
        t = np.where(valid, t, 0.0)
        xyz = d * t[..., None]
        out[k, ..., :3] = xyz
        out[k, ..., 3] = np.where(valid, rng.uniform(0, 0.5, t.shape), 0)
        out[k, ..., 4] = np.linalg.norm(xyz, axis=-1)
        out[k, ..., 5] = np.where(valid, label, 0)
    return out
