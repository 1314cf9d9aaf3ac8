"""Weather and sensor faults on the LiDAR, applied per ray to a cast scan (never re-casting).

The modification space's effect dims (falsify.world.space.EFFECT_DIMS) become an `Effects`
(`effects`), and the Simulator's `to_scan` hands a clear scan's first hits to `Weather` (`model`:
ego motion, the medium, then the faults) to get what the sensor records. One module per effect,
each with the published model it follows:

- `fog`: two-way extinction and the fog's soft back-scattered echo (Hahner et al., ICCV 2021);
- `rain`, `snow`: extinction from the drop-size distribution (Marshall and Palmer 1948; Gunn and
  Marshall 1958) and the drops and flakes on a ray (`particles`);
- `wet_road`: a water film darkening the road's return (Lekner and Dorf 1988);
- `faults`: beam_loss, beams (Robo3D's ring selection, Kong et al., ICCV 2023) and crosstalk;
- `ego_motion`: each column fired from where the ego is at its time in the sweep.

Spurious points get label 0, instance 0 and SemanticKITTI id 0 (unlabeled). Every random draw
comes from a seed fixed by the sample (derived from the scan's generator without consuming it),
so a sample gives the same bytes every time and zero severity gives today's scan.
"""

from falsify.sensor.weather.effects import (
    _RECORDED,
    Echoes,
    Effects,
    draw_effects,
    effect_seed,
    effects_of,
    stream,
)
from falsify.sensor.weather.ego_motion import KMH
from falsify.sensor.weather.faults import check_beams, kept_rows
from falsify.sensor.weather.fog import (
    FOG_BACKSCATTER,
    FOG_CONTRAST,
    FOG_GAMMA,
    LIGHT_SPEED,
    OVERLAP_FULL_M,
    OVERLAP_START_M,
    PULSE_HALF_POWER_S,
    PULSE_RANGE_M,
    crossover,
    fog_coefficients,
    fog_peak,
    soft_echo,
    soft_integral,
)
from falsify.sensor.weather.model import COS_FLOOR, NOMINAL_INTENSITY, Weather, detection_floor
from falsify.sensor.weather.particles import (
    BEAM_DIVERGENCE,
    BEAM_EXIT_M,
    Particles,
    beam_width,
    poisson_quantile,
)
from falsify.sensor.weather.rain import WATER_INDEX
from falsify.sensor.weather.wet_road import INTERNAL_REFLECTANCE, fresnel, wet_factor

# `rain` and `snow`, the distributions, stay in their modules: their names are the modules'.
__all__ = [
    "BEAM_DIVERGENCE", "BEAM_EXIT_M", "COS_FLOOR", "FOG_BACKSCATTER", "FOG_CONTRAST", "FOG_GAMMA",
    "INTERNAL_REFLECTANCE", "KMH", "LIGHT_SPEED", "NOMINAL_INTENSITY", "OVERLAP_FULL_M",
    "OVERLAP_START_M", "PULSE_HALF_POWER_S", "PULSE_RANGE_M", "WATER_INDEX", "Echoes",
    "Effects", "Particles", "Weather", "_RECORDED", "beam_width", "check_beams", "crossover",
    "detection_floor", "draw_effects", "effect_seed", "effects_of", "fog_coefficients",
    "fog_peak", "fresnel", "kept_rows", "poisson_quantile", "soft_echo", "soft_integral",
    "stream", "wet_factor",
]
