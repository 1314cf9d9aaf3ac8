"""Snow: Gunn and Marshall's size distribution of melted flakes (1958) as particles
(falsify.sensor.weather.particles): extinction from it, plus the flakes that sit on a ray."""

from __future__ import annotations

from falsify.sensor.weather.particles import MIN_RATE, Particles

SNOW_N0 = (3800.0, -0.87)    # Gunn-Marshall: N0 = 3800 S^-0.87 m^-3 mm^-1 (melted diameter)
SNOW_LAMBDA = (2.55, -0.48)  # Lambda = 2.55 S^-0.48 mm^-1, S in mm/h of water
SNOW_DENSITY = 0.1           # a flake's density relative to water: its diameter is
#                              (1 / 0.1)^(1/3) = 2.15 times the melted drop's
# Snow is white and rough: Lambertian at its near-infrared albedo (about 0.8 near 0.9 um;
# Warren, "Optical properties of snow", Rev. Geophys. 1982).
SNOW_ECHO = 0.8
SNOW_MAX_MM = 10.0           # melted diameter of the largest aggregates drawn


def snow(rate: float) -> Particles:
    """Gunn and Marshall (1958), J. Meteorology 15:452: N0 = 3800 S^-0.87, Lambda = 2.55 S^-0.48
    (melted diameters; a flake is (1 / SNOW_DENSITY)^(1/3) times wider)."""
    rate = max(rate, MIN_RATE)
    return Particles(SNOW_N0[0] * rate ** SNOW_N0[1], SNOW_LAMBDA[0] * rate ** SNOW_LAMBDA[1],
                     (1.0 / SNOW_DENSITY) ** (1.0 / 3.0), SNOW_ECHO, SNOW_MAX_MM)
