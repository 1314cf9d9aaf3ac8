"""The ground of a real scan: its points bucketed for quick look-ups around a place, which
points a car may stand on, and the plane fitted to them under a car."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

# SemanticKITTI ids a car may stand on: road, parking, sidewalk, other-ground, lane-marking,
# terrain. Unlabeled (0) and outlier (1) are neither ground nor obstacle.
GROUND_IDS = np.array([40, 44, 48, 49, 60, 72])
IGNORED_IDS = np.array([0, 1])
GROUND_MARGIN_M = 1.0    # the ground plane is fitted on points this far around the car
MIN_GROUND_POINTS = 20   # fewer than this around the car: look twice as far (three times)
FIT_POINTS = 1000        # about this many ground points fit a car's plane
MAX_SLOPE = 0.3          # a fitted plane steeper than this (17 degrees) is clamped to it
LOWEST_CELL_M = 1.0      # unlabelled scans: ground = points near their 1 m cell's lowest point
LOWEST_BAND_M = 0.15


@dataclass(frozen=True)
class PointIndex:
    """Points bucketed in CELL_M squares of the ground plane and sorted by square, so the
    points around a place are a few contiguous runs (a car's ground fit and collision test
    read a thousand points, not the scan's hundred thousand)."""

    points: np.ndarray             # (N, 3), sorted by square
    semantic: np.ndarray | None    # (N,) raw SemanticKITTI ids of the points, where known
    keys: np.ndarray               # (N,) each point's square, sorted

    @classmethod
    def of(cls, points: np.ndarray, semantic: np.ndarray | None = None) -> PointIndex:
        keys = _square_keys(points[:, 0], points[:, 1])
        order = np.argsort(keys, kind="stable")
        return cls(np.ascontiguousarray(points[order]),
                   None if semantic is None else semantic[order], keys[order])

    def __len__(self) -> int:
        return len(self.points)

    def near(self, x: float, y: float, reach: float) -> np.ndarray:
        """Indices of the points in the squares that the square of half-side `reach` around
        (x, y) touches (a superset of those within `reach`)."""
        ix = np.arange(math.floor((x - reach) / CELL_M), math.floor((x + reach) / CELL_M) + 1)
        lo = np.searchsorted(self.keys, _square_key(ix, math.floor((y - reach) / CELL_M)))
        hi = np.searchsorted(self.keys, _square_key(ix, math.floor((y + reach) / CELL_M)),
                             side="right")
        runs = [np.arange(a, b) for a, b in zip(lo.tolist(), hi.tolist(), strict=True) if b > a]
        return np.concatenate(runs) if runs else np.empty(0, np.int64)

    def subset(self, keep: np.ndarray) -> PointIndex:
        """The points where `keep` is true, still sorted by square."""
        return PointIndex(self.points[keep], None if self.semantic is None
                          else self.semantic[keep], self.keys[keep])


CELL_M = 2.0   # side of PointIndex's squares
_KEY_OFFSET = 1 << 24   # squares of 2 m: keys stay positive and distinct within 33,000 km


def _square_key(ix, iy):
    return (np.asarray(ix, np.int64) + _KEY_OFFSET) * (2 * _KEY_OFFSET) + (iy + _KEY_OFFSET)


def _square_keys(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    return _square_key(np.floor(x / CELL_M).astype(np.int64),
                       np.floor(y / CELL_M).astype(np.int64))



def ground_points(xyz: np.ndarray, semantic: np.ndarray | None) -> np.ndarray:
    """The points a car may stand on: labelled ground where every point is labelled, else each
    1 m cell's lowest points (within LOWEST_BAND_M of its lowest)."""
    if semantic is not None:
        return xyz[np.isin(semantic, GROUND_IDS)]
    _, inv, low = _lowest_cells(xyz)
    return xyz[xyz[:, 2] <= low[inv] + LOWEST_BAND_M]


def fit_ground(ground: PointIndex, x: float, y: float, reach: float, default_z: float
               ) -> tuple[float, float, float]:
    """(z, dz/dx, dz/dy) of the ground plane at (x, y): least squares over the ground points
    within reach + GROUND_MARGIN_M (twice and three times that when too few; every k-th of
    them where there are more than 2 FIT_POINTS, a plane needs no more), refitted once without
    points more than 0.15 m off; flat at `default_z` where none are near."""
    for grow in (1.0, 2.0, 3.0):
        r = (reach + GROUND_MARGIN_M) * grow
        idx = ground.near(x, y, r)
        cand = ground.points[idx[::max(1, len(idx) // FIT_POINTS)]]
        near = cand[(cand[:, 0] - x) ** 2 + (cand[:, 1] - y) ** 2 <= r * r]
        if len(near) >= MIN_GROUND_POINTS:
            break
    else:
        return default_z, 0.0, 0.0
    a = np.column_stack([np.ones(len(near)), near[:, 0] - x, near[:, 1] - y])
    coef = _plane(a, near[:, 2])
    keep = np.abs(a @ coef - near[:, 2]) <= 0.15
    if keep.sum() >= MIN_GROUND_POINTS:
        coef = _plane(a[keep], near[keep, 2])
    gx, gy = (float(np.clip(v, -MAX_SLOPE, MAX_SLOPE)) for v in coef[1:])
    return float(coef[0]), gx, gy


def _plane(a: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Least-squares coefficients of z ~ a (n x 3), by lstsq where the normal equations are
    near singular (points on a line), else by solving them (several times faster)."""
    ata = a.T @ a
    if abs(np.linalg.det(ata)) <= 1e-12 * np.trace(ata) ** 3:
        return np.linalg.lstsq(a, z, rcond=None)[0]
    return np.linalg.solve(ata, a.T @ z)



def lowest_band(cloud: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Bool per point: within LOWEST_BAND_M of the lowest point of the cloud in its
    LOWEST_CELL_M cell (as ground_points picks an unlabelled scan's ground)."""
    uniq, _, low = _lowest_cells(cloud)
    k = _cell_keys(points)
    at = np.clip(np.searchsorted(uniq, k), 0, max(len(uniq) - 1, 0))
    found = (uniq[at] == k) if len(uniq) else np.zeros(len(k), bool)
    return found & (points[:, 2] <= np.where(found, low[at], -np.inf) + LOWEST_BAND_M)


def _cell_keys(p: np.ndarray) -> np.ndarray:
    """Each point's LOWEST_CELL_M cell as one int64 key."""
    cell = np.floor(p[:, :2] / LOWEST_CELL_M).astype(np.int64)
    return (cell[:, 0] << 32) + (cell[:, 1] & 0xFFFFFFFF)


def _lowest_cells(cloud: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The cloud's cells (sorted keys), each point's cell among them, and each cell's lowest z."""
    uniq, inv = np.unique(_cell_keys(cloud), return_inverse=True)
    low = np.full(len(uniq), np.inf)
    np.minimum.at(low, inv, cloud[:, 2])
    return uniq, inv, low
