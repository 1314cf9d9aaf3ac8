"""Drawing on camera images: LiDAR points as dots coloured by depth or by a flag, and 2D boxes."""

from __future__ import annotations

import numpy as np

# A short perceptual ramp (near = yellow, far = purple), viridis-like, for depth-coloured dots.
_RAMP = np.array([[253, 231, 37], [94, 201, 98], [33, 145, 140], [59, 82, 139], [68, 1, 84]],
                 np.float64)
INSIDE_RGB = (0, 255, 60)
OUTSIDE_RGB = (255, 0, 255)
BOX_RGB = (255, 210, 0)
DONTCARE_RGB = (150, 150, 150)


def depth_colours(depth: np.ndarray, near: float = 3.0, far: float = 60.0) -> np.ndarray:
    """(N, 3) uint8 colours for depths (metres), near yellow to far purple."""
    t = np.clip((np.asarray(depth, np.float64) - near) / (far - near), 0.0, 1.0)
    x = t * (len(_RAMP) - 1)
    k = np.minimum(x.astype(np.int64), len(_RAMP) - 2)
    f = (x - k)[:, None]
    return (_RAMP[k] * (1 - f) + _RAMP[k + 1] * f + 0.5).astype(np.uint8)


def draw_points(rgb: np.ndarray, col: np.ndarray, row: np.ndarray, colours,
                size: int = 2) -> np.ndarray:
    """Draw size×size dots (top-left at each pixel) in place; far-to-near order is the caller's."""
    h, w, _ = rgb.shape
    colours = np.broadcast_to(np.asarray(colours, np.uint8), (len(col), 3))
    for dr in range(size):
        for dc in range(size):
            r, c = row + dr, col + dc
            ok = (r >= 0) & (r < h) & (c >= 0) & (c < w)
            rgb[r[ok], c[ok]] = colours[ok]
    return rgb


def draw_box(rgb: np.ndarray, box: tuple[float, float, float, float], colour,
             width: int = 2) -> np.ndarray:
    """Outline a (left, top, right, bottom) pixel box in place, clipped to the image."""
    h, w, _ = rgb.shape
    left, top, right, bottom = (int(round(v)) for v in box)
    left, right = max(0, left), min(w - 1, right)
    top, bottom = max(0, top), min(h - 1, bottom)
    if left > right or top > bottom:
        return rgb
    c = np.asarray(colour, np.uint8)
    rgb[top:top + width, left:right + 1] = c
    rgb[max(top, bottom - width + 1):bottom + 1, left:right + 1] = c
    rgb[top:bottom + 1, left:left + width] = c
    rgb[top:bottom + 1, max(left, right - width + 1):right + 1] = c
    return rgb
