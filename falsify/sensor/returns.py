"""The sensor's return model: intensity and return probability per hit, fitted on real scans.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from falsify.paths import RETURN_MODELS
from falsify.world.materials import MATERIALS, RETRO


@dataclass(frozen=True)
class ReturnModel:
    """The fitted sensor response (configs/returns/NAME.json, made by falsify.jobs.fit_returns).

    intensity = reflectivity * cos(incidence)^cos_exp * exp(-range / atten_m), clipped to 1;
    P(return) = p_min + (p_max - p_min) * (1 - exp(-(intensity / i0)^k)); glass never returns;
    ``row_keep`` scales it per laser row; ``blocked`` holds, for the lowest rows, the return
    probability per azimuth bin left by the ego car's body (bins of 360 / len(row) degrees
    starting at +180, clockwise).
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

    @cached_property
    def material_reflectivity(self) -> np.ndarray:
        return np.array([self.reflectivity[m.level] for m in MATERIALS], dtype=np.float32)

    def intensity(self, mat: np.ndarray, cos: np.ndarray, rng: np.ndarray) -> np.ndarray:
        """float32 intensity in [0, 1] per hit."""
        refl = self.material_reflectivity[mat]
        c = np.clip(np.asarray(cos, np.float32), 0.0, 1.0)
        gain = np.where(RETRO[mat], np.float32(self.retro_gain), c ** np.float32(self.cos_exp))
        att = np.exp(np.asarray(rng, np.float32) * np.float32(-1.0 / self.atten_m))
        return np.clip(refl * gain * att, 0.0, 1.0)

    def p_return(self, intensity: np.ndarray) -> np.ndarray:
        x = np.maximum(intensity, 0.0) / np.float32(self.i0)
        return self.p_min + (self.p_max - self.p_min) * (1.0 - np.exp(-(x ** np.float32(self.k))))

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


def load_return_model(name: str) -> ReturnModel:
    """Read a fitted return model by name from configs/returns/."""
    raw = json.loads((RETURN_MODELS / f"{name}.json").read_text())
    p = raw["params"]
    return ReturnModel(name=name, reflectivity=dict(p["reflectivity"]), cos_exp=p["cos_exp"],
                       atten_m=p["atten_m"], p_min=p["p_min"], p_max=p["p_max"], i0=p["i0"],
                       k=p["k"], retro_gain=p["retro_gain"], row_keep=tuple(p["row_keep"]),
                       blocked_rows=tuple(p["blocked_rows"]),
                       blocked=tuple(tuple(r) for r in p["blocked"]))
