"""Weather and sensor faults on the LiDAR, applied per ray to a cast scan (never re-casting).

The modification space's effect dims (falsify.world.space.EFFECT_DIMS) become an `Effects`, and
the Simulator's `to_scan` hands a clear scan's first hits to `Weather` (ego motion, the medium,
then the faults) to get what the sensor records:

- fog: the hard echo attenuated two-way, exp(-2 alpha R) with alpha = ln(20) / visibility
  (Koschmieder's 5 % contrast), against the fog's own back-scattered soft echo, the integral of
  the pulse over the fog's back-scatter (Hahner et al., "Fog Simulation on Real LiDAR Point Clouds
  for 3D Object Detection in Adverse Weather", ICCV 2021, Sec. 3: the LiDAR equation with a sin^2
  pulse and its hard- and soft-target responses, and their parameters);
- rain and snow: extinction from the drop-size distribution (Marshall and Palmer 1948; Gunn and
  Marshall 1958), plus the drops and flakes that sit on a ray, drawn as a Poisson process: each
  one's echo competes with the target's (a near spurious point of low intensity);
- wet_road: a water film on the road darkens its diffuse return, most at grazing incidence
  (Fresnel transmission in and out of the film and the light it traps: Lekner and Dorf, "Why some
  things are darker when wet", Applied Optics 27(7), 1988);
- beam_loss: whole rows (lasers) out, drawn at random; beams: a sensor with fewer lasers, N of the
  rows kept evenly spaced (rows (k * H) // N: every other one for 32 of 64), the cross-sensor
  corruption of Robo3D (Kong et al., ICCV 2023), 64 -> 32 / 16 beams by ring selection;
  crosstalk: spurious points from another sensor at random
  pixels and ranges; ego_speed: each column fired at its time in the sweep from where the ego then
  is (the motion distortion of a rotating sensor).

The sensor reports the strongest echo of a ray when its received power reaches the detection
floor: the weakest power today's clear return model reports (the darkest material at max range,
88 deg from its normal), so that clear weather is exactly today's scan. Received power is in
the units where a hard target of intensity I at range R gives I / R^2 (the return model's
intensity is range-compensated).
Spurious points get label 0, instance 0 and SemanticKITTI id 0 (unlabeled). Every random draw
comes from a seed fixed by the sample (derived from the scan's generator without consuming it),
so a sample gives the same bytes every time and zero severity gives today's scan.
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass, fields
from functools import lru_cache

import numpy as np

from falsify.errors import ConfigError
from falsify.rotations import rot_y
from falsify.sensor.lidar import Sensor
from falsify.sensor.returns import ReturnModel
from falsify.world.materials import MATERIAL_ID
from falsify.world.space import EFFECT_DIMS, Categorical, Sample, Space

LIGHT_SPEED = 299_792_458.0  # m/s

# -- fog (Hahner et al. 2021, Sec. 3 and their parameter set) ---------------------------------
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

# -- rain and snow ----------------------------------------------------------------------------
RAIN_N0 = 8000.0             # Marshall-Palmer: N(D) = N0 exp(-Lambda D), m^-3 mm^-1
RAIN_LAMBDA = (4.1, -0.21)   # Lambda = 4.1 R^-0.21 mm^-1, R in mm/h
SNOW_N0 = (3800.0, -0.87)    # Gunn-Marshall: N0 = 3800 S^-0.87 m^-3 mm^-1 (melted diameter)
SNOW_LAMBDA = (2.55, -0.48)  # Lambda = 2.55 S^-0.48 mm^-1, S in mm/h of water
SNOW_DENSITY = 0.1           # a flake's density relative to water: its diameter is
#                              (1 / 0.1)^(1/3) = 2.15 times the melted drop's
WATER_INDEX = 1.33           # refractive index of water near 905 nm
# A drop returns like a mirror sphere: back-scatter cross-section R_F pi a^2, which a Lambertian
# patch covering the same share of the beam matches at reflectivity R_F / 4 (R_F: normal-incidence
# Fresnel reflectance). Snow is white and rough: Lambertian at its near-infrared albedo
# (about 0.8 near 0.9 um; Warren, "Optical properties of snow", Rev. Geophys. 1982).
RAIN_ECHO = ((WATER_INDEX - 1) / (WATER_INDEX + 1)) ** 2 / 4
SNOW_ECHO = 0.8
RAIN_MAX_MM = 8.0            # drops break up beyond about 8 mm (Pruppacher and Klett 1997)
SNOW_MAX_MM = 10.0           # melted diameter of the largest aggregates drawn
BEAM_EXIT_M = 0.01           # the beam's diameter at the sensor
BEAM_DIVERGENCE = 2e-3       # full angle, rad: diameter w(r) = 0.01 + 0.002 r m

# -- wet road (Lekner and Dorf 1988) ----------------------------------------------------------
TEXTURE_DEPTH_MM = 0.7       # mean texture depth of dense asphalt (sand patch, ISO 13473-1);
#                              heights taken uniform on [0, 2 MTD]: a film of h mm submerges the
#                              share min(1, h / (2 MTD)) of the footprint
WATER_ABSORPTION = 6.7       # 1/m near 905 nm (Hale and Querry 1973: k = 4.86e-7 at 0.9 um)
WET = np.isin(np.arange(256), (MATERIAL_ID["asphalt"], MATERIAL_ID["concrete"]))  # by id
GROUND_NORMAL_Z = 0.9        # a ground pixel's normal is within 25 deg of the sensor's up axis

# -- detection, intensity without a return model, the sweep -----------------------------------
COS_FLOOR = math.cos(math.radians(88.0))   # the most grazing hit the detection floor covers
NOMINAL_INTENSITY = 0.3      # a sensor without a return model: every hit this bright (road)
KMH = 1.0 / 3.6

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


# -- fog --------------------------------------------------------------------------------------
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


# -- rain and snow ----------------------------------------------------------------------------
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
        pi n0 g^2 / lam^3 (1e-6 turns mm^2 m^-3 into 1/m). Rain: 0.365 R^0.63 per km."""
        return math.pi * self.n0 * self.grow ** 2 / self.lam ** 3 * 1e-6

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


def rain(rate: float) -> Particles:
    """Marshall and Palmer (1948), J. Meteorology 5:165: N0 = 8000, Lambda = 4.1 R^-0.21."""
    return Particles(RAIN_N0, RAIN_LAMBDA[0] * rate ** RAIN_LAMBDA[1], 1.0, RAIN_ECHO,
                     RAIN_MAX_MM)


def snow(rate: float) -> Particles:
    """Gunn and Marshall (1958), J. Meteorology 15:452: N0 = 3800 S^-0.87, Lambda = 2.55 S^-0.48
    (melted diameters; a flake is (1 / SNOW_DENSITY)^(1/3) times wider)."""
    return Particles(SNOW_N0[0] * rate ** SNOW_N0[1], SNOW_LAMBDA[0] * rate ** SNOW_LAMBDA[1],
                     (1.0 / SNOW_DENSITY) ** (1.0 / 3.0), SNOW_ECHO, SNOW_MAX_MM)


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


def stream(seed: int, which: int) -> np.random.Generator:
    """The generator of one effect's draws for one scan."""
    return np.random.Generator(np.random.PCG64([seed, which]))


# -- wet road (Lekner and Dorf 1988) ----------------------------------------------------------
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


# -- the effects on one scan ------------------------------------------------------------------
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
        # Column firing times: a clockwise sweep (seen from above), t = 0 facing forward.
        self.column_time = -sensor.azimuths_deg / (360.0 * sensor.rotation_hz)
        self.forward = rot_y(sensor.pitch_deg).T @ np.array([1.0, 0.0, 0.0])  # ego +x, sensor

    # -- geometry: ego motion ----------------------------------------------------------------
    def moving_ranges(self, dist: np.ndarray, normal: np.ndarray, cos: np.ndarray,
                      speed_kmh: float) -> np.ndarray:
        """Each ray's range fired from where the ego is at its column's time: the hit surface
        taken as its plane (point and normal, turned to the sensor, from the clear cast), the ray
        from the moved origin meets it at R - n.d / n.u = R + n.d / cos (d: the displacement;
        grazing hits clipped to 5 |d|)."""
        step = speed_kmh * KMH * self.column_time            # (W,) metres along the ego's +x
        nd = (normal @ self.forward) * step                  # (H, W)
        reach = 5.0 * np.abs(step)
        shift = np.clip(nd / np.maximum(cos, 1e-9), -reach, reach)
        return dist + shift

    # -- the medium: fog, rain, snow, wet road -----------------------------------------------
    def medium(self, fx: Effects, seed: int, e: Echoes, clear_i: np.ndarray, mat: np.ndarray,
               cos: np.ndarray, normal: np.ndarray) -> Echoes:
        """The strongest echo per ray among the attenuated hard target, the fog's soft echo and
        the particles on the ray, kept where it reaches the detection floor. `clear_i` is the
        hard echo's clear intensity, 0 where there is none."""
        ground = None
        if fx.wet_road > 0:
            ground = self.ground(mat, normal, np.where(e.valid, e.r, np.inf)) & e.valid
        return self.through(fx, seed, e, clear_i, ground, cos)[0]

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
            wet = np.interp(cos[ground], *_wet_table(float(fx.wet_road), self.road_albedo))
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
            best, best_r, spur = self._fog(alpha, beta, hard_r, best)
        for p, which in pf:
            if spur is None:
                best, best_r, spur = best.copy(), hard_r.copy(), np.zeros(hard.shape, bool)
            self._particles(p, stream(seed, which), alpha, hard_r, best, best_r, spur)
        ok = best >= self.floor
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

    def _fog(self, alpha: float, beta: float, hard_r: np.ndarray, hard_p: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The stronger of the hard echo and the fog's soft echo per ray (power, range, and
        whether the fog's won); a soft echo outside the sensor's ranges is not seen."""
        s = self.sensor
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

    def _particles(self, p: Particles, gen: np.random.Generator, alpha: float,
                   hard_r: np.ndarray, best: np.ndarray, best_r: np.ndarray,
                   spur: np.ndarray) -> None:
        """Drops or flakes on the rays (in place): a Poisson process along every ray up to its
        target, at p.hits_per_m, drawn as one count over the image out to the particles' reach
        and thinned by each ray's own length (uniform pixel and position each). Each particle
        covers (D / w(r))^2 of the beam: its echo, that share times its reflectivity, takes the
        ray where it is the strongest; one as wide as the beam hides what is behind it."""
        s = self.sensor
        n_pix = hard_r.size
        reach = p.reach(self.floor, s.max_range)
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
        seen = (at >= s.min_range) & (power >= self.floor)
        block = share >= 1.0   # hides the target, the fog and the particles behind it
        if block.any():
            order = np.argsort(-at[block], kind="stable")   # nearest last: it wins
            bp, ba, bw = pix[block][order], at[block][order], power[block][order]
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

    def ground(self, mat: np.ndarray, normal: np.ndarray, hard_r: np.ndarray) -> np.ndarray:
        """Road and pavement pixels: asphalt or concrete, facing up, below the sensor by more
        than half its height (not a floor seen through a window)."""
        z = self.sensor.directions[..., 2] * np.where(np.isfinite(hard_r), hard_r, 0.0)
        return WET[mat] & (normal[..., 2] >= GROUND_NORMAL_Z) & (
            z < -0.5 * self.sensor.mount_height)

    # -- faults ------------------------------------------------------------------------------
    def faults(self, fx: Effects, seed: int, e: Echoes) -> Echoes:
        """Crosstalk points written over the image, then the lost lasers' rows emptied, then the
        rows a sensor with `beams` lasers would not have."""
        s = self.sensor
        r, valid, intensity, cls, inst, sem = (e.r, e.valid, e.intensity, e.cls, e.inst,
                                               e.semantic)
        if fx.crosstalk > 0:
            # Row k: point k's pixel, range and intensity (more points: more rows, same first).
            u = stream(seed, _CROSSTALK).random((fx.crosstalk, 3))
            n_pix = s.rows * s.columns
            pix = np.minimum((u[:, 0] * n_pix).astype(np.int64), n_pix - 1)
            rows, cols = pix // s.columns, pix % s.columns
            r, valid, cls, inst = r.copy(), valid.copy(), cls.copy(), inst.copy()
            # The other sensor's pulse comes at any time in the listening window: any range.
            r[rows, cols] = s.min_range + u[:, 1] * (s.max_range - s.min_range)
            valid[rows, cols] = True
            cls[rows, cols] = 0
            inst[rows, cols] = 0
            if sem is not None:
                sem = sem.copy()
                sem[rows, cols] = 0
            if intensity is not None:
                intensity = intensity.copy()
                intensity[rows, cols] = u[:, 2]
        if fx.beam_loss > 0:
            order = np.argsort(stream(seed, _BEAMS).random(s.rows), kind="stable")
            valid = valid.copy()
            valid[order[:min(fx.beam_loss, s.rows)]] = False
        if 0 < fx.beams < s.rows:
            kept = np.zeros(s.rows, bool)
            kept[kept_rows(s.rows, fx.beams)] = True
            valid = valid & kept[:, None]
        return Echoes(r, valid, intensity, cls, inst, sem)


def check_beams(space: Space, sensor: Sensor) -> None:
    """ConfigError naming dims.beams where a value is neither 0 (all lasers) nor a divisor of
    the sensor's lasers: ring selection (Robo3D's cross-sensor corruption) keeps every k-th."""
    dim = space.dims.get("beams")
    if dim is None:
        return
    rows = sensor.rows
    if not isinstance(dim, Categorical):
        raise ConfigError(f"{space.source}: dims.beams: give values = [...], lasers that divide "
                          f"{sensor.name}'s {rows}; a range lets a search pick ones that do not")
    for v in dim.grid():
        if int(v) and rows % int(v):
            allowed = [d for d in range(1, rows + 1) if rows % d == 0]
            raise ConfigError(f"{space.source}: dims.beams: {int(v)} lasers do not divide "
                              f"{sensor.name}'s {rows}; allowed: 0 (all), "
                              + ", ".join(map(str, allowed)))


def kept_rows(rows: int, beams: int) -> np.ndarray:
    """The rows a sensor of `beams` lasers keeps of `rows`, evenly spaced from the first."""
    return (np.arange(min(beams, rows)) * rows) // min(beams, rows)


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
