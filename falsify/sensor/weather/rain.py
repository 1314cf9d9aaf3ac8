"""Rain: Marshall and Palmer's drop-size distribution (1948) as particles (falsify.sensor.weather
.particles): extinction from it, plus the drops that sit on a ray."""

from __future__ import annotations

from falsify.sensor.weather.particles import MIN_RATE, Particles

RAIN_N0 = 8000.0             # Marshall-Palmer: N(D) = N0 exp(-Lambda D), m^-3 mm^-1
RAIN_LAMBDA = (4.1, -0.21)   # Lambda = 4.1 R^-0.21 mm^-1, R in mm/h
WATER_INDEX = 1.33           # refractive index of water near 905 nm
# A drop returns like a mirror sphere: back-scatter cross-section R_F pi a^2, which a Lambertian
# patch covering the same share of the beam matches at reflectivity R_F / 4 (R_F: normal-incidence
# Fresnel reflectance).
RAIN_ECHO = ((WATER_INDEX - 1) / (WATER_INDEX + 1)) ** 2 / 4
RAIN_MAX_MM = 8.0            # drops break up beyond about 8 mm (Pruppacher and Klett 1997)


def rain(rate: float) -> Particles:
    """Marshall and Palmer (1948), J. Meteorology 5:165: N0 = 8000, Lambda = 4.1 R^-0.21."""
    rate = max(rate, MIN_RATE)
    return Particles(RAIN_N0, RAIN_LAMBDA[0] * rate ** RAIN_LAMBDA[1], 1.0, RAIN_ECHO,
                     RAIN_MAX_MM)
