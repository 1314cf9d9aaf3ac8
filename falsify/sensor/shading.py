"""Shading of camera hits: sun, sky, haze, surface colours, shadows and rain streaks.
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from falsify.sensor.camera import Camera
from falsify.sensor.look import COLOURS, EXTINCTION, SUN_KEPT, Look
from falsify.sensor.simulator import Simulator


@dataclass
class Hits:
    """Nearest hit per pixel (flat): distance, owner (-1 background, k = car k), primitive,
    unnormalised normal in the owner's frame."""

    t: np.ndarray
    owner: np.ndarray
    prim: np.ndarray
    normal: np.ndarray


class Renderer(Protocol):
    """What shading reads of the camera renderer: its simulator (the cars' casters) and camera.
    A protocol, so shading need not import the renderer that imports it."""

    @property
    def sim(self) -> Simulator: ...

    @property
    def camera(self) -> Camera: ...

# Linear light to 8-bit sRGB-like values (gamma 2.2) through a table: 16 linear steps per code.
_GAMMA = (np.linspace(0.0, 1.0, 4096) ** (1 / 2.2) * 255 + 0.5).astype(np.uint8)
# Fog and rain take the sky's colour 10 degrees above the horizon.
_HAZE_RAY = np.array([[math.cos(math.radians(10)), 0.0, math.sin(math.radians(10))]])


def sun(look: Look) -> tuple[np.ndarray, float, np.ndarray]:
    """Unit direction to the sun (world), its strength after clouds, and its colour."""
    el = math.radians(62.0 * math.sin(math.pi * (look.hour - 6.0) / 12.0))
    az = math.radians(100.0 - 200.0 * (look.hour - 6.0) / 12.0)
    d = np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
    strength = float(np.clip(math.sin(el) * 4.0, 0.0, 1.0)) * SUN_KEPT[look.weather]
    warm = float(np.clip(math.sin(el) * 2.5, 0.0, 1.0))
    colour = np.array([1.0, 0.55 + 0.42 * warm, 0.30 + 0.60 * warm])
    return d, strength, colour


def _sky(look: Look, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sky colour per ray and the ambient light level (linear RGB)."""
    sun_el = math.sin(math.radians(62.0 * math.sin(math.pi * (look.hour - 6.0) / 12.0)))
    day = float(np.clip(sun_el * 3.0 + 0.25, 0.0, 1.0))
    up = np.clip(dirs[:, 2], 0.0, 1.0)[:, None]
    if look.weather == "clear":
        zenith, horizon = np.array([0.10, 0.25, 0.65]), np.array([0.55, 0.68, 0.85])
    else:
        zenith, horizon = np.array([0.42, 0.44, 0.47]), np.array([0.60, 0.62, 0.64])
    dusk = float(np.clip(1.0 - abs(sun_el) * 5.0, 0.0, 1.0))
    horizon = horizon * (1 - 0.5 * dusk) + 0.5 * dusk * np.array([0.95, 0.50, 0.30])
    night = np.array([0.004, 0.006, 0.02])
    sky = (horizon + (zenith - horizon) * np.sqrt(up)) * day + night * (1 - day)
    ambient = horizon * (0.35 * day) + np.array([0.01, 0.012, 0.025])
    return sky, ambient


def _palette(keys: np.ndarray, colours: np.ndarray) -> np.ndarray:
    """A fixed colour per integer key (deterministic hash)."""
    h = (keys.astype(np.uint64) * np.uint64(2654435761)) % np.uint64(len(colours))
    return colours[h.astype(np.int64)]


_BUILDING = np.array([[0.40, 0.33, 0.25], [0.30, 0.27, 0.24], [0.45, 0.42, 0.36],
                      [0.28, 0.14, 0.10], [0.38, 0.38, 0.38], [0.50, 0.45, 0.32]])
_CLOTHES = np.array([[0.05, 0.05, 0.10], [0.40, 0.05, 0.05], [0.08, 0.20, 0.40],
                     [0.35, 0.30, 0.20], [0.10, 0.10, 0.10], [0.50, 0.45, 0.40]])
_PARKED = np.array([list(COLOURS[c]) for c in ("red", "white", "black", "silver", "grey",
                                                "blue", "green")])


_ROAD = (0.075, 0.075, 0.08)
_DASH = (0.70, 0.70, 0.66)
_PAVE = (0.30, 0.29, 0.27)
_GRASS = (0.07, 0.14, 0.04)


def ground_colours(bg, x: np.ndarray, y: np.ndarray, z: np.ndarray, up: np.ndarray,
                   col: np.ndarray) -> None:
    """Colour the background's upward-facing points in `col`: road (within 5 cm of the road's
    crown height at x, so a street that climbs stays road), its centre dashes, pavement within
    6.5 m beyond the kerb, grass beyond."""
    if bg.terrain is not None:
        kerb, crown = bg.terrain.kerb(x), bg.terrain.road_z(x)
    else:
        kerb, crown = bg.road_half_width, 0.0
    road = up & (z < crown + 0.05) & (np.abs(y) < kerb)
    col[road] = _ROAD
    col[road & (np.abs(y) < 0.08) & (np.mod(x, 9.0) < 3.0)] = _DASH
    pave = up & ~road & (np.abs(y) < kerb + 6.5)
    col[pave] = _PAVE
    col[up & ~road & ~pave] = _GRASS


def shade(r: Renderer, bg, placed, paints, hits: Hits, dirs, origin, axis: np.ndarray,
          look: Look, streaks: np.ndarray, shadow_test
          ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Lambert plus a sun highlight on paint, cast shadows, sky light, headlights at night,
    and weather as attenuation with depth and darkening, for the rays `dirs` and their hits
    (`shadow_test(points, sun_dir)` says which points the sun cannot see); returns RGB (N, 3)
    uint8, which pixels the sun lights, and the lit hit points."""
    n = len(hits.t)
    hit = np.isfinite(hits.t)
    pos = origin + dirs * np.where(hit, hits.t, 0.0)[:, None]
    normal = hits.normal.astype(np.float64)
    albedo = np.zeros((n, 3))
    spec = np.zeros(n)
    b, colours = _background_albedo(bg, hits, hit, pos, normal)
    albedo[b] = colours
    _car_albedo(r, placed, paints, hits, pos, normal, albedo, spec)
    # Light.
    nrm = normal / np.maximum(np.sqrt(np.einsum("ij,ij->i", normal, normal)), 1e-12)[:, None]
    nrm *= np.where(np.einsum("ij,ij->i", nrm, dirs) > 0, -1.0, 1.0)[:, None]
    sun_d, sun_k, sun_c = sun(look)
    sky, ambient = _sky(look, dirs)
    facing = np.flatnonzero(hit & (nrm @ sun_d > 0) & (sun_k > 0))
    points = pos[facing] + nrm[facing] * 0.02
    free = ~shadow_test(points, sun_d)
    lit = np.zeros(n, bool)
    lit[facing[free]] = True
    lambert = np.where(lit, nrm @ sun_d, 0.0)
    sky_light = 0.6 + 0.4 * np.clip(nrm[:, 2], 0.0, 1.0)
    light = ambient[None, :] * sky_light[:, None] + sun_k * lambert[:, None] * sun_c
    if sun_d[2] < 0.05:  # headlights: the ego car lights the road ahead at night
        cos_axis = np.clip(dirs @ axis, 0.0, 1.0)
        dist = np.where(hit, hits.t, np.inf)
        beam = np.clip((cos_axis - 0.9) * 10.0, 0.0, 1.0) * 40.0 / (dist ** 2 + 25.0)
        light = light + (beam * np.clip(-np.einsum("ij,ij->i", nrm, dirs), 0, 1))[:, None] \
            * np.array([1.0, 0.95, 0.85])
    out = albedo * light
    shiny = np.flatnonzero(spec > 0)  # paint and glass: a sun highlight and the sky reflected
    if len(shiny):
        d, nr, sp = dirs[shiny], nrm[shiny], spec[shiny]
        half = sun_d[None, :] - d
        half /= np.sqrt(np.einsum("ij,ij->i", half, half))[:, None]
        cos_h = np.clip(np.einsum("ij,ij->i", nr, half), 0, 1)
        highlight = sp * np.where(lit[shiny], cos_h ** 60, 0.0)
        reflect = sp * 0.25 * (1 - np.clip(-np.einsum("ij,ij->i", nr, d), 0, 1)) ** 2
        out[shiny] += highlight[:, None] * sun_k * sun_c + reflect[:, None] * sky[shiny]
    if look.weather == "rain":
        out *= 0.8  # wet, dull surfaces
    out = np.where(hit[:, None], out, sky)
    # Weather: attenuation towards the horizon's colour with distance.
    dist = np.where(hit, hits.t, r.camera.max_depth * 4)
    ext = EXTINCTION[look.weather] if look.extinction is None else look.extinction
    keep = np.exp(-dist * ext)[:, None]
    haze = _sky(look, _HAZE_RAY)[0] if look.weather in ("fog", "rain") else sky
    out = out * keep + haze * (1 - keep)
    if look.weather == "rain":
        out = out + 0.08 * streaks[:, None] * haze
    rgb = _GAMMA[(np.clip(out, 0.0, 1.0) * (len(_GAMMA) - 1) + 0.5).astype(np.int64)]
    return rgb, lit, points[free]


def _background_albedo(bg, hits: Hits, hit: np.ndarray, pos: np.ndarray, normal: np.ndarray
                       ) -> tuple[np.ndarray, np.ndarray]:
    """The background's hit pixels and their colours, by class and shape: the ground's, trees
    green high up and brown low down, parked cars' paint, people's clothes, buildings'."""
    b = np.flatnonzero(hit & (hits.owner < 0))
    cls, inst = bg.face_class[hits.prim[b]], bg.face_instance[hits.prim[b]]
    nb = normal[b]
    up = np.abs(nb[:, 2]) > 0.9 * np.sqrt(np.einsum("ij,ij->i", nb, nb))
    z, y, x = pos[b, 2], pos[b, 1], pos[b, 0]
    col = _palette(hits.prim[b] // 12, _BUILDING)
    ground_colours(bg, x, y, z, up, col)
    things = np.flatnonzero((cls == 0) & (inst > 0))
    tx, ty, tz = x[things], y[things], z[things]
    above = tz - (bg.terrain.height(tx, ty) if bg.terrain is not None else 0.0)
    col[things] = np.where((above > 2.0)[:, None], (0.05, 0.14, 0.04), (0.16, 0.12, 0.08))
    col[cls == 1] = _palette(inst[cls == 1], _PARKED)
    people = (cls == 2) | (cls == 3)
    col[people] = _palette(inst[people], _CLOTHES)
    return b, col


def _car_albedo(r: Renderer, placed, paints, hits: Hits, pos: np.ndarray, normal: np.ndarray,
                albedo: np.ndarray, spec: np.ndarray) -> None:
    """The sampled cars' pixels, in place: paint, dark glass above the belt line, dark tyres
    and sills low down (albedo and specular share), their normals turned to the world frame."""
    for k, car in enumerate(placed):
        mine = np.flatnonzero(hits.owner == k)
        if not len(mine):
            continue
        _, corners = r.sim.car_caster(car.model)
        height = float(corners[:, 2].max() - corners[:, 2].min())
        local = (pos[mine] - car.translation()) @ car.rotation()
        n_loc = normal[mine] / np.maximum(np.linalg.norm(normal[mine], axis=1,
                                                         keepdims=True), 1e-12)
        paint = np.tile(np.asarray(paints[k], np.float64), (len(mine), 1))
        glass = (local[:, 2] > 0.62 * height) & (local[:, 2] < 0.96 * height) \
            & (np.abs(n_loc[:, 2]) < 0.8)
        paint[glass] = (0.02, 0.025, 0.03)
        low = local[:, 2] < 0.27 * height
        paint[low] = (0.03, 0.03, 0.03)
        albedo[mine] = paint
        spec[mine] = np.where(low, 0.05, np.where(glass, 0.9, 0.5))
        normal[mine] = normal[mine] @ car.rotation().T


def shadowed(r: Renderer, bg_caster, placed, points: np.ndarray,
              sun_d: np.ndarray) -> np.ndarray:
    """Whether each point's ray to the sun is blocked by the background or a car."""
    blocked = np.zeros(len(points), bool)
    if len(points) == 0:
        return blocked
    t, _ = bg_caster.bvh.cast(points, np.broadcast_to(sun_d, points.shape), 1000.0)
    blocked |= np.isfinite(t)
    for car in placed:
        caster, corners = r.sim.car_caster(car.model)
        c_rot = car.rotation()
        o = (points - car.translation()) @ c_rot
        d = sun_d @ c_rot
        near = slab(o, d, corners.min(axis=0), corners.max(axis=0)) & ~blocked
        if near.any():
            t, _ = caster.bvh.cast(o[near], np.broadcast_to(d, (int(near.sum()), 3)), 1000.0)
            blocked[np.flatnonzero(near)[np.isfinite(t)]] = True
    return blocked


def slab(o: np.ndarray, d: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Which rays o + s d (s > 0, one direction d for all) cross the box [lo, hi]."""
    tmin = np.zeros(len(o))
    tmax = np.full(len(o), np.inf)
    for k in range(3):
        if abs(d[k]) < 1e-12:  # parallel to this slab: inside it or never
            outside = (o[:, k] < lo[k]) | (o[:, k] > hi[k])
            tmax[outside] = -1.0
            continue
        t1, t2 = (lo[k] - o[:, k]) / d[k], (hi[k] - o[:, k]) / d[k]
        if d[k] < 0:
            t1, t2 = t2, t1
        np.maximum(tmin, t1, out=tmin)
        np.minimum(tmax, t2, out=tmax)
    return tmax >= tmin


def rain_streaks(shape: tuple[int, int]) -> np.ndarray:
    """A fixed pattern of short slanted streaks (deterministic: no per-run randomness)."""
    h, w = shape
    seed = int.from_bytes(hashlib.sha256(f"rain{h}x{w}".encode()).digest()[:4], "little")
    rng = np.random.default_rng(seed)
    out = np.zeros((h, w))
    n = max(1, h * w // 900)
    r0, c0 = rng.integers(0, h, n), rng.integers(0, w, n)
    length = max(2, h // 25)
    for k in range(length):
        rr, cc = r0 + k, c0 + k // 4
        ok = (rr < h) & (cc < w)
        out[rr[ok], cc[ok]] = 1.0
    return out
