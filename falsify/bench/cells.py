"""`bench cells`: a run's cell maps (the mean score per x, y cell, and per every other pair of
dims that vary), as `grid`, `report` and `gate` compute them, against the naive path of one
pandas group per cell, on the same rows; the maps must be the same bytes.

The rows are drawn, not scored: the maps' cost depends on how many rows and cells there are,
not on what the network said, and a run of 50,000 scored samples takes most of an hour on two
cores. Rows are placed as a search places them (uniform over each continuous dim's bounds, a
categorical dim's values drawn alike), with undefined and invalid rows among them.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from falsify.bench.machine import machine
from falsify.jobs.run import extra_map_pairs
from falsify.results.metrics import Status
from falsify.results.miou_maps import CellMap, _match, axis_values, cell_mean, miou_map, snap
from falsify.world.space import Categorical, Space, load_space

UNDEFINED_SHARE = 0.10   # rows whose IoU is undefined (no car in label or prediction)
INVALID_SHARE = 0.05     # rows of scenes that cannot exist


def per_group_map(frame: pd.DataFrame, space: Space, a: str = "x", b: str = "y",
                  column: str = "car_iou") -> CellMap:
    """The naive path: one pandas group per cell, each matched to its axis values in turn."""
    a_vals, b_vals = axis_values(space, a), axis_values(space, b)
    shape = (len(b_vals), len(a_vals))
    miou = np.full(shape, np.nan)
    samples, undefined, invalid = (np.zeros(shape, np.int64) for _ in range(3))
    ai = {v: i for i, v in enumerate(a_vals)}
    bi = {v: j for j, v in enumerate(b_vals)}
    sa, sb = snap(frame[a], space, a), snap(frame[b], space, b)
    for (av, bv), grp in frame.groupby([sa, sb], sort=True):
        i, j = ai.get(_match(av, a_vals)), bi.get(_match(bv, b_vals))
        if i is None or j is None:
            continue
        scored = grp[grp["status"] != Status.INVALID]
        values = scored[column].astype(float).dropna()
        samples[j, i] = len(values)
        undefined[j, i] = len(scored) - len(values)
        invalid[j, i] = len(grp) - len(scored)
        if len(values):
            miou[j, i] = cell_mean(values.to_numpy())
    return CellMap(a, b, a_vals, b_vals, miou, samples, undefined, invalid)


def drawn_rows(space: Space, n: int, seed: int = 0) -> pd.DataFrame:
    """`n` rows over the space's dims, placed as a search places them, with a score each."""
    rng = np.random.default_rng(seed)
    cols: dict[str, object] = {}
    for name, dim in space.dims.items():
        if isinstance(dim, Categorical):
            values = list(dim.values)
            cols[name] = [values[k] for k in rng.integers(len(values), size=n)]
        else:
            cols[name] = rng.uniform(dim.lo, dim.hi, n) if dim.hi > dim.lo else np.full(n, dim.lo)
    u = rng.random(n)
    status = np.where(u < INVALID_SHARE, Status.INVALID.value,
                      np.where(u < INVALID_SHARE + UNDEFINED_SHARE, Status.UNDEFINED.value,
                               Status.OK.value))
    iou = rng.random(n)
    cols["status"] = status
    cols["car_iou"] = [None if s != Status.OK.value else float(v)
                       for s, v in zip(status, iou, strict=True)]
    return pd.DataFrame(cols)


@dataclass(frozen=True)
class CellsBench:
    """Seconds for every map of a run of `samples` rows, both ways, and whether they agree."""

    config: str
    samples: int
    maps: list[dict]
    t_arrays: float
    t_per_group: float
    identical: bool

    def to_json(self) -> dict:
        return {"benchmark": "cells", "config": self.config, "samples": self.samples,
                "cells": sum(m["cells"] for m in self.maps), "maps": self.maps,
                "s_arrays": round(self.t_arrays, 4), "s_per_group": round(self.t_per_group, 3),
                "speedup": round(self.t_per_group / self.t_arrays, 1),
                "identical": self.identical, "machine": machine()}


def bench_cells(config: str | Path, samples: int = 50_000, seed: int = 0) -> CellsBench:
    """Every map a run of `samples` drawn rows over `config`'s space gets, timed both ways (the
    fast path the best of three, the naive path once), compared byte for byte."""
    space = load_space(config)
    frame = drawn_rows(space, samples, seed)
    maps, t_fast, t_naive, same = [], 0.0, 0.0, True
    for a, b in [("x", "y"), *extra_map_pairs(space)]:
        times = []
        for _ in range(3):
            t0 = time.perf_counter()
            fast = miou_map(frame, space, a, b)
            times.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        naive = per_group_map(frame, space, a, b)
        t1 = time.perf_counter() - t0
        agree = (fast.miou.tobytes() == naive.miou.tobytes()
                 and all(np.array_equal(p, q) for p, q in
                         ((fast.samples, naive.samples), (fast.undefined, naive.undefined),
                          (fast.invalid, naive.invalid))))
        maps.append({"dims": [a, b], "cells": int(fast.miou.size),
                     "filled": int(fast.filled.sum()), "s_arrays": round(min(times), 4),
                     "s_per_group": round(t1, 3), "identical": agree})
        t_fast, t_naive, same = t_fast + min(times), t_naive + t1, same and agree
    return CellsBench(str(config), samples, maps, t_fast, t_naive, same)
