"""Rain drops and snow flakes as particles: an exponential size distribution's extinction, and the
particles that sit on a ray, drawn as a Poisson process, each one's echo competing with the
target's (a near spurious point of low intensity). The distributions themselves are in
falsify.sensor.weather.rain (Marshall and Palmer 1948) and .snow (Gunn and Marshall 1958).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from falsify.sensor.lidar import Sensor

BEAM_EXIT_M = 0.01           # the beam's diameter at the sensor
BEAM_DIVERGENCE = 2e-3       # full angle, rad: diameter w(r) = 0.01 + 0.002 r m


# The smallest rate the size distributions take: a subnormal rate reads as 0 where a library has
# switched on flush-to-zero, and 0 ** -0.21 raises; below it rain and snow change nothing anyway.
MIN_RATE = 1e-300


@dataclass(frozen=True)
class Particles:
    """An exponential size distribution N(D) = n0 exp(-lam D) (D in mm, melted for snow, drawn
    up to d_max), the factor from its D to the particle's optical diameter, and its echo's
    reflectivity."""

    n0: float       # m^-3 mm^-1
    lam: float      # 1/mm
    grow: float     # optical diameter / D
    echo: float     # Lambertian-equivalent reflectivity of a particle filling the beam
    d_max: float    # mm

    @property
    def extinction(self) -> float:
        """Extinction, 1/m: geometric optics (extinction efficiency 2, large particles:
        van de Hulst 1957) over the distribution, 2 int (pi (g D)^2 / 4) N(D) dD =
        pi n0 g^2 / lam^3 (1e-6 turns mm^2 m^-3 into 1/m). Rain: 0.365 R^0.63 per km. Divided
        by lam one factor at a time: lam^3 overflows for a snow rate below 1e-213 mm/h."""
        return math.pi * 1e-6 * self.grow ** 2 * (self.n0 / self.lam) / self.lam / self.lam

    @property
    def hits_per_m(self) -> float:
        """Particles a ray's axis passes through per metre: their geometric cross-section per
        volume, half the extinction."""
        return self.extinction / 2

    def reach(self, floor: float, far: float) -> float:
        """The farthest range (<= far) at which the largest particle's echo can still reach the
        detection floor: beyond it no particle can be seen or hide the target."""
        return _reach(self.grow * self.d_max * 1e-3, self.echo, floor, far)


@lru_cache(maxsize=64)
def _reach(width: float, echo: float, floor: float, far: float) -> float:
    """Particles.reach by bisection: echo * min(1, (width / w(r))^2) / r^2 falls with r."""
    lo, hi = 0.0, far
    for _ in range(60):
        mid = (lo + hi) / 2
        share = min(1.0, (width / (BEAM_EXIT_M + BEAM_DIVERGENCE * mid)) ** 2)
        lo, hi = (mid, hi) if echo * share / mid ** 2 >= floor else (lo, mid)
    return hi


def beam_width(r: np.ndarray | float) -> np.ndarray:
    """The beam's diameter (m) at range r."""
    return BEAM_EXIT_M + BEAM_DIVERGENCE * np.asarray(r)


def poisson_quantile(u: float, mean: float) -> int:
    """The Poisson count at quantile u: one uniform gives counts that never fall as the mean
    grows (so a heavier rain holds every drop a lighter one held, with the same seed)."""
    from scipy.special import pdtr, pdtrik

    if mean <= 0:
        return 0
    k = max(math.ceil(float(pdtrik(u, mean))), 0)
    while k > 0 and pdtr(k - 1, mean) >= u:
        k -= 1
    while pdtr(k, mean) < u:
        k += 1
    return k


def particle_echoes(s: Sensor, floor: float, p: Particles, gen: np.random.Generator,
                    alpha: float, hard_r: np.ndarray, best: np.ndarray, best_r: np.ndarray,
                    spur: np.ndarray) -> None:
    """Drops or flakes on the rays of sensor `s` (in place; `floor`: its detection floor): a
    Poisson process along every ray up to its target, at p.hits_per_m, drawn as one count over
    the image out to the particles' reach and thinned by each ray's own length (uniform pixel
    and position each). Each particle covers (D / w(r))^2 of the beam: its echo, that share
    times its reflectivity, takes the ray where it is the strongest; one as wide as the beam
    hides what is behind it (and, inside the sensor's min_range, leaves the ray empty)."""
    n_pix = hard_r.size
    reach = p.reach(floor, s.max_range)
    n = poisson_quantile(float(gen.random()), p.hits_per_m * reach * n_pix)
    if n == 0:
        return
    u = gen.random((n, 5))   # row k: particle k's draws (more particles: more rows)
    pix = np.minimum((u[:, 0] * n_pix).astype(np.int64), n_pix - 1)
    at = u[:, 1] * reach
    inside = at < hard_r.reshape(-1)[pix]
    pix, at, u = pix[inside], at[inside], u[inside]
    if not len(pix):
        return
    # Sizes of the particles a line meets: area-weighted, D^2 N(D), a gamma of shape 3.
    d = np.minimum(-np.log(u[:, 2] * u[:, 3] * u[:, 4] + 1e-300) / p.lam, p.d_max)
    share = np.minimum(1.0, (p.grow * d * 1e-3 / beam_width(at)) ** 2)
    power = p.echo * share * np.exp(-2.0 * alpha * at) / at ** 2
    flat_best, flat_r, flat_spur = best.reshape(-1), best_r.reshape(-1), spur.reshape(-1)
    seen = (at >= s.min_range) & (power >= floor)
    block = share >= 1.0   # hides the target, the fog and the particles behind it
    if block.any():
        order = np.argsort(-at[block], kind="stable")   # nearest last: it wins
        bp, ba, bw = pix[block][order], at[block][order], power[block][order]
        bw = np.where(ba >= s.min_range, bw, 0.0)   # inside min_range: hides, is not reported
        farther = flat_r[bp] > ba
        flat_best[bp[farther]] = bw[farther]
        flat_r[bp[farther]] = ba[farther]
        flat_spur[bp[farther]] = True
        wall = np.full(n_pix, np.inf)
        np.minimum.at(wall, bp, ba)
        seen &= at <= wall[pix]
    pix, at, power = pix[seen], at[seen], power[seen]
    order = np.argsort(power, kind="stable")   # strongest last: it wins its pixel
    pix, at, power = pix[order], at[order], power[order]
    stronger = power > flat_best[pix]
    flat_best[pix[stronger]] = power[stronger]
    flat_r[pix[stronger]] = at[stronger]
    flat_spur[pix[stronger]] = True
