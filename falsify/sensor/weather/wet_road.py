"""Wet road: a water film on the road darkens its diffuse return, most at grazing incidence
(Fresnel transmission in and out of the film and the light it traps: Lekner and Dorf, "Why some
things are darker when wet", Applied Optics 27(7), 1988).
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np

from falsify.sensor.lidar import Sensor
from falsify.sensor.weather.rain import WATER_INDEX
from falsify.world.materials import MATERIAL_ID

TEXTURE_DEPTH_MM = 0.7       # mean texture depth of dense asphalt (sand patch, ISO 13473-1);
#                              heights taken uniform on [0, 2 MTD]: a film of h mm submerges the
#                              share min(1, h / (2 MTD)) of the footprint
WATER_ABSORPTION = 6.7       # 1/m near 905 nm (Hale and Querry 1973: k = 4.86e-7 at 0.9 um)
WET = np.isin(np.arange(256), (MATERIAL_ID["asphalt"], MATERIAL_ID["concrete"]))  # by id
GROUND_NORMAL_Z = 0.9        # a ground pixel's normal is within 25 deg of the sensor's up axis


def fresnel(cos_i: np.ndarray, n: float) -> np.ndarray:
    """Unpolarised Fresnel reflectance from a medium of index 1 into one of index n (n < 1 is
    the way out: total internal reflection beyond the critical angle)."""
    cos_i = np.clip(np.asarray(cos_i, dtype=np.float64), 0.0, 1.0)
    sin_t2 = (1.0 - cos_i ** 2) / n ** 2
    total = sin_t2 >= 1.0
    cos_t = np.sqrt(np.clip(1.0 - sin_t2, 0.0, 1.0))
    rs = ((cos_i - n * cos_t) / np.maximum(cos_i + n * cos_t, 1e-300)) ** 2
    rp = ((n * cos_i - cos_t) / np.maximum(n * cos_i + cos_t, 1e-300)) ** 2
    return np.where(total, 1.0, (rs + rp) / 2)


def _diffuse_internal_reflectance(n: float = WATER_INDEX) -> float:
    """R-bar: the share of diffuse (Lambertian) light inside water that the water-air interface
    reflects back down, int_0^{pi/2} R(theta) sin(2 theta) d theta (Lekner and Dorf's r-bar)."""
    theta = np.linspace(0.0, math.pi / 2, 20001)
    f = fresnel(np.cos(theta), 1.0 / n) * np.sin(2 * theta)
    return float(np.sum((f[1:] + f[:-1]) / 2 * np.diff(theta)))


INTERNAL_REFLECTANCE = _diffuse_internal_reflectance()


def wet_factor(cos_i: np.ndarray, film_mm: float, albedo: float) -> np.ndarray:
    """How much of a dry road's back-scattered power a water film of `film_mm` leaves, at the
    incidence cosine `cos_i`: on the submerged share of the footprint the light crosses the film's
    surface twice (Fresnel transmission, the specular loss that grows at grazing incidence), its
    radiance drops by n^2 on the way out and the light the surface reflects back down is partly
    re-absorbed, 1 / (1 - albedo R-bar) (Lekner and Dorf 1988), and the water absorbs a little."""
    cos_i = np.clip(np.asarray(cos_i, dtype=np.float64), 1e-6, 1.0)
    covered = min(1.0, film_mm / (2.0 * TEXTURE_DEPTH_MM))
    t_in = 1.0 - fresnel(cos_i, WATER_INDEX)
    cos_t = np.sqrt(1.0 - (1.0 - cos_i ** 2) / WATER_INDEX ** 2)
    absorbed = np.exp(-2.0 * WATER_ABSORPTION * film_mm * 1e-3 / cos_t)
    wet = t_in ** 2 / WATER_INDEX ** 2 / (1.0 - albedo * INTERNAL_REFLECTANCE) * absorbed
    return (1.0 - covered) + covered * wet


@lru_cache(maxsize=64)
def _wet_table(film_mm: float, albedo: float) -> tuple[np.ndarray, np.ndarray]:
    """wet_factor on a fine grid of incidence cosines (interpolated per pixel: cheap)."""
    cos = np.concatenate([np.geomspace(1e-4, 0.05, 200), np.linspace(0.05, 1.0, 400)[1:]])
    return cos, wet_factor(cos, film_mm, albedo)



def wet_ground(sensor: Sensor, mat: np.ndarray, normal: np.ndarray,
               hard_r: np.ndarray) -> np.ndarray:
    """Road and pavement pixels: asphalt or concrete, facing up, below the sensor by more
    than half its height (not a floor seen through a window)."""
    z = sensor.directions[..., 2] * np.where(np.isfinite(hard_r), hard_r, 0.0)
    return WET[mat] & (normal[..., 2] >= GROUND_NORMAL_Z) & (
        z < -0.5 * sensor.mount_height)


def wet_factors(cos_i: np.ndarray, film_mm: float, albedo: float) -> np.ndarray:
    """wet_factor per pixel, interpolated in a cached fine table of incidence cosines."""
    return np.interp(cos_i, *_wet_table(film_mm, albedo))
