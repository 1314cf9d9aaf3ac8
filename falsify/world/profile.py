"""A world profile: what training scenes draw from real places, fitted on labelled real scans by
`falsify fit-world` (falsify.jobs.fit_world) and used by `falsify dataset --world PROFILE`.

A profile holds, per fit scan, what the sensor saw of its own pose (the road plane's pitch and
the sensor's height above it, in the sensor frame) and how many cars stood in its front 90
degrees. A scene draws one fit scan's pose and adds the difference to the world's own plus
Gaussian jitter (a kernel density estimate of the fit scans, bandwidth by Silverman's rule), and
draws its car count from the fit scans' counts. Its streets keep each parked car with
probability ``parked_keep``, the share that brings the world's cars in view nearest the fit
scans' (fitted by `fit-world` over PARKED_KEEP_GRID). A profile with ``places`` (version 2)
makes each street stand for one fit scan's place (falsify.world.places): its ego pose and its
roadside, and (version 3, places with their road edges) its road's width; a space takes such
streets with `[dims.background] world = "NAME"`.
"""

from __future__ import annotations

import functools
import json
import math
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from falsify.errors import ConfigError
from falsify.paths import CONFIGS, config_path
from falsify.world.places import Place, place_index, place_pose, place_street
from falsify.world.streets import Background, build_background, thin_parked_cars

WORLDS = CONFIGS / "worlds"   # the fitted profiles that ship

PROFILE_VERSION = 3
READS_VERSIONS = (1, 2, 3)
POSE_KEYS = ("pitch_deg", "height_m", "cars_front")
PARKED_KEEP_GRID = (1.0, 0.75, 0.5, 0.35, 0.25, 0.15, 0.1, 0.05, 0.0)


@dataclass(frozen=True)
class WorldProfile:
    """Per-scan measurements of real places, drawn from by training scenes.

    ``pitch_deg``: the road plane's slope along the sensor's x axis seen from the sensor,
    atan(dz/dx) (positive: the road rises ahead); ``height_m``: the sensor's height above that
    plane at its foot; ``cars_front``: cars (SemanticKITTI car or moving-car instances) in the
    front 90 degrees within the fit's range. ``base_*``: the same measured on the world itself,
    so a draw adds ``real - base``. ``parked_keep``: the probability each of a street's parked
    cars stays (1: the streets as built).
    """

    name: str
    scans: tuple[str, ...]
    pitch_deg: tuple[float, ...]
    height_m: tuple[float, ...]
    cars_front: tuple[int, ...]
    base_pitch_deg: float = 0.0
    base_height_m: float = 1.73
    pitch_jitter_deg: float = 0.25
    height_jitter_m: float = 0.03
    parked_keep: float = 1.0
    places: tuple[Place, ...] = ()

    def __post_init__(self) -> None:
        n = len(self.scans)
        for key in POSE_KEYS:
            if len(getattr(self, key)) != n:
                raise ConfigError(f"world profile {self.name!r}: {key} has "
                                  f"{len(getattr(self, key))} values for {n} scans")
        if n == 0:
            raise ConfigError(f"world profile {self.name!r}: no scans")
        values = [*self.pitch_deg, *self.height_m, self.base_pitch_deg, self.base_height_m,
                  self.pitch_jitter_deg, self.height_jitter_m]
        if not all(math.isfinite(v) for v in values):
            raise ConfigError(f"world profile {self.name!r}: pitch and height values must be "
                              "finite numbers")
        if any(abs(p) > 15.0 for p in self.pitch_deg):
            raise ConfigError(f"world profile {self.name!r}: pitch_deg must be within ±15 degrees")
        if any(not 0.5 <= h <= 4.0 for h in self.height_m):
            raise ConfigError(f"world profile {self.name!r}: height_m must be in 0.5..4.0 m")
        if any(c < 0 or c > 40 for c in self.cars_front):
            raise ConfigError(f"world profile {self.name!r}: cars_front must be in 0..40")
        if self.pitch_jitter_deg < 0 or self.height_jitter_m < 0:
            raise ConfigError(f"world profile {self.name!r}: jitters must be >= 0")
        if not (isinstance(self.parked_keep, int | float) and 0.0 <= self.parked_keep <= 1.0):
            raise ConfigError(f"world profile {self.name!r}: parked_keep must be a number in "
                              f"0..1, not {self.parked_keep!r}")

    def draw_pose(self, rng: np.random.Generator) -> tuple[float, float]:
        """(pitch offset in degrees, height offset in metres) for one scene: one fit scan's
        measurement less the world's own, plus jitter; (0, 0) with places, whose streets carry
        their place's pose themselves."""
        if self.places:
            return 0.0, 0.0
        k = int(rng.integers(len(self.scans)))
        dp = self.pitch_deg[k] - self.base_pitch_deg + rng.normal(0.0, self.pitch_jitter_deg)
        dh = self.height_m[k] - self.base_height_m + rng.normal(0.0, self.height_jitter_m)
        return float(dp), float(dh)

    def draw_cars(self, rng: np.random.Generator, most: int) -> int:
        """A car count for one scene: a fit scan's, at most `most`."""
        return min(int(self.cars_front[int(rng.integers(len(self.scans)))]), most)

    def background_source(self) -> Callable[[int], Background] | None:
        """What a Simulator builds this world's streets with: each street standing for a place
        (with places), the streets with their parked cars thinned, or None (the streets as
        built) where the profile keeps them all."""
        if self.places:
            return functools.partial(profiled_street, profile=self)
        if self.parked_keep >= 1.0:
            return None
        return functools.partial(thinned_street, keep=self.parked_keep)

    def place_name(self, bg_id: int) -> str | None:
        """The real place street `bg_id` stands for (its fit scan's name); None without places."""
        return self.places[place_index(bg_id, len(self.places))].name if self.places else None

    def street(self, bg_id: int) -> Background:
        """Street `bg_id` of this world: standing for place place_index(bg_id) with its pose,
        its parked cars thinned to parked_keep."""
        if not self.places:
            return thinned_street(bg_id, self.parked_keep)
        place = self.places[place_index(bg_id, len(self.places))]
        pose = place_pose(bg_id, place, self.base_pitch_deg, self.base_height_m,
                          self.pitch_jitter_deg, self.height_jitter_m)
        return thin_parked_cars(place_street(bg_id, place, pose), self.parked_keep)

    def to_json(self) -> dict:
        out = {"version": PROFILE_VERSION, **asdict(self)}
        out["places"] = [p.to_json() for p in self.places]
        return out


@functools.lru_cache(maxsize=2)
def profiled_street(bg_id: int, profile: WorldProfile) -> Background:
    """Street `bg_id` of `profile` (module level, so a profile's source pickles into workers;
    cached like the streets themselves)."""
    return profile.street(bg_id)


def thinned_street(bg_id: int, keep: float) -> Background:
    """Street `bg_id` with its parked cars thinned to `keep` (a module-level function, so a
    profile's background source pickles into workers)."""
    return thin_parked_cars(build_background(bg_id), keep)


def profile_file(path: str | Path) -> Path:
    """The file a profile's name or path means: a file, a bundled one's path such as
    configs/worlds/NAME.json, or its NAME."""
    p = config_path(path)
    if not p.exists() and not p.suffix and (WORLDS / f"{p.name}.json").is_file():
        p = WORLDS / f"{p.name}.json"
    return p


def load_profile(path: str | Path) -> WorldProfile:
    """Read a profile written by `falsify fit-world` (a file, a bundled one's path such as
    configs/worlds/NAME.json, or its NAME); ConfigError names the file and the key."""
    p = profile_file(path)
    if not p.is_file():
        raise ConfigError(f"--world {p}: no such file (write one with `falsify fit-world`)")
    try:
        raw = json.loads(p.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ConfigError(f"--world {p}: not JSON ({exc})") from exc
    if not isinstance(raw, dict) or raw.get("version") not in READS_VERSIONS:
        raise ConfigError(f"--world {p}: not a world profile of version "
                          f"{' or '.join(map(str, READS_VERSIONS))}")
    fields = set(WorldProfile.__dataclass_fields__)
    unknown = sorted(set(raw) - fields - {"version", "fit"})
    if unknown:
        raise ConfigError(f"--world {p}: unknown key {unknown[0]!r} (allowed: "
                          f"{', '.join(sorted(fields))})")
    missing = sorted(k for k in ("name", "scans", *POSE_KEYS) if k not in raw)
    if missing:
        raise ConfigError(f"--world {p}: missing key {missing[0]!r}")
    try:
        kw = {k: v for k, v in raw.items() if k in fields}
        for k in ("scans", "pitch_deg", "height_m", "cars_front"):
            kw[k] = tuple(kw[k])
        kw["cars_front"] = tuple(int(c) for c in kw["cars_front"])
        kw["pitch_deg"] = tuple(float(v) for v in kw["pitch_deg"])
        kw["height_m"] = tuple(float(v) for v in kw["height_m"])
        kw["places"] = tuple(Place.from_json(r, f"--world {p}: places[{k}]")
                             for k, r in enumerate(kw.get("places", ())))
        return WorldProfile(**kw)
    except (TypeError, ValueError, ConfigError) as exc:
        raise ConfigError(f"--world {p}: {exc}") from exc
