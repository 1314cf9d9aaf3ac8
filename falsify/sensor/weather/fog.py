"""Fog: the hard echo attenuated two-way, exp(-2 alpha R) with alpha = ln(20) / visibility
(Koschmieder's 5 % contrast), against the fog's own back-scattered soft echo, the integral of the
pulse over the fog's back-scatter (Hahner et al., "Fog Simulation on Real LiDAR Point Clouds for 3D
Object Detection in Adverse Weather", ICCV 2021, Sec. 3: the LiDAR equation with a sin^2 pulse and
its hard- and soft-target responses, and their parameters).
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np

from falsify.sensor.lidar import Sensor

LIGHT_SPEED = 299_792_458.0  # m/s

# Hahner et al. 2021, Sec. 3 and their parameter set.
FOG_CONTRAST = 0.05          # Koschmieder: visibility is where contrast falls to 5 %
FOG_BACKSCATTER = 0.046      # beta = 0.046 / visibility, 1/(m sr) (Rasshofer, Spies and Spies,
#                              "Influences of weather phenomena on automotive laser radar
#                              systems", Adv. Radio Sci. 9, 2011; as Hahner 2021)
PULSE_HALF_POWER_S = 20e-9   # tau_H: the pulse P(t) = P0 sin^2(pi t / (2 tau_H)), 0 <= t <= 2 tau_H
OVERLAP_START_M = 0.9        # R_1: the receiver starts to see the transmitted beam
OVERLAP_FULL_M = 1.0         # R_2: it sees all of it (xi(R) linear in between)
FOG_GAMMA = 1e-6             # Gamma: the hard target's reflectivity in their calibration of the
#                              soft echo against the hard one; here the intensity scale's 1.0
PULSE_RANGE_M = LIGHT_SPEED * PULSE_HALF_POWER_S   # c tau_H: the pulse's length in range
_GL_NODES, _GL_WEIGHTS = np.polynomial.legendre.leggauss(32)


def fog_coefficients(visibility: float) -> tuple[float, float]:
    """(alpha, beta): extinction (1/m, Koschmieder: ln(20) / V) and back-scatter (1/(m sr),
    0.046 / V) of fog of visibility V metres (Hahner 2021; Rasshofer 2011)."""
    if visibility <= 0:
        return 0.0, 0.0
    return -math.log(FOG_CONTRAST) / visibility, FOG_BACKSCATTER / visibility


def crossover(s: np.ndarray) -> np.ndarray:
    """xi(R): the share of the transmitted beam the receiver sees at range R (linear between
    R_1 and R_2; Hahner 2021)."""
    return np.clip((s - OVERLAP_START_M) / (OVERLAP_FULL_M - OVERLAP_START_M), 0.0, 1.0)


def soft_integral(r: np.ndarray, alpha: float, r0: np.ndarray | float = np.inf) -> np.ndarray:
    """The soft target's integral I(R) = int_0^{2 tau_H} sin^2(pi t / (2 tau_H))
    xi(R - ct/2) exp(-2 alpha (R - ct/2)) / (R - ct/2)^2 U(R_0 - R + ct/2) dt, in s/m^2
    (Hahner 2021, Sec. 3: the LiDAR equation P_R(R) = C_A int P(t) H(R - ct/2) dt with the sin^2
    pulse and the fog's response H = xi(R) exp(-2 alpha R) / R^2 * beta up to the target, so
    P_R,soft(R) = C_A P_0 beta I(R)).

    Computed in the range variable s = R - ct/2 (dt = 2 ds / c) by Gauss-Legendre on the pieces
    where the integrand is smooth (split where xi bends and where the hard target at R_0 cuts
    the fog off); exact to about 1e-12 relative.
    """
    r = np.asarray(r, dtype=np.float64)
    r0 = np.broadcast_to(np.asarray(r0, dtype=np.float64), r.shape)
    lo = np.maximum(r - PULSE_RANGE_M, OVERLAP_START_M)
    hi = np.minimum(r, r0)
    total = np.zeros(r.shape)
    for a, b in ((lo, np.minimum(hi, OVERLAP_FULL_M)), (np.maximum(lo, OVERLAP_FULL_M), hi)):
        width = b - a
        ok = width > 0
        if not ok.any():
            continue
        half, mid = (width / 2)[..., None], ((a + b) / 2)[..., None]
        s = mid + half * _GL_NODES
        f = (np.sin(math.pi * (r[..., None] - s) / PULSE_RANGE_M) ** 2 * crossover(s)
             * np.exp(-2.0 * alpha * s) / s ** 2)
        total += np.where(ok, (f * _GL_WEIGHTS).sum(axis=-1) * half[..., 0], 0.0)
    return total * (2.0 / LIGHT_SPEED)


def _peak(alpha: float, r0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Where I(R) peaks over R and its value there, per hard-target range r0: a grid, a finer
    grid around the best point, then a parabola through the best three. The peak lies in
    [R_1, R_2 + c tau_H]: beyond, every point of the pulse sees fog farther than R_2, where the
    integrand only falls with range."""
    r0 = np.asarray(r0, dtype=np.float64)
    lo = np.full(r0.shape, OVERLAP_START_M)
    hi = np.minimum(r0, OVERLAP_FULL_M) + PULSE_RANGE_M
    for n in (40, 20):
        grid = lo[..., None] + (hi - lo)[..., None] * np.linspace(0.0, 1.0, n)
        vals = soft_integral(grid, alpha, r0[..., None])
        k = np.clip(np.argmax(vals, axis=-1), 1, n - 2)
        step = (hi - lo) / (n - 1)
        centre = np.take_along_axis(grid, k[..., None], -1)[..., 0]
        lo, hi = centre - step, centre + step
    step = (hi - lo) / 2   # a parabola through (centre - step, centre, centre + step)
    x = np.stack([lo, (lo + hi) / 2, hi], axis=-1)
    y = soft_integral(x, alpha, r0[..., None])
    den = y[..., 0] - 2 * y[..., 1] + y[..., 2]
    shift = np.where(den < 0, 0.5 * (y[..., 0] - y[..., 2]) / np.where(den < 0, den, -1.0), 0.0)
    best = x[..., 1] + np.clip(shift, -1.0, 1.0) * step
    return best, soft_integral(best, alpha, r0)


@lru_cache(maxsize=512)
def fog_peak(alpha: float) -> tuple[float, float]:
    """(R_fog, I_max) of fog in front of a far target: the range the soft echo is reported at
    (the peak of P_R,soft shifted by c tau_H / 2, the same shift that puts a hard target's peak
    at its range R_0; Hahner 2021) and the integral there (s/m^2)."""
    best, value = _peak(alpha, np.array([np.inf]))
    return float(best[0] - PULSE_RANGE_M / 2), float(value[0])


def soft_echo(alpha: float, beta: float, r0: np.ndarray,
              hard_power: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(range, received power) of the fog's soft echo in front of hard targets at ranges `r0`
    (inf: none), where it could beat `hard_power`. Power in hard-target units (I / R^2 for
    intensity I at R): pi beta I / Gamma, Hahner's calibration P_soft / P_hard =
    R_0^2 (beta / beta_0) I with beta_0 = Gamma / pi. A target nearer than the peak cuts the fog
    off; its smaller peak is only searched where the uncut one would beat the target."""
    r0 = np.asarray(r0, dtype=np.float64)
    r_fog, i_max = fog_peak(alpha)
    ranges = np.full(r0.shape, r_fog)
    power = np.full(r0.shape, math.pi * beta * i_max / FOG_GAMMA)
    near = (r0 < r_fog + PULSE_RANGE_M / 2) & (power > hard_power)
    if near.any():
        best, value = _peak(alpha, r0[near])
        ranges[near] = best - PULSE_RANGE_M / 2
        power[near] = math.pi * beta * value / FOG_GAMMA
    return ranges, power


def fog_echoes(s: Sensor, alpha: float, beta: float, hard_r: np.ndarray, hard_p: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The stronger of the hard echo and the fog's soft echo per ray (power, range, and
    whether the fog's won); a soft echo outside the sensor `s`'s ranges is not seen."""
    r_fog, i_max = fog_peak(alpha)
    power = math.pi * beta * i_max / FOG_GAMMA
    if not s.min_range <= r_fog <= s.max_range:
        return hard_p, hard_r, np.zeros(hard_r.shape, bool)
    spur = hard_p < power
    near = spur & (hard_r < r_fog + PULSE_RANGE_M / 2)   # a target cuts the fog off
    best = np.maximum(hard_p, power)
    best_r = np.where(spur, r_fog, hard_r)
    if near.any():
        fr, fp = soft_echo(alpha, beta, hard_r[near], hard_p[near])
        won = (fp > hard_p[near]) & (fr >= s.min_range)
        best[near] = np.where(won, fp, hard_p[near])
        best_r[near] = np.where(won, fr, hard_r[near])
        spur[near] = won
    return best, best_r, spur
