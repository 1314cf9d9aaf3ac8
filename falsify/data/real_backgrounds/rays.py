"""The sensor's rays as a real scan's image holds them: each pixel's direction, each column's
azimuth, and whether a ray's segment meets a box."""

from __future__ import annotations

import math

import numpy as np

from falsify.sensor.lidar import Sensor


def pixel_directions(sensor: Sensor) -> np.ndarray:
    """(H, W, 3) unit direction of each pixel of the sensor's image: its ray for the ring
    layout; the centre of its bin for RangeNet++'s spherical projection (Milioto et al., IROS
    2019: yaw = pi (1 - 2 (col + 0.5) / W) to the left, pitch = (1 - (row + 0.5) / H) fov +
    fov_down)."""
    if sensor.projection != "spherical":
        return np.array(sensor.directions, dtype=np.float64)
    h, w = sensor.shape
    down = math.radians(sensor.fov_down_deg)
    fov = abs(down) + abs(math.radians(sensor.fov_up_deg))
    pitch = (1.0 - (np.arange(h) + 0.5) / h) * fov - abs(down)
    az = np.pi * (1.0 - 2.0 * (np.arange(w) + 0.5) / w)
    el, az = np.meshgrid(pitch, az, indexing="ij")
    return np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=-1)


def column_azimuths(sensor: Sensor) -> np.ndarray:
    """Each image column's centre azimuth, degrees counter-clockwise from +x."""
    if sensor.projection == "spherical":
        return 180.0 - (np.arange(sensor.columns) + 0.5) * 360.0 / sensor.columns
    return np.asarray(sensor.azimuths_deg)


def meets_box(o: np.ndarray, d: np.ndarray, limit: np.ndarray, lo: np.ndarray,
               hi: np.ndarray) -> np.ndarray:
    """Bool per ray (car frame): the segment from o along d for `limit` metres meets the box
    [lo, hi] (the slab test, Kay and Kajiya, SIGGRAPH 1986: the segment's parameter range
    inside each pair of planes, intersected). A direction component of 0 is taken as 1e-12,
    so a ray parallel to a slab is inside it or not, never NaN."""
    enter = np.zeros(len(d))
    leave = np.asarray(limit, dtype=np.float64).copy()
    for k in range(3):   # one axis at a time: 1-D arrays, no strided reductions
        dk = d[:, k]
        dk = np.where(np.abs(dk) < 1e-12, 1e-12, dk)
        t1 = (lo[k] - o[:, k]) / dk
        t2 = (hi[k] - o[:, k]) / dk
        np.maximum(enter, np.minimum(t1, t2), out=enter)
        np.minimum(leave, np.maximum(t1, t2), out=leave)
    return leave >= enter
