"""Ground that is not a plane: road grade and crests, crowned camber, kerbs, sidewalks, and per
side a roadside profile (grass verge, ditch, embankment up or down, far hills) with height noise.

Everything is a function of one seeded `Terrain`: `height(x, y)` is the surface the sensor sees
(the mesh samples it), `pose_on(x, y, heading)` the z, pitch and roll of a vehicle standing
there, so the ego and every car follow the ground. World frame as in backgrounds.py.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from falsify import shapes
from falsify.materials import mid

ROADSIDE_KINDS: tuple[str, ...] = ("flat", "ditch", "embankment up", "embankment down", "hill")


@dataclass(frozen=True)
class Side:
    """Cross-section beyond one sidewalk: piecewise-linear (u, dz) from the sidewalk's back edge
    (u = 0) outward, then far hills of `hill_amp` metres; `noise` is the grass roughness (m)."""

    kind: str
    knots: tuple[tuple[float, float], ...]
    hill_amp: float
    noise: float


@dataclass(frozen=True)
class Terrain:
    """A street's ground, fully determined by its numbers (drawn by `draw_terrain`)."""

    half_width: float
    curb_h: float
    sidewalk: tuple[float, float]  # width on the left (+y) and right (-y)
    grade: float  # longitudinal slope of the road (rise per metre along +x)
    crest_amp: float  # metres of the long vertical curve
    crest_len: float
    crest_phase: float
    camber: float  # cross slope from the crown (y = 0) down to each kerb
    sides: tuple[Side, Side]  # left (+y), right (-y)
    noise_phase: tuple[float, ...]  # phases of the roughness waves
    hill_phase: float

    # -- the surface ---------------------------------------------------------------------------
    def road_z(self, x: np.ndarray) -> np.ndarray:
        """Height of the road's crown line."""
        x = np.asarray(x, dtype=np.float64)
        w = 2 * math.pi / self.crest_len
        return self.grade * x + self.crest_amp * (np.sin(w * x + self.crest_phase)
                                                  - math.sin(self.crest_phase))

    def sidewalk_z(self, x: np.ndarray) -> np.ndarray:
        return self.road_z(x) - self.camber * self.half_width + self.curb_h

    def _roughness(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Unit-amplitude smooth bumps (sum of six plane waves, wavelengths 1.3-9 m)."""
        out = np.zeros(np.broadcast(x, y).shape)
        ph = self.noise_phase
        for i, lam in enumerate((1.3, 1.9, 2.9, 4.1, 6.3, 9.0)):
            a = ph[i] * 7.0
            kx, ky = math.cos(a) * 2 * math.pi / lam, math.sin(a) * 2 * math.pi / lam
            out += np.sin(kx * x + ky * y + ph[i] * 13.0) * (0.12 + 0.05 * i)
        return out

    def roadside_dz(self, side: int, u: np.ndarray, x: np.ndarray) -> np.ndarray:
        """Height above the sidewalk at distance u >= 0 beyond it, on side +1 (left) or -1."""
        s = self.sides[0 if side > 0 else 1]
        k = np.asarray(s.knots, dtype=np.float64)
        base = np.interp(u, k[:, 0], k[:, 1])
        ramp = np.clip((u - k[-1, 0]) / 60.0, 0.0, 1.0)
        hills = s.hill_amp * ramp * (1.0 - np.cos(2 * math.pi * x / 260.0 + self.hill_phase
                                                  + 0.02 * u)) / 2
        rough = s.noise * np.clip(u / 0.6, 0.0, 1.0) * self._roughness(x, side * u)
        return base + hills + rough

    def height(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Ground height at world (x, y): road, sidewalks, then the roadside profiles."""
        x, y = np.broadcast_arrays(np.asarray(x, np.float64), np.asarray(y, np.float64))
        hw = self.half_width
        z = self.road_z(x) - self.camber * np.minimum(np.abs(y), hw)
        out = np.where(np.abs(y) < hw, z, self.sidewalk_z(x))
        for side, sw in ((1, self.sidewalk[0]), (-1, self.sidewalk[1])):
            u = side * y - hw - sw
            beyond = u > 0
            if beyond.any():
                out = np.where(beyond, self.sidewalk_z(x) + self.roadside_dz(side, np.maximum(
                    u, 0.0), x), out)
        return out

    def pose_on(self, x: float, y: float, heading_deg: float, half_length: float = 1.4,
                half_width: float = 0.8) -> tuple[float, float, float]:
        """(z, pitch_deg, roll_deg) of a vehicle whose wheels stand on the ground at (x, y).

        Pitch follows falsify.sensor.rot_y (positive tilts the nose down), roll rot_x (positive
        lifts the left side).
        """
        h = math.radians(heading_deg)
        fwd = np.array([math.cos(h), math.sin(h)])
        left = np.array([-fwd[1], fwd[0]])
        pts = np.array([[x, y]]) + np.array([[a * half_length, b * half_width]
                                            for a in (1, -1) for b in (1, -1)]) @ np.stack(
            [fwd, left])
        z = self.height(pts[:, 0], pts[:, 1])  # front-left, front-right, rear-left, rear-right
        front, rear = (z[0] + z[1]) / 2, (z[2] + z[3]) / 2
        lft, rgt = (z[0] + z[2]) / 2, (z[1] + z[3]) / 2
        pitch = math.degrees(math.atan2(rear - front, 2 * half_length))
        roll = math.degrees(math.atan2(lft - rgt, 2 * half_width))
        return float(z.mean()), pitch, roll


def draw_terrain(rng: np.random.Generator, half_width: float, curb_h: float,
                 sidewalk: tuple[float, float], flat_sides: bool = False) -> Terrain:
    """Seeded terrain numbers: gentle grades and crests, 1-3 % camber, a roadside per side
    (both flat for ``flat_sides``, with the same draws otherwise)."""
    flat_road = rng.random() < 0.25
    grade = 0.0 if flat_road else float(rng.uniform(-0.035, 0.035))
    crest_len = float(rng.uniform(160.0, 420.0))
    crest_amp = 0.0 if flat_road else float(rng.uniform(0.0, 0.03) * crest_len / (2 * math.pi))
    sides = tuple(_draw_side(rng, "flat" if flat_sides else None) for _ in range(2))
    return Terrain(half_width=half_width, curb_h=curb_h, sidewalk=sidewalk, grade=grade,
                   crest_amp=crest_amp, crest_len=crest_len,
                   crest_phase=float(rng.uniform(0, 2 * math.pi)),
                   camber=float(rng.uniform(0.01, 0.03)), sides=sides,  # type: ignore[arg-type]
                   noise_phase=tuple(float(v) for v in rng.uniform(0, 2 * math.pi, 6)),
                   hill_phase=float(rng.uniform(0, 2 * math.pi)))


def _draw_side(rng: np.random.Generator, kind: str | None = None) -> Side:
    drawn = str(rng.choice(ROADSIDE_KINDS, p=[0.3, 0.2, 0.25, 0.1, 0.15]))
    kind = kind or drawn
    verge = float(rng.uniform(0.5, 4.0))
    noise = float(rng.uniform(0.02, 0.09))
    hill = float(rng.uniform(0.0, 8.0))
    if kind == "flat":
        knots = ((0.0, 0.0), (verge, -0.05), (200.0, float(rng.uniform(-0.5, 0.5))))
        noise *= 0.5
    elif kind == "ditch":
        d, w = float(rng.uniform(0.4, 1.2)), float(rng.uniform(1.5, 3.5))
        knots = ((0.0, 0.0), (verge, -0.1), (verge + w / 2, -d), (verge + w, -0.1),
                 (200.0, float(rng.uniform(-1.0, 2.0))))
    elif kind == "embankment up":
        height = float(rng.uniform(1.5, 9.0))
        run = height / math.tan(math.radians(rng.uniform(18.0, 38.0)))
        ditch = float(rng.uniform(0.0, 0.8))
        knots = ((0.0, 0.0), (verge, -ditch), (verge + 0.8, -ditch),
                 (verge + 0.8 + run, height), (200.0, height + float(rng.uniform(0, 3))))
    elif kind == "embankment down":
        depth = float(rng.uniform(1.5, 6.0))
        run = depth / math.tan(math.radians(rng.uniform(18.0, 35.0)))
        knots = ((0.0, 0.0), (verge, -0.05), (verge + run, -depth), (200.0, -depth))
    else:  # hill: a long rising field
        height = float(rng.uniform(3.0, 15.0))
        knots = ((0.0, 0.0), (verge, -0.1), (verge + 40.0, height * 0.5), (200.0, height))
        hill *= 1.5
    return Side(kind, knots, hill, noise)


def _grid_mesh(xs: np.ndarray, ys: np.ndarray, z: np.ndarray, up: bool = True) -> shapes.Mesh:
    """A heightfield over the grid xs × ys (z shape (nx, ny)), triangles facing +z."""
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    v = np.stack([gx, gy, z], axis=-1).reshape(-1, 3)
    ny = len(ys)
    i, j = np.meshgrid(np.arange(len(xs) - 1), np.arange(ny - 1), indexing="ij")
    a = (i * ny + j).ravel()
    b, c, d = a + ny, a + ny + 1, a + 1
    if up:
        f = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    else:
        f = np.concatenate([np.stack([a, c, b], 1), np.stack([a, d, c], 1)])
    return v, f


def _roadside_u(extent: float) -> np.ndarray:
    """Cross-road sample distances beyond a sidewalk: fine near, coarse far."""
    near = np.arange(0.0, 12.0, 0.4)
    mid_ = np.arange(12.0, 40.0, 1.0)
    far = np.geomspace(40.0, extent, 14)
    return np.unique(np.concatenate([near, mid_, far]))


def terrain_meshes(t: Terrain, x_range: tuple[float, float], extent: float
                   ) -> list[tuple[shapes.Mesh, int]]:
    """The ground as meshes with their material: road, kerb faces, sidewalks, roadsides."""
    x0, x1 = x_range
    out: list[tuple[shapes.Mesh, int]] = []
    xs = np.arange(x0, x1 + 1e-9, 2.0)
    hw = t.half_width
    ys = np.array([-hw, 0.0, hw])
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    out.append((_grid_mesh(xs, ys, t.height(gx, gy * 0.999999)), mid("asphalt")))
    sz = t.sidewalk_z(xs)
    road_edge = t.road_z(xs) - t.camber * hw
    for side, sw in ((1, t.sidewalk[0]), (-1, t.sidewalk[1])):
        # Kerb face: a vertical strip from the road edge up to the sidewalk, facing the road.
        ys_k = np.array([side * hw, side * hw])
        zk = np.stack([road_edge, sz], axis=1)
        v, f = _grid_mesh(xs, ys_k, zk)
        v[:, 1] = side * hw
        v[:, 2] = zk.reshape(-1)
        f = f if side > 0 else f[:, ::-1]
        out.append(((v, f), mid("concrete")))
        lo, hi = sorted((side * hw, side * (hw + sw)))
        ys_s = np.array([lo, hi])
        out.append((_grid_mesh(xs, ys_s, np.stack([sz, sz], axis=1)), mid("concrete")))
        # Roadside: grass (soil on steep slopes is still grass-coloured to the laser).
        u = _roadside_u(extent)
        xr = np.arange(x0, x1 + 1e-9, 1.0)
        gxr, gu = np.meshgrid(xr, u, indexing="ij")
        z = t.sidewalk_z(gxr) + t.roadside_dz(side, gu, gxr)
        yy = side * (hw + sw + u)
        if side > 0:
            out.append((_grid_mesh(xr, yy, z), mid("grass")))
        else:
            out.append((_grid_mesh(xr, yy[::-1], z[:, ::-1]), mid("grass")))
    return out
