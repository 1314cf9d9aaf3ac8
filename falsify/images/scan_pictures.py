"""Pictures of a scan: the range image coloured by class and a bird's-eye view, as RGB arrays
(falsify.images.png encodes them)."""

from __future__ import annotations

import numpy as np

# unknown (grey, shaded by range), car, pedestrian, cyclist
CLASS_RGB = np.array([[150, 150, 150], [230, 60, 50], [50, 120, 230], [240, 190, 30]], np.uint8)
EMPTY_RGB = np.array([18, 18, 24], np.uint8)


def range_image_rgb(image: np.ndarray, row_scale: int = 3) -> np.ndarray:
    """(H·row_scale, W, 3) uint8: classes in colour, unknown shaded by range, empty pixels dark."""
    valid = image[..., 4] > 0
    cls = image[..., 5].astype(np.int64).clip(0, 3)
    rgb = CLASS_RGB[cls].astype(np.float32)
    shade = 1.0 - np.clip(image[..., 4] / 80.0, 0.0, 0.75)
    rgb[cls == 0] *= shade[cls == 0, None]
    rgb[~valid] = EMPTY_RGB
    return np.repeat(rgb.astype(np.uint8), row_scale, axis=0)


def bev_rgb(image: np.ndarray, size: int = 256, ahead: float = 40.0,
            side: float = 20.0) -> np.ndarray:
    """(size, size, 3) uint8 top view of the points, sensor at the bottom centre, forward up."""
    out = np.empty((size, size, 3), np.uint8)
    out[:] = EMPTY_RGB
    m = image[..., 4] > 0
    pts = image[m]
    order = np.argsort(pts[:, 5], kind="stable")  # draw labelled classes last, on top
    pts = pts[order]
    col = ((pts[:, 1] * -1 + side) / (2 * side) * size).astype(np.int64)
    row = ((ahead - pts[:, 0]) / ahead * size).astype(np.int64)
    ok = (col >= 0) & (col < size) & (row >= 0) & (row < size)
    cls = pts[ok, 5].astype(np.int64).clip(0, 3)
    out[row[ok], col[ok]] = CLASS_RGB[cls]
    out[size - 3:, size // 2 - 2:size // 2 + 2] = (255, 255, 255)  # the sensor
    return out


def scan_picture(image: np.ndarray) -> np.ndarray:
    """The range image over a bird's-eye view, one picture as wide as the range image."""
    top = range_image_rgb(image)
    width = top.shape[1]
    bev = bev_rgb(image, size=min(width, 512))
    pad = np.zeros((bev.shape[0], width, 3), np.uint8)
    pad[:] = EMPTY_RGB
    x0 = (width - bev.shape[1]) // 2
    pad[:, x0:x0 + bev.shape[1]] = bev
    gap = np.full((4, width, 3), 255, np.uint8)
    return np.concatenate([top, gap, pad], axis=0)
