"""What a sample asks of the weather and what the sensor records: the `Effects` a sample's effect
dims give (read, or drawn for training scans), the per-pixel `Echoes` they act on, and the seeded
streams their random draws come from.

Every random draw comes from a seed fixed by the sample (derived from the scan's generator without
consuming it), so a sample gives the same bytes every time and zero severity gives today's scan.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, fields

import numpy as np

from falsify.world.space import EFFECT_DIMS, Categorical, Sample, Space

# Streams of the effects' draws (one generator each, so each effect's draws are its own);
# _RECORDED: the return model's dropouts of a weathered real scan's echoes.
_RAIN, _SNOW, _CROSSTALK, _BEAMS, _RECORDED = 1, 2, 3, 4, 5


@dataclass(frozen=True)
class Effects:
    """A sample's weather and faults in physical units; all zero is clear weather."""

    fog: float = 0.0           # meteorological visibility, m (0 = no fog)
    rain: float = 0.0          # mm/h
    snow: float = 0.0          # mm/h of water
    wet_road: float = 0.0      # water film, mm
    beam_loss: int = 0         # lasers out
    beams: int = 0             # lasers kept, evenly spaced (0 = all)
    crosstalk: int = 0         # spurious points per scan
    ego_speed: float = 0.0     # km/h

    @property
    def clear(self) -> bool:
        return not any(getattr(self, f.name) for f in fields(self))

    @property
    def medium(self) -> bool:
        """Whether anything between the sensor and the target changes the echo."""
        return bool(self.fog or self.rain or self.snow or self.wet_road)


def _effects(values: dict[str, float]) -> Effects:
    """Effects from dim values (counts rounded to whole numbers: samplers draw reals)."""
    return Effects(**{k: (int(round(v)) if EFFECT_DIMS[k][3] else v) for k, v in values.items()})


def effects_of(sample: Sample) -> Effects:
    """The effects a sample's dims ask for."""
    return _effects({name: float(v) for name in EFFECT_DIMS
                     if (v := sample.get(name)) is not None})


def draw_effects(space: Space, rng: np.random.Generator) -> Effects:
    """Effects drawn uniformly from a space's effect dims (a value list: one of its values), for
    training scans that should see the weather a falsification space tests."""
    values = {}
    for name in EFFECT_DIMS:
        dim = space.dims.get(name)
        if dim is None:
            continue
        if isinstance(dim, Categorical):
            values[name] = float(dim.values[int(rng.integers(len(dim.values)))])
        else:
            values[name] = float(rng.uniform(dim.lo, dim.hi))
    return _effects(values)


def effect_seed(rng: np.random.Generator | None, fallback: int) -> int:
    """A seed for the effects' draws fixed by the generator's state, read without drawing from
    it (so the scan's own draws stay today's); `fallback` when there is no generator."""
    if rng is None:
        return int(fallback) & 0xFFFFFFFF
    state = repr(rng.bit_generator.state).encode()
    return int.from_bytes(hashlib.blake2b(state, digest_size=4).digest(), "little")



def stream(seed: int, which: int) -> np.random.Generator:
    """The generator of one effect's draws for one scan."""
    return np.random.Generator(np.random.PCG64([seed, which]))


@dataclass
class Echoes:
    """Per pixel what the sensor records: range, validity, intensity (None without a return
    model), class, instance and raw SemanticKITTI id (None: not tracked)."""

    r: np.ndarray
    valid: np.ndarray
    intensity: np.ndarray | None
    cls: np.ndarray
    inst: np.ndarray
    semantic: np.ndarray | None = None
