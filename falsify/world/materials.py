"""Surface materials: the table every triangle's material id points into.

A material has a reflectivity level (the fitted sensor model turns it into intensity and
return probability), a pass-through probability per surface crossing (foliage, chain-link), and
flags for glass (never returns: the ray goes on) and retro-reflective sheeting. How rays pass
porous surfaces is the sensor's business (falsify.sensor.raycast.cast_through).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


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
