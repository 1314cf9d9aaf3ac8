"""Sensor faults: beam_loss, whole rows (lasers) out, drawn at random; beams, a sensor with fewer
lasers, N of the rows kept evenly spaced (rows (k * H) // N: every other one for 32 of 64), the
cross-sensor corruption of Robo3D (Kong et al., ICCV 2023), 64 -> 32 / 16 beams by ring
selection; crosstalk, spurious points from another sensor at random pixels and ranges.
"""

from __future__ import annotations

import numpy as np

from falsify.errors import ConfigError
from falsify.sensor.lidar import Sensor
from falsify.sensor.weather.effects import _BEAMS, _CROSSTALK, Echoes, Effects, stream
from falsify.world.space import Categorical, Continuous, Space


def sensor_faults(s: Sensor, fx: Effects, seed: int, e: Echoes) -> Echoes:
    """Crosstalk points written over the image, then the lost lasers' rows emptied, then the
    rows a sensor with `beams` lasers would not have."""
    r, valid, intensity, cls, inst, sem = (e.r, e.valid, e.intensity, e.cls, e.inst,
                                           e.semantic)
    if fx.crosstalk > 0:
        # Row k: point k's pixel, range and intensity (more points: more rows, same first).
        u = stream(seed, _CROSSTALK).random((fx.crosstalk, 3))
        n_pix = s.rows * s.columns
        pix = np.minimum((u[:, 0] * n_pix).astype(np.int64), n_pix - 1)
        rows, cols = pix // s.columns, pix % s.columns
        r, valid, cls, inst = r.copy(), valid.copy(), cls.copy(), inst.copy()
        # The other sensor's pulse comes at any time in the listening window: any range.
        r[rows, cols] = s.min_range + u[:, 1] * (s.max_range - s.min_range)
        valid[rows, cols] = True
        cls[rows, cols] = 0
        inst[rows, cols] = 0
        if sem is not None:
            sem = sem.copy()
            sem[rows, cols] = 0
        if intensity is not None:
            intensity = intensity.copy()
            intensity[rows, cols] = u[:, 2]
    if fx.beam_loss > 0:
        order = np.argsort(stream(seed, _BEAMS).random(s.rows), kind="stable")
        valid = valid.copy()
        valid[order[:min(fx.beam_loss, s.rows)]] = False
    if 0 < fx.beams < s.rows:
        kept = np.zeros(s.rows, bool)
        kept[kept_rows(s.rows, fx.beams)] = True
        valid = valid & kept[:, None]
    return Echoes(r, valid, intensity, cls, inst, sem)


def check_beams(space: Space, sensor: Sensor) -> None:
    """ConfigError naming dims.beams where a value is neither 0 (all lasers) nor a divisor of
    the sensor's lasers: ring selection (Robo3D's cross-sensor corruption) keeps every k-th."""
    dim = space.dims.get("beams")
    if dim is None:
        return
    rows = sensor.rows
    fixed = isinstance(dim, Continuous) and dim.lo == dim.hi   # `values = [v]` reads as lo = hi
    if not (isinstance(dim, Categorical) or fixed):
        raise ConfigError(f"{space.source}: dims.beams: give values = [...], lasers that divide "
                          f"{sensor.name}'s {rows}; a range lets a search pick ones that do not")
    for v in dim.grid():
        if int(v) and rows % int(v):
            allowed = [d for d in range(1, rows + 1) if rows % d == 0]
            raise ConfigError(f"{space.source}: dims.beams: {int(v)} lasers do not divide "
                              f"{sensor.name}'s {rows}; allowed: 0 (all), "
                              + ", ".join(map(str, allowed)))


def kept_rows(rows: int, beams: int) -> np.ndarray:
    """The rows a sensor of `beams` lasers keeps of `rows`, evenly spaced from the first."""
    return (np.arange(min(beams, rows)) * rows) // min(beams, rows)
