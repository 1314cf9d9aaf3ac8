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


# bird's-eye view of a prediction: other points, car found, car missed, false car
HIT_RGB = CLASS_RGB[1]
MISS_RGB = np.array([255, 0, 255], np.uint8)
FALSE_CAR_RGB = np.array([0, 220, 255], np.uint8)


def car_errors_bev_rgb(image: np.ndarray, pred: np.ndarray, size: int = 512,
                       ahead: float = 50.0, side: float = 25.0) -> np.ndarray:
    """(size, size, 3) uint8 top view: other points grey, cars found red, cars missed (label car,
    predicted not) magenta, false cars (predicted car, label not) cyan, errors drawn on top."""
    car, said = image[..., 5] == 1, pred == 1
    code = np.where(car & said, 1, np.where(car, 2, np.where(said, 3, 0)))
    coded = image.copy()
    coded[..., 5] = code
    bev = bev_rgb(coded, size=size, ahead=ahead, side=side)
    # bev_rgb paints exact CLASS_RGB colours (it draws higher codes last): recolour the codes
    out = bev.copy()
    for k, rgb in ((1, HIT_RGB), (2, MISS_RGB), (3, FALSE_CAR_RGB)):
        out[(bev == CLASS_RGB[k]).all(axis=-1)] = rgb
    return out


def prediction_picture(image: np.ndarray, pred: np.ndarray, labelled: bool = True) -> np.ndarray:
    """The range image coloured by label over the same coloured by prediction, then a top view
    of the car errors (of the prediction alone where the scan has no labels), as wide as the
    range image."""
    predicted = image.copy()
    predicted[..., 5] = np.where(image[..., 4] > 0, pred, 0)
    top = np.concatenate([range_image_rgb(image), _gap(image.shape[1]),
                          range_image_rgb(predicted)], axis=0)
    width = top.shape[1]
    size = min(width, 512)
    bev = (car_errors_bev_rgb(image, pred, size=size) if labelled
           else bev_rgb(predicted, size=size, ahead=50.0, side=25.0))
    pad = np.zeros((bev.shape[0], width, 3), np.uint8)
    pad[:] = EMPTY_RGB
    x0 = (width - bev.shape[1]) // 2
    pad[:, x0:x0 + bev.shape[1]] = bev
    return np.concatenate([top, _gap(width), pad], axis=0)


def _gap(width: int) -> np.ndarray:
    return np.full((4, width, 3), 255, np.uint8)
