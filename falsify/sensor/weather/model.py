"""The weather of one sensor and return model: `Weather` takes a clear scan's first hits through
ego motion, the medium (fog, rain, snow, wet road) and the faults to what the sensor records.

The sensor reports the strongest echo of a ray when its received power reaches the detection
floor: the weakest power today's clear return model reports (the darkest material at max range,
88 deg from its normal), so that clear weather is exactly today's scan. Received power is in
the units where a hard target of intensity I at range R gives I / R^2 (the return model's
intensity is range-compensated).
"""

from __future__ import annotations

import math

import numpy as np

from falsify.sensor.lidar import Sensor
from falsify.sensor.returns import ReturnModel
from falsify.sensor.weather.effects import _RAIN, _SNOW, Echoes, Effects, stream
from falsify.sensor.weather.ego_motion import column_times, forward_axis, moving_ranges
from falsify.sensor.weather.faults import sensor_faults
from falsify.sensor.weather.fog import fog_coefficients, fog_echoes
from falsify.sensor.weather.particles import particle_echoes
from falsify.sensor.weather.rain import rain
from falsify.sensor.weather.snow import snow
from falsify.sensor.weather.wet_road import wet_factors, wet_ground

COS_FLOOR = math.cos(math.radians(88.0))   # the most grazing hit the detection floor covers
NOMINAL_INTENSITY = 0.3      # a sensor without a return model: every hit this bright (road)


class Weather:
    """The effects for one sensor and return model: detection floor, ground test, sweep."""

    def __init__(self, sensor: Sensor, returns: ReturnModel | None):
        self.sensor = sensor
        self.returns = returns
        self.floor = detection_floor(sensor, returns)
        if returns is not None:
            self.road_albedo = float(returns.reflectivity["road"])
        else:
            self.road_albedo = NOMINAL_INTENSITY
        self.column_time = column_times(sensor)
        self.forward = forward_axis(sensor)   # ego +x, sensor frame

    # -- geometry: ego motion ----------------------------------------------------------------
    def moving_ranges(self, dist: np.ndarray, normal: np.ndarray, cos: np.ndarray,
                      speed_kmh: float) -> np.ndarray:
        """Each ray's range fired from where the ego is at its column's time
        (ego_motion.moving_ranges)."""
        return moving_ranges(dist, normal, cos, speed_kmh, self.column_time, self.forward)

    # -- the medium: fog, rain, snow, wet road -----------------------------------------------
    def medium(self, fx: Effects, seed: int, e: Echoes, clear_i: np.ndarray, mat: np.ndarray,
               cos: np.ndarray, normal: np.ndarray, least: np.ndarray | None = None) -> Echoes:
        """The strongest echo per ray among the attenuated hard target, the fog's soft echo and
        the particles on the ray, kept where it reaches the detection floor. `clear_i` is the
        hard echo's clear intensity, 0 where there is none; `least` as `through` takes it."""
        ground = None
        if fx.wet_road > 0:
            ground = self.ground(mat, normal, np.where(e.valid, e.r, np.inf)) & e.valid
        return self.through(fx, seed, e, clear_i, ground, cos, least)[0]

    def through(self, fx: Effects, seed: int, e: Echoes, clear_i: np.ndarray,
                ground: np.ndarray | None, cos: np.ndarray | None,
                least: np.ndarray | None = None) -> tuple[Echoes, np.ndarray]:
        """`medium` given the wet pixels (`ground`, with their incidence cosines `cos`; None
        without a water film), and the pixels that now hold a spurious echo (a particle's or the
        fog's). `least`, where given, is the least intensity each hard echo is taken to have had
        when deciding what is detected (a recorded return reached the floor: its received power
        was at least the floor, however dark its stored remission); the intensity reported for a
        kept hard echo is still `clear_i` attenuated."""
        hard = e.valid
        hard_r = np.where(hard, e.r, np.inf)
        hard_i = clear_i.astype(np.float64)
        lifted = None if least is None else np.maximum(hard_i, least)
        if ground is not None:
            wet = wet_factors(cos[ground], float(fx.wet_road), self.road_albedo)
            hard_i[ground] *= wet
            if lifted is not None:
                lifted[ground] *= wet
        pf = [(rain(fx.rain), _RAIN)] if fx.rain > 0 else []
        pf += [(snow(fx.snow), _SNOW)] if fx.snow > 0 else []
        alpha_fog, beta = fog_coefficients(fx.fog)
        alpha = alpha_fog + sum(p.extinction for p, _ in pf)
        if alpha > 0:
            hard_i *= np.exp(-2.0 * alpha * hard_r)
            if lifted is not None:
                lifted *= np.exp(-2.0 * alpha * hard_r)
        # received power; 0 where no hard echo
        best = (hard_i if lifted is None else lifted) / (hard_r * hard_r)
        best_r = hard_r
        spur = None                            # where the echo is not the hard target's
        if beta > 0:
            best, best_r, spur = fog_echoes(self.sensor, alpha, beta, hard_r, best)
        for p, which in pf:
            if spur is None:
                best, best_r, spur = best.copy(), hard_r.copy(), np.zeros(hard.shape, bool)
            particle_echoes(self.sensor, self.floor, p, stream(seed, which), alpha, hard_r,
                            best, best_r, spur)
        # An echo needs power: a floor of 0 (a model's darkest level 0, or exp(-range /
        # atten_m) underflowing) would otherwise report every miss, at range inf.
        ok = (best >= self.floor) & (best > 0)
        cls, inst, sem, intensity = e.cls, e.inst, e.semantic, None
        if spur is not None:
            real = ~(ok & spur)
            cls, inst = cls * real, inst * real
            sem = None if sem is None else sem * real
        if e.intensity is not None:
            if spur is not None:
                hard_i = np.where(spur, best * np.where(ok, best_r, 0.0) ** 2, hard_i)
            intensity = (hard_i * ok).astype(np.float32)
        spurious = np.zeros(hard.shape, bool) if spur is None else ok & spur
        return Echoes(best_r, ok, intensity, cls, inst, sem), spurious

    def ground(self, mat: np.ndarray, normal: np.ndarray, hard_r: np.ndarray) -> np.ndarray:
        """Road and pavement pixels (wet_road.wet_ground)."""
        return wet_ground(self.sensor, mat, normal, hard_r)

    # -- faults ------------------------------------------------------------------------------
    def faults(self, fx: Effects, seed: int, e: Echoes) -> Echoes:
        """Crosstalk, lost lasers and fewer beams (faults.sensor_faults)."""
        return sensor_faults(self.sensor, fx, seed, e)


def detection_floor(sensor: Sensor, returns: ReturnModel | None) -> float:
    """The weakest received power the clear model reports: the darkest material at max range,
    hit at COS_FLOOR (88 deg from the normal). Every clear return within range reaches it, so
    clear weather drops nothing, and weather drops an echo once it falls below."""
    far = sensor.max_range
    if returns is None:
        return NOMINAL_INTENSITY / far ** 2
    dark = min(returns.reflectivity.values())
    weakest = dark * COS_FLOOR ** returns.cos_exp * math.exp(-far / returns.atten_m)
    return float(weakest / far ** 2)
