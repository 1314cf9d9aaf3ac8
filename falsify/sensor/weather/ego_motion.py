"""Ego motion: each column fired at its time in the sweep from where the ego then is (the motion
distortion of a rotating sensor)."""

from __future__ import annotations

import numpy as np

from falsify.rotations import rot_y
from falsify.sensor.lidar import Sensor

KMH = 1.0 / 3.6


def column_times(sensor: Sensor) -> np.ndarray:
    """Column firing times, s: a clockwise sweep (seen from above), t = 0 facing forward."""
    return -sensor.azimuths_deg / (360.0 * sensor.rotation_hz)


def forward_axis(sensor: Sensor) -> np.ndarray:
    """The ego's +x in the sensor frame (the sensor pitched on its mount)."""
    return rot_y(sensor.pitch_deg).T @ np.array([1.0, 0.0, 0.0])


def moving_ranges(dist: np.ndarray, normal: np.ndarray, cos: np.ndarray, speed_kmh: float,
                  column_time: np.ndarray, forward: np.ndarray) -> np.ndarray:
    """Each ray's range fired from where the ego is at its column's time (`column_time`, moving
    along `forward`): the hit surface taken as its plane (point and normal, turned to the
    sensor, from the clear cast), the ray from the moved origin meets it at
    R - n.d / n.u = R + n.d / cos (d: the displacement; grazing hits clipped to 5 |d|)."""
    step = speed_kmh * KMH * column_time                 # (W,) metres along the ego's +x
    nd = (normal @ forward) * step                       # (H, W)
    reach = 5.0 * np.abs(step)
    shift = np.clip(nd / np.maximum(cos, 1e-9), -reach, reach)
    return dist + shift
