"""Streets fitted to real places: each street takes one fit scan's place (`Place`, measured by
`falsify fit-world` from its SemanticKITTI labels) and draws its ego pose and roadside from it,
so the world holds hard places as the road does, not one average street.

What a place sets on its street:
- the ego's pitch and height over the road as the fit scan's sensor saw them (plus a small
  per-street jitter), added to the ego's pose on the street's own terrain;
- the roadside near the kerb: sidewalks as narrow as the place's clutter is near, a green
  strip (bushes and hedge runs) right behind them as dense as the place's vegetation within
  30 m, and unlabeled clutter (boxes, bins, containers, low structures: SemanticKITTI's
  "unlabeled") as much as the place holds; fences by the place's fence share.
Everything else (road, buildings, trees, parked cars) is the street's own. The coefficients
that map a place's shares to densities (GREEN_PER_SHARE, CLUTTER_PER_SHARE, FENCE_PER_SHARE)
were set on the fit split, by the shares the streets then show (docs/experiments/
streets_as_hard.md).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields, replace

import numpy as np

from falsify.classes import UNKNOWN
from falsify.errors import ConfigError
from falsify.semantic import RAW_ID
from falsify.world import buildings, shapes, vegetation
from falsify.world.materials import mid
from falsify.world.street_layout import FREE_ZONE, _Layout, _layout, _rect, _rng, _Street

BANDS_M: tuple[float, ...] = (0.0, 15.0, 30.0, 60.0)   # range bands a share is measured in
GROUPS: tuple[str, ...] = ("road", "sidewalk", "terrain", "vegetation", "building", "fence",
                           "pole", "car", "other_vehicle", "unlabeled")
PLACE_STREAM = 23          # the random stream of a street's place draws
NEAR_CLUTTER_M = 8.0       # a side whose clutter stands nearer than this gets a narrow sidewalk
GREEN_PER_SHARE = 3.0      # kerb-length coverage of the green strip per unit vegetation share
CLUTTER_PER_SHARE = 1.2    # clutter objects per metre of roadside per unit unlabeled share
FENCE_PER_SHARE = 8.0      # kerb-length coverage of fences per unit fence share
ALONG_X: tuple[float, float] = (-40.0, 110.0)   # where a place's roadside is built
ROAD_HALF_M: tuple[float, float] = (3.0, 15.0)   # the road half-widths a place's edges may set
EGO_KERB_M = 1.5   # the ego's centre keeps this far inside either kerb (it is 1.9 m wide)


@dataclass(frozen=True)
class Place:
    """One real scan's place as a street draws it: the sensor's pitch (degrees, road rising
    ahead positive) and height (m) over the road plane, the share of its front-90-degree points
    per class group (GROUPS) in each range band (BANDS_M), and how near its roadside clutter
    stands to the sensor's line on the left and right (m, 5th percentile of |y| at x 5..30),
    and where the road ends on each side (m from the sensor's line; None in profiles measured
    before, whose streets keep their own road width)."""

    name: str
    pitch_deg: float
    height_m: float
    shares: tuple[tuple[float, ...], ...]   # per GROUPS entry, one share per band
    clutter_left_m: float
    clutter_right_m: float
    edge_left_m: float | None = None
    edge_right_m: float | None = None

    def __post_init__(self) -> None:
        if len(self.shares) != len(GROUPS):
            raise ConfigError(f"place {self.name!r}: shares must hold {', '.join(GROUPS)}")
        for group, vals in zip(GROUPS, self.shares, strict=True):
            if len(vals) != len(BANDS_M) - 1 or not all(
                    math.isfinite(v) and 0.0 <= v <= 1.0 for v in vals):
                raise ConfigError(f"place {self.name!r}: shares.{group} must be "
                                  f"{len(BANDS_M) - 1} shares in 0..1, one per range band")
        for key in ("pitch_deg", "height_m", "clutter_left_m", "clutter_right_m"):
            if not math.isfinite(getattr(self, key)):
                raise ConfigError(f"place {self.name!r}: {key} must be a finite number")
        for key in ("edge_left_m", "edge_right_m"):
            v = getattr(self, key)
            if v is not None and not (math.isfinite(v) and v >= 0.0):
                raise ConfigError(f"place {self.name!r}: {key} must be a distance >= 0 m")
        if (self.edge_left_m is None) != (self.edge_right_m is None):
            raise ConfigError(f"place {self.name!r}: edge_left_m and edge_right_m go together")

    def near(self, group: str) -> float:
        """The group's share within 30 m (the mean of the first two bands)."""
        return float(np.mean(self.share(group)[:2]))

    def share(self, group: str) -> tuple[float, ...]:
        """The group's share per range band."""
        return self.shares[GROUPS.index(group)]

    def to_json(self) -> dict:
        out = {k: v for k, v in asdict(self).items() if v is not None}
        out["shares"] = {g: [round(v, 5) for v in vals]
                         for g, vals in zip(GROUPS, self.shares, strict=True)}
        return out

    @classmethod
    def from_json(cls, raw: dict, where: str) -> Place:
        """A place from its JSON; ConfigError names the key."""
        if not isinstance(raw, dict):
            raise ConfigError(f"{where}: a place must be a table")
        names = {f.name for f in fields(cls)}
        unknown = sorted(set(raw) - names)
        if unknown:
            raise ConfigError(f"{where}: unknown key {unknown[0]!r} (allowed: "
                              f"{', '.join(sorted(names))})")
        missing = sorted(names - set(raw) - {"edge_left_m", "edge_right_m"})
        if missing:
            raise ConfigError(f"{where}: missing key {missing[0]!r}")
        got = raw["shares"]
        if not isinstance(got, dict) or set(got) != set(GROUPS):
            have = sorted(got) if isinstance(got, dict) else []
            wrong = sorted(set(have) ^ set(GROUPS))
            raise ConfigError(f"{where}: shares must be a table of {', '.join(GROUPS)}"
                              + (f" (not {wrong[0]!r})" if wrong else ""))
        try:
            shares = tuple(tuple(float(v) for v in got[g]) for g in GROUPS)
            return cls(name=str(raw["name"]), pitch_deg=float(raw["pitch_deg"]),
                       height_m=float(raw["height_m"]), shares=shares,
                       clutter_left_m=float(raw["clutter_left_m"]),
                       clutter_right_m=float(raw["clutter_right_m"]),
                       **{k: float(raw[k]) for k in ("edge_left_m", "edge_right_m")
                          if k in raw})
        except (TypeError, ValueError, AttributeError) as exc:
            raise ConfigError(f"{where}: {exc}") from exc


def place_index(bg_id: int, n: int) -> int:
    """Which of n places street `bg_id` takes: consecutive ids walk the places with a stride
    near n / golden ratio that is coprime with n, so any n consecutive streets take every place
    once and a few consecutive ones spread over the places' order (their sequences)."""
    stride = max(1, round(n * 0.381966))
    while math.gcd(stride, n) != 1:
        stride += 1
    return (int(bg_id) * stride) % n


def place_pose(bg_id: int, place: Place, base_pitch_deg: float, base_height_m: float,
               pitch_jitter_deg: float, height_jitter_m: float) -> tuple[float, float]:
    """(pitch offset in degrees, height offset in m) the street's ego takes: the place's less
    the world's own, plus a jitter fixed per street."""
    rng = _rng(bg_id, PLACE_STREAM)
    dp = place.pitch_deg - base_pitch_deg + float(rng.normal(0.0, pitch_jitter_deg))
    dh = place.height_m - base_height_m + float(rng.normal(0.0, height_jitter_m))
    return dp, dh


def road_half_width(place: Place) -> float | None:
    """The half-width of the road a place's street takes: the mean of where its road ends on
    the two sides (the street is symmetric about the sensor's line), within ROAD_HALF_M; None
    for a place measured without its edges."""
    if place.edge_left_m is None or place.edge_right_m is None:
        return None
    return float(np.clip((place.edge_left_m + place.edge_right_m) / 2.0, *ROAD_HALF_M))


def road_offset(place: Place) -> float:
    """Where across its road (m, +left of the crown) the street's ego stands so that each kerb
    is as far from it as the place's road edge on that side: half the right edge less the left
    (a road widened to ROAD_HALF_M widens evenly), at least EGO_KERB_M inside both kerbs; 0
    for a place measured without its edges."""
    half = road_half_width(place)
    if half is None or place.edge_left_m is None or place.edge_right_m is None:
        return 0.0
    reach = max(half - EGO_KERB_M, 0.0)
    return float(np.clip((place.edge_right_m - place.edge_left_m) / 2.0, -reach, reach))


def place_layout(bg_id: int, place: Place) -> _Layout:
    """The street's layout with its sidewalks narrowed where the place's clutter is near and
    its road as wide as the place's, the whole length (no wider stretch at the test site)."""
    lay = _layout(bg_id)
    rng = _rng(bg_id, PLACE_STREAM + 1)
    sidewalk = list(lay.sidewalk)
    for k, near in enumerate((place.clutter_left_m, place.clutter_right_m)):
        if near < NEAR_CLUTTER_M:
            sidewalk[k] = float(rng.uniform(1.5, 2.2))
    sw = (sidewalk[0], sidewalk[1])
    half = road_half_width(place)
    if half is None:
        return replace(lay, sidewalk=sw, terrain=replace(lay.terrain, sidewalk=sw))
    return replace(lay, half_width=half, sidewalk=sw,
                   terrain=replace(lay.terrain, half_width=half, sidewalk=sw, narrow=0.0))


def free_zone(lay: _Layout):
    """The test site kept clear of the street's objects: FREE_ZONE, cut to the road between the
    kerbs, so the place's roadside stands right beside the road as it does on the place's own
    (a sampled car beyond the kerb may meet it: an invalid sample, as in the real scan)."""
    (x0, x1), (y0, y1) = FREE_ZONE
    half = lay.terrain.narrowest_kerb(x0, x1)
    return (x0, x1), (max(y0, -half), min(y1, half))


def roadside_step(place: Place):
    """The placement step (streets.STEPS' signature) that builds the place's roadside."""
    def step(st: _Street, lay: _Layout, bg_id: int) -> None:
        _green_strip(st, lay, bg_id, place)
        _fences(st, lay, bg_id, place)
        _clutter(st, lay, bg_id, place)
    return step


def _runs(rng: np.random.Generator, coverage: float, mean_len: float):
    """(xa, xb) stretches along ALONG_X covering about `coverage` of it."""
    if coverage <= 0.0:
        return
    x = ALONG_X[0] + float(rng.uniform(0.0, mean_len))
    while x < ALONG_X[1]:
        length = float(rng.uniform(0.5, 1.5)) * mean_len
        gap = length * (1.0 - min(coverage, 0.98)) / max(min(coverage, 0.98), 0.02)
        yield x, min(x + length, ALONG_X[1])
        x += length + gap * float(rng.uniform(0.5, 1.5))


def _green_strip(st: _Street, lay: _Layout, bg_id: int, place: Place) -> None:
    """Bushes and hedge runs right behind the sidewalks, as dense as the place is green."""
    rng = _rng(bg_id, PLACE_STREAM + 2)
    t = lay.terrain
    coverage = min(1.0, GREEN_PER_SHARE * place.near("vegetation"))
    for side, sw in ((1, lay.sidewalk[0]), (-1, lay.sidewalk[1])):
        n = 0
        for xa, xb in _runs(rng, coverage, 12.0):
            for pa, pb in t.straight_kerb(xa, xb):
                if pb - pa < 2.0:
                    continue
                y_in = side * (float(t.kerb(pa)) + sw + float(rng.uniform(0.1, 0.8)))
                if rng.random() < 0.4:
                    lo, hi = sorted((y_in, y_in + side * 1.3))
                    if st.fits(_rect(pa, pb, lo, hi), 0.0):
                        vegetation.hedge(st, t, rng, pa, pb, y_in, side, f"place hedge {n}")
                        n += 1
                    continue
                u0 = abs(y_in) - float(t.kerb(pa)) - sw
                density = float(rng.uniform(0.3, 0.8))
                n += vegetation.bushes(st, t, rng, side, (u0, u0 + 3.0), (pa, pb), density)


def _fences(st: _Street, lay: _Layout, bg_id: int, place: Place) -> None:
    """Fence runs at the back of the sidewalks, as many as the place's fence share asks."""
    rng = _rng(bg_id, PLACE_STREAM + 3)
    t = lay.terrain
    coverage = min(1.0, FENCE_PER_SHARE * place.near("fence"))
    for side, sw in ((1, lay.sidewalk[0]), (-1, lay.sidewalk[1])):
        for n, (xa, xb) in enumerate(_runs(rng, coverage, 20.0)):
            for pa, pb in t.straight_kerb(xa, xb):
                y_in = side * (float(t.kerb(pa)) + sw + 0.05)
                lo, hi = sorted((y_in, y_in + side * 0.3))
                if pb - pa > 3.0 and st.fits(_rect(pa, pb, lo, hi), 0.0):
                    buildings.fence(st, t, rng, pa, pb, y_in, side, f"place fence {n}")


CLUTTER_KINDS = ("box", "bin", "container", "block")


def _clutter(st: _Street, lay: _Layout, bg_id: int, place: Place) -> None:
    """Objects no class names (SemanticKITTI's unlabeled): boxes, bins, containers and low
    blocks on the roadside, as many as the place's unlabeled share within 30 m asks."""
    rng = _rng(bg_id, PLACE_STREAM + 4)
    t = lay.terrain
    per_m = CLUTTER_PER_SHARE * float(np.mean(place.share("unlabeled")))
    n = int(rng.poisson(per_m * (ALONG_X[1] - ALONG_X[0]) * 2))
    for k in range(n):
        side = 1 if rng.random() < 0.5 else -1
        sw = lay.sidewalk[0] if side > 0 else lay.sidewalk[1]
        x = float(rng.uniform(*ALONG_X))
        u = float(rng.uniform(-sw + 0.3, 12.0))     # on the sidewalk's back or beyond it
        y = side * (float(t.kerb(x)) + sw + u)
        kind = CLUTTER_KINDS[int(rng.integers(len(CLUTTER_KINDS)))]
        lx, ly_, h = {"box": (rng.uniform(0.4, 1.2), rng.uniform(0.4, 1.2), rng.uniform(0.4, 1.3)),
                      "bin": (rng.uniform(0.5, 0.8), rng.uniform(0.5, 0.8), rng.uniform(0.9, 1.3)),
                      "container": (rng.uniform(1.5, 4.0), rng.uniform(1.2, 2.2),
                                    rng.uniform(1.0, 2.4)),
                      "block": (rng.uniform(1.0, 5.0), rng.uniform(0.3, 0.8),
                                rng.uniform(0.5, 1.2))}[kind]
        poly = _rect(x - lx / 2, x + lx / 2, y - ly_ / 2, y + ly_ / 2)
        if not st.fits(poly, margin=0.1):
            continue
        z = float(t.height(np.array([x]), np.array([y]))[0])
        mat = mid(str(rng.choice(["metal", "concrete", "paint mid", "paint dark"])))
        if kind == "bin":
            mesh = shapes.cylinder([x, y, z - 0.05], [x, y, z + h], lx / 2, 10)
        else:
            mesh = shapes.boxes([x - lx / 2, y - ly_ / 2, z - 0.05],
                                [x + lx / 2, y + ly_ / 2, z + h])
        st.add(mesh, UNKNOWN, 0, mat, RAW_ID["unlabeled"])
        st.occupy(f"clutter {k}", poly)


def place_street(bg_id: int, place: Place, pose: tuple[float, float]):
    """Street `bg_id` standing for `place`: its own street with the place's layout and roadside
    (built before the street furniture, which fills around it) and the ego pose offsets `pose`
    (pitch degrees, height m)."""
    from falsify.world import streets

    steps = (*streets.STEPS[:2], roadside_step(place), *streets.STEPS[2:])
    lay = place_layout(bg_id, place)
    own_road = road_half_width(place) is not None   # the place's road width, roadside beside
    dy = road_offset(place)
    st, lay = streets.placed(bg_id, steps, lay, free_zone(lay) if own_road else FREE_ZONE, dy)
    bg = streets.assemble(bg_id, st, lay)
    return replace(bg, ego_pitch_deg=float(pose[0]), ego_dz=float(pose[1]), ego_dy=dy,
                   kerbs_stop_cars=not own_road)
