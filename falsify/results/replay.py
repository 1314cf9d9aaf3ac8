"""A stored row back into its sample, its scan and the model's prediction.

The retraining-set export and the report's previews both replay rows this one way: the sample
rebuilt from the row's dims, the scene cast with the row's own sensor-effects seed.
"""

from __future__ import annotations

import math

import numpy as np
import pandas as pd

from falsify.data.real_backgrounds import scanner_for
from falsify.results.samples import sample_seed
from falsify.sensor.scan import Scan
from falsify.sensor.simulator import Scanner
from falsify.world.space import Categorical, Sample, Space


def row_sample(space: Space, row: pd.Series) -> Sample:
    """The Sample of a stored row (categorical ints come back from SQLite as floats)."""
    values = {}
    for name, dim in space.dims.items():
        if name not in row.index:
            continue
        raw = row[name]
        if raw is None or (isinstance(raw, float) and math.isnan(raw)):
            continue
        if isinstance(dim, Categorical):
            raw = _category(dim, raw)
        values[name] = raw
    return space.make(values)


def _category(dim: Categorical, raw: object) -> object:
    for v in dim.values:
        if str(v) == str(raw):
            return v
        if not isinstance(v, str) and not isinstance(raw, str):
            try:
                if float(v) == float(raw):
                    return v
            except (TypeError, ValueError):
                continue
    return raw


def row_seed(space: Space, sample: Sample, row: pd.Series) -> int:
    """The seed the row was scanned with: stored with it, else derived as the pipeline does."""
    seed = row.get("seed")
    return sample_seed(space, sample) if seed is None or pd.isna(seed) else int(seed)


class Replay:
    """Re-casts stored rows with one warm simulator at the run's car level of detail."""

    def __init__(self, space: Space, lod: int = 2, sim: Scanner | None = None):
        self.space = space
        self.sim = sim or scanner_for(space, lod=lod)

    def scan(self, row: pd.Series) -> tuple[Sample, Scan]:
        """The row's sample and its scan, as the run cast it (InvalidSample if it was invalid)."""
        sample = row_sample(self.space, row)
        rng = np.random.default_rng(row_seed(self.space, sample, row))
        return sample, self.sim.scan(sample, rng=rng)

