"""The sensor's return model: intensity and return probability per hit, fitted on real scans.
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from statistics import NormalDist

import numpy as np

from falsify.errors import ConfigError
from falsify.paths import RETURN_MODELS
from falsify.semantic import TRAIN_CLASSES, train_ids
from falsify.world.materials import MATERIALS, RETRO

SCORE_LEVELS = 4096   # a point's own normal score: one of this many equiprobable quantiles
NORMAL_LEVELS = np.array([NormalDist().inv_cdf((k + 0.5) / SCORE_LEVELS)
                          for k in range(SCORE_LEVELS)], np.float32)


@dataclass(frozen=True)
class ClassReturns:
    """Per SemanticKITTI training class (index = train id): the corrected reflectivity at the
    standard-normal scores `z` (its quantile function), the share of its spread that lies
    between instances, and P(return). A hit's score is a Gaussian copula,
    sqrt(s) * z_instance + sqrt(1 - s) * z_point, so each class keeps its fitted marginal and
    each object its own shade (a Gaussian copula: Nelsen, "An Introduction to Copulas", 2006,
    sec. 2.3; the sum of independent standard normals weighted to unit variance is standard
    normal, so the class's quantile function at it draws the fitted distribution)."""

    z: tuple[float, ...]
    reflectivity: tuple[tuple[float, ...], ...]
    instance_share: tuple[float, ...]
    p_return: tuple[float, ...]
    dropout_by_class: bool = True

    @cached_property
    def _table(self) -> np.ndarray:
        return np.asarray(self.reflectivity, np.float32)

    @cached_property
    def _share(self) -> np.ndarray:
        return np.asarray(self.instance_share, np.float32)

    @cached_property
    def _fine(self) -> np.ndarray:
        """(classes * SCORE_LEVELS,) each class's reflectivity at every level of NORMAL_LEVELS:
        a stuff point's shade is one lookup."""
        n = len(self.reflectivity)
        train = np.repeat(np.arange(n), SCORE_LEVELS)
        return self.reflectivity_at(train, np.tile(NORMAL_LEVELS, n))

    @cached_property
    def _median(self) -> np.ndarray:
        """(classes,) each class's reflectivity at score 0: the shade of every hit without draws."""
        n = len(self.reflectivity)
        return self.reflectivity_at(np.arange(n), np.zeros(n, np.float32))

    def shades(self, train: np.ndarray, instance: np.ndarray,
               draws: np.random.Generator | None) -> np.ndarray:
        """float32 reflectivity per hit: each class's median without draws. A point's own score
        is one of SCORE_LEVELS equiprobable normal quantiles; a thing's instance (id > 0) adds
        its shared score, weighted by the class's instance share."""
        if draws is None:
            return self._median.take(train)
        k = (draws.random(train.shape, dtype=np.float32) * SCORE_LEVELS).astype(np.int32)
        np.minimum(k, SCORE_LEVELS - 1, out=k)
        refl = self._fine.take(train * np.int32(SCORE_LEVELS) + k)
        things = np.flatnonzero(instance > 0)
        if len(things):
            inst = instance[things]
            ids = np.unique(inst)   # unique, then searchsorted: return_inverse costs twice as much
            z_inst = draws.standard_normal(len(ids), dtype=np.float32)[np.searchsorted(ids, inst)]
            share = self._share[train[things]]
            z = np.sqrt(share) * z_inst + np.sqrt(1.0 - share) * NORMAL_LEVELS[k[things]]
            refl[things] = self.reflectivity_at(train[things], z)
        return refl

    def reflectivity_at(self, train: np.ndarray, z: np.ndarray) -> np.ndarray:
        """Each hit's class quantile function at its score, linear between the table's scores
        and held at its ends."""
        t = self._table
        k = t.shape[1]
        step = np.float32((self.z[-1] - self.z[0]) / (k - 1))
        pos = (np.asarray(z, np.float32) - np.float32(self.z[0])) / step
        np.clip(pos, 0.0, np.float32(k - 1.0001), out=pos)
        lo = pos.astype(np.int32)
        pos -= lo
        base = np.asarray(train, np.int32) * np.int32(k) + lo
        a = t.take(base)
        b = t.take(base + 1)
        return a + (b - a) * pos


@dataclass(frozen=True)
class ReturnModel:
    """The fitted sensor response (configs/returns/NAME.json, made by falsify.jobs.fit_returns).

    intensity = reflectivity * cos(incidence)^cos_exp * exp(-range / atten_m), clipped to 1;
    P(return) = p_min + (p_max - p_min) * (1 - exp(-(intensity / i0)^k)); glass never returns;
    ``row_keep`` scales it per laser row; ``blocked`` holds, for the lowest rows, the return
    probability per azimuth bin left by the ego car's body (bins of 360 / len(row) degrees
    starting at +180, clockwise). With `classes` (fitted on labelled scans) the reflectivity
    (and, where it drops by class, P(return)) is the hit's class's instead of its material's.

    The form is the radiometric model of Kashani et al., "A Review of LIDAR Radiometric
    Processing", Sensors 15(11), 2015 (the range equation for an extended Lambertian target:
    received power ~ reflectance * cos(incidence) / range^2), with the cosine's exponent and an
    exponential range factor fitted, since KITTI's remission is already corrected for range by
    the sensor.
    """

    name: str
    reflectivity: dict[str, float]
    cos_exp: float
    atten_m: float
    p_min: float
    p_max: float
    i0: float
    k: float
    retro_gain: float
    row_keep: tuple[float, ...]
    blocked_rows: tuple[int, ...]
    blocked: tuple[tuple[float, ...], ...]
    classes: ClassReturns | None = None

    @cached_property
    def material_reflectivity(self) -> np.ndarray:
        return np.array([self.reflectivity[m.level] for m in MATERIALS], dtype=np.float32)

    def intensity(self, mat: np.ndarray, cos: np.ndarray, rng: np.ndarray,
                  semantic: np.ndarray | None = None, instance: np.ndarray | None = None,
                  draws: np.random.Generator | None = None) -> np.ndarray:
        """float32 intensity in [0, 1] per hit: by class (raw SemanticKITTI ids `semantic`,
        shades drawn from `draws`) where the model has classes, else by material."""
        c = np.clip(np.asarray(cos, np.float32), 0.0, 1.0)
        att = np.exp(np.asarray(rng, np.float32) * np.float32(-1.0 / self.atten_m))
        if self.classes is not None and semantic is not None:
            train = train_ids(np.asarray(semantic)).astype(np.int32)
            inst = np.zeros(train.shape, np.int64) if instance is None else instance
            refl = self.classes.shades(train, inst, draws)
            return np.clip(refl * c ** np.float32(self.cos_exp) * att, 0.0, 1.0)
        refl = self.material_reflectivity[mat]
        gain = np.where(RETRO[mat], np.float32(self.retro_gain), c ** np.float32(self.cos_exp))
        return np.clip(refl * gain * att, 0.0, 1.0)

    def p_return(self, intensity: np.ndarray) -> np.ndarray:
        x = np.maximum(intensity, 0.0) / np.float32(self.i0)
        return self.p_min + (self.p_max - self.p_min) * (1.0 - np.exp(-(x ** np.float32(self.k))))

    def return_probability(self, intensity: np.ndarray, semantic: np.ndarray | None) -> np.ndarray:
        """P(return) per hit before the row factor: the class's where the model drops by class,
        else from the expected intensity (p_return)."""
        c = self.classes
        if c is not None and c.dropout_by_class and semantic is not None:
            return np.asarray(c.p_return, np.float32)[train_ids(np.asarray(semantic))]
        return self.p_return(intensity)

    def keep_map(self, rows: int, azimuths_deg: np.ndarray) -> np.ndarray:
        """(rows, W) per-pixel factor of the return probability: the laser's own factor per
        row (for the 64-row layout it was fitted on) times the ego body's shadow."""
        out = np.ones((rows, len(azimuths_deg)))
        if rows == len(self.row_keep):
            out *= np.asarray(self.row_keep)[:, None]
        for r, probs in zip(self.blocked_rows, self.blocked, strict=True):
            if r >= rows:
                continue
            bins = len(probs)
            b = np.floor(((180.0 - azimuths_deg) % 360.0) / (360.0 / bins)).astype(int) % bins
            out[r] = np.asarray(probs)[b]
        return out


def _dropout_kind(value) -> bool:
    """True where a class table's `dropout` is "class", False for "intensity"."""
    if value not in ("class", "intensity"):
        raise ValueError(f"classes.dropout: {value!r}; allowed: class, intensity")
    return value == "class"


def side_generator(rng: np.random.Generator) -> np.random.Generator:
    """A generator seeded from `rng`'s state without drawing from it: the shades a scan draws
    leave its own draws (dropout, noise) as a model without classes would make them."""
    state = json.dumps(rng.bit_generator.state, sort_keys=True, default=str).encode()
    return np.random.default_rng(np.frombuffer(hashlib.sha256(state).digest(), np.uint32))


def load_return_model(name: str) -> ReturnModel:
    """Read a fitted return model: by name from configs/returns/, or a .json file's path; a
    ConfigError names a file that cannot be read or is not one."""
    path = Path(name) if name.endswith(".json") else RETURN_MODELS / f"{name}.json"
    if not name.endswith(".json") and not path.is_file():
        allowed = ", ".join(sorted(q.stem for q in RETURN_MODELS.glob("*.json")))
        raise ConfigError(f"returns: {name!r} is not a fitted return model; allowed: {allowed} "
                          "(configs/returns/) or a .json file that `falsify fit-returns` wrote")
    try:
        raw = json.loads(path.read_text())
        return _model(name if not name.endswith(".json") else str(raw.get("name", path.stem)),
                      raw["params"])
    except OSError as exc:
        raise ConfigError(f"returns: cannot read {path} ({exc.strerror})") from None
    except (json.JSONDecodeError, KeyError, TypeError, ValueError, AttributeError) as exc:
        raise ConfigError(f"returns: {path} is not a return model that `falsify fit-returns` "
                          f"wrote ({type(exc).__name__}: {exc})") from None


# The scalar params' allowed values (lowest, highest, lowest excluded): the intensity divides by
# atten_m, P(return) by i0 and raises to k, so those must be positive (0 or NaN gave a traceback
# or a silently empty scan).
PARAM_BOUNDS = {"cos_exp": (0.0, math.inf, False), "atten_m": (0.0, math.inf, True),
                "p_min": (0.0, 1.0, False), "p_max": (0.0, 1.0, False),
                "i0": (0.0, math.inf, True), "k": (0.0, math.inf, True),
                "retro_gain": (0.0, math.inf, False)}


def _check_params(p: dict) -> None:
    """ValueError naming the first scalar param or reflectivity level outside its allowed
    values (PARAM_BOUNDS; a level: a finite number >= 0)."""
    for key, (lo, hi, open_lo) in PARAM_BOUNDS.items():
        v = p[key]
        if (isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v)
                or v < lo or (open_lo and v == lo) or v > hi):
            span = (f"{'>' if open_lo else '>='} {lo:g}" if hi == math.inf
                    else f"in [{lo:g}, {hi:g}]")
            raise ValueError(f"params.{key}: {v!r}; allowed: a finite number {span}")
    for level, v in dict(p["reflectivity"]).items():
        if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v) or v < 0:
            raise ValueError(f"params.reflectivity.{level}: {v!r}; allowed: a finite number "
                             ">= 0")


def _model(name: str, p: dict) -> ReturnModel:
    """The model from a JSON document's params; ValueError names a scalar param out of its
    bounds or a class table that is not one row per training class over evenly spaced rising
    scores."""
    _check_params(p)
    c = p.get("classes")
    classes = None
    if c is not None:
        z = np.asarray(c["z"], np.float64)
        rows = [tuple(float(v) for v in r) for r in c["reflectivity"]]
        n = len(TRAIN_CLASSES)
        if len(z) < 2 or not np.allclose(np.diff(z), z[1] - z[0]) or z[1] <= z[0]:
            raise ValueError("classes.z must be evenly spaced rising scores")
        if len(rows) != n or any(len(r) != len(z) for r in rows) or \
                len(c["instance_share"]) != n or len(c["p_return"]) != n:
            raise ValueError(f"classes: one row of {len(z)} values per training class ({n})")
        classes = ClassReturns(z=tuple(float(v) for v in z), reflectivity=tuple(rows),
                               instance_share=tuple(float(v) for v in c["instance_share"]),
                               p_return=tuple(float(v) for v in c["p_return"]),
                               dropout_by_class=_dropout_kind(c.get("dropout", "class")))
    return ReturnModel(name=name, reflectivity=dict(p["reflectivity"]), cos_exp=p["cos_exp"],
                       atten_m=p["atten_m"], p_min=p["p_min"], p_max=p["p_max"], i0=p["i0"],
                       k=p["k"], retro_gain=p["retro_gain"], row_keep=tuple(p["row_keep"]),
                       blocked_rows=tuple(p["blocked_rows"]),
                       blocked=tuple(tuple(r) for r in p["blocked"]), classes=classes)
