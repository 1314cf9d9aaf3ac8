"""Surface materials and the ray caster that lets rays pass porous and glass surfaces.

Every triangle of a scene carries a material id. A material has a reflectivity (the fitted
sensor model turns it into intensity and return probability), a pass-through probability per
surface crossing (foliage, chain-link), and flags for glass (never returns: the ray goes on)
and retro-reflective sheeting. Whether a ray passes a porous triangle is decided by a hash of
(ray index, triangle id, seed), so a scan is reproducible and a composed scan (background cache
plus windowed cars) makes exactly the decisions a full re-cast of the merged scene makes.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from falsify.paths import RETURN_MODELS
from falsify.raycast import MeshCaster

MAX_LAYERS = 8  # porous surfaces a ray may pass before the caster stops (then it misses)
STEP = 2e-3  # metres a re-cast starts beyond the surface it passed


@dataclass(frozen=True)
class Material:
    """How one kind of surface answers the laser. `level` names the fitted reflectivity
    quantile it takes (see configs/returns/*.json); `pass_prob` is per surface crossing."""

    name: str
    level: str
    pass_prob: float = 0.0
    glass: bool = False
    retro: bool = False


MATERIALS: tuple[Material, ...] = (
    Material("asphalt", "road"),
    Material("concrete", "bright"),
    Material("grass", "mid"),
    Material("foliage", "mid", pass_prob=0.45),
    Material("hedge", "mid", pass_prob=0.25),
    Material("bark", "dark"),
    Material("facade", "mid"),
    Material("glass", "dark", pass_prob=1.0, glass=True),
    Material("metal", "bright"),
    Material("retro", "retro", retro=True),
    Material("paint dark", "dark"),
    Material("paint mid", "mid"),
    Material("paint bright", "bright"),
    Material("rubber", "dark"),
    Material("clothing", "mid"),
    Material("chain-link", "bright", pass_prob=0.7),
    Material("interior", "dark"),
    Material("soil", "mid"),
)
MATERIAL_ID: dict[str, int] = {m.name: i for i, m in enumerate(MATERIALS)}
PASS_PROB = np.array([m.pass_prob for m in MATERIALS], dtype=np.float64)
GLASS = np.array([m.glass for m in MATERIALS], dtype=bool)
RETRO = np.array([m.retro for m in MATERIALS], dtype=bool)
PAINTS: tuple[int, ...] = tuple(MATERIAL_ID[n] for n in ("paint dark", "paint mid",
                                                         "paint bright"))


def mid(name: str) -> int:
    """The id of material `name` (KeyError names an unknown material)."""
    return MATERIAL_ID[name]


def _mix(x: np.ndarray) -> np.ndarray:
    """splitmix64 finaliser on uint64 arrays (wrapping arithmetic)."""
    x = x ^ (x >> np.uint64(30))
    x = x * np.uint64(0xBF58476D1CE4E5B9)
    x = x ^ (x >> np.uint64(27))
    x = x * np.uint64(0x94D049BB133111EB)
    return x ^ (x >> np.uint64(31))


def unit_hash(ray: np.ndarray, face: np.ndarray, seed: int) -> np.ndarray:
    """A uniform number in [0, 1) fixed by (ray index, triangle id, seed)."""
    with np.errstate(over="ignore"):
        h = _mix(np.asarray(ray, dtype=np.uint64) * np.uint64(0x9E3779B97F4A7C15)
                 + np.uint64(seed & 0xFFFFFFFF))
        h = _mix(h ^ (np.asarray(face, dtype=np.uint64) + np.uint64(0x632BE59BD9B4E019)))
    return (h >> np.uint64(11)).astype(np.float64) * (1.0 / (1 << 53))


def cast_through(caster: MeshCaster, origin: np.ndarray, dirs: np.ndarray,
                 max_dist: np.ndarray | float, face_pass: np.ndarray, ray_ids: np.ndarray,
                 seed: int) -> tuple[np.ndarray, np.ndarray]:
    """First surface each ray returns from: porous and glass triangles are passed with their
    probability (hash-decided) and the ray is re-cast from just beyond them.

    `origin` is (3,) or (n, 3); `face_pass` the per-triangle pass probability. Returns range
    from `origin` (inf on a miss) and the triangle id (-1 on a miss).
    """
    n = len(dirs)
    max_d = np.broadcast_to(np.asarray(max_dist, dtype=np.float64), (n,)).copy()
    t, prim = caster.cast(origin, dirs, max_d)
    if n == 0 or not (face_pass > 0).any():
        return t, prim
    total = t.copy()
    for _ in range(MAX_LAYERS):
        hit = prim >= 0
        p = np.zeros(n)
        p[hit] = face_pass[prim[hit]]
        passed = hit & (p > 0)
        if passed.any():
            idx = np.flatnonzero(passed)
            passed[idx] = unit_hash(ray_ids[idx], prim[idx], seed) < p[idx]
        if not passed.any():
            return total, prim
        idx = np.flatnonzero(passed)
        start = total[idx] + STEP
        o = np.broadcast_to(origin, (n, 3))[idx] + dirs[idx] * start[:, None]
        t2, p2 = caster.cast(o, dirs[idx], np.maximum(max_d[idx] - start, 0.0))
        total[idx] = np.where(p2 >= 0, start + t2, np.inf)
        prim[idx] = p2
    hit = prim >= 0  # still inside foliage after MAX_LAYERS crossings: call it a miss
    p = np.zeros(n)
    p[hit] = face_pass[prim[hit]]
    stuck = hit & (p > 0) & (unit_hash(ray_ids, np.maximum(prim, 0), seed) < p)
    total[stuck], prim[stuck] = np.inf, -1
    return total, prim


@dataclass(frozen=True)
class ReturnModel:
    """The fitted sensor response (configs/returns/NAME.json, made by falsify.fit_returns).

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
