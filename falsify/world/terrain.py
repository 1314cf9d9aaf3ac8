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

from falsify.world import shapes
from falsify.world.materials import mid

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
    # A street narrower away from the test site: beyond `wide_x` (and a taper of `taper`
    # metres) the kerbs stand `narrow` metres further in, and all beyond them moves in too.
    narrow: float = 0.0
    wide_x: tuple[float, float] = (0.0, 0.0)
    taper: float = 10.0

    # -- the kerb line -------------------------------------------------------------------------
    def inset(self, x: np.ndarray) -> np.ndarray:
        """How far inside `half_width` the kerbs stand at x: 0 along the wide stretch, rising
        linearly over the tapers to `narrow`."""
        x = np.asarray(x, dtype=np.float64)
        if self.narrow <= 0.0:
            return np.zeros_like(x)
        a, b = self.wide_x
        outside = np.maximum(np.maximum(a - x, x - b), 0.0)
        return self.narrow * np.clip(outside / self.taper, 0.0, 1.0)

    def kerb(self, x: np.ndarray) -> np.ndarray:
        """|y| of the kerbs at x."""
        return self.half_width - self.inset(x)

    def kerb_breaks(self, x0: float, x1: float) -> list[float]:
        """x0, the kerb line's corners inside (x0, x1), then x1: it is straight in between."""
        a, b = self.wide_x
        inner = ([a - self.taper, a, b, b + self.taper] if self.narrow > 0.0 else [])
        return [x0, *sorted(v for v in inner if x0 < v < x1), x1]

    def widest_kerb(self, x0: float, x1: float) -> float:
        """The largest |y| of the kerbs over [x0, x1]."""
        return float(self.kerb(np.array(self.kerb_breaks(x0, x1))).max())

    def narrowest_kerb(self, x0: float, x1: float) -> float:
        """The smallest |y| of the kerbs over [x0, x1]."""
        return float(self.kerb(np.array(self.kerb_breaks(x0, x1))).min())

    def straight_kerb(self, x0: float, x1: float) -> list[tuple[float, float]]:
        """The pieces of [x0, x1] along which the kerbs run parallel to the road (no taper)."""
        br = self.kerb_breaks(x0, x1)
        return [(u, v) for u, v in zip(br[:-1], br[1:], strict=False)
                if v > u and abs(float(self.kerb(u)) - float(self.kerb(v))) < 1e-9]

    # -- the surface ---------------------------------------------------------------------------
    def road_z(self, x: np.ndarray) -> np.ndarray:
        """Height of the road's crown line."""
        x = np.asarray(x, dtype=np.float64)
        w = 2 * math.pi / self.crest_len
        return self.grade * x + self.crest_amp * (np.sin(w * x + self.crest_phase)
                                                  - math.sin(self.crest_phase))

    def sidewalk_z(self, x: np.ndarray) -> np.ndarray:
        return self.road_z(x) - self.camber * self.kerb(x) + self.curb_h

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

    def surface(self, x: float, y: float) -> str:
        """What the ground at (x, y) is: "road" inside the kerbs, "sidewalk" out to the
        sidewalk's back edge (kerb faces count as sidewalk, as SemanticKITTI labels them), else
        "terrain"."""
        kerb = float(self.kerb(x))
        if abs(y) < kerb:
            return "road"
        return "sidewalk" if abs(y) <= kerb + self.sidewalk[0 if y > 0 else 1] else "terrain"

    def height(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Ground height at world (x, y): road, sidewalks, then the roadside profiles."""
        x, y = np.broadcast_arrays(np.asarray(x, np.float64), np.asarray(y, np.float64))
        hw = self.kerb(x)
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
                 sidewalk: tuple[float, float], flat_sides: bool = False,
                 narrowing: tuple[float, tuple[float, float], float] | None = None) -> Terrain:
    """Seeded terrain numbers: gentle grades and crests, 1-3 % camber, a roadside per side
    (both flat for ``flat_sides``, with the same draws otherwise); ``narrowing`` is
    (narrow, wide_x, taper), drawn by the caller (see Terrain)."""
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
                   hill_phase=float(rng.uniform(0, 2 * math.pi)),
                   **({} if narrowing is None else
                      {"narrow": narrowing[0], "wide_x": narrowing[1], "taper": narrowing[2]}))


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


def _grid_mesh(xs: np.ndarray, ys: np.ndarray, z: np.ndarray, up: bool = True,
               y_of: np.ndarray | None = None) -> shapes.Mesh:
    """A heightfield over the grid xs × ys (z shape (nx, ny)), triangles facing +z; `y_of`
    (shape (nx, ny)) moves each vertex to its own y (a grid whose rows bend with the kerb)."""
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    if y_of is not None:
        gy = y_of
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
    """The ground as meshes with their material: road, kerb faces, sidewalks, roadsides. Where
    the street narrows every row of vertices follows the kerb line (its corners are vertices)."""
    x0, x1 = x_range
    out: list[tuple[shapes.Mesh, int]] = []
    xs = _with_breaks(np.arange(x0, x1 + 1e-9, 2.0), t, x0, x1)
    kerb = t.kerb(xs)
    s = np.array([-1.0, 0.0, 1.0])
    y_road = kerb[:, None] * s[None, :]
    out.append((_grid_mesh(xs, s, t.height(xs[:, None], y_road * 0.999999), y_of=y_road),
                mid("asphalt")))
    sz = t.sidewalk_z(xs)
    road_edge = t.road_z(xs) - t.camber * kerb
    for side, sw in ((1, t.sidewalk[0]), (-1, t.sidewalk[1])):
        # Kerb face: a vertical strip from the road edge up to the sidewalk, facing the road.
        zk = np.stack([road_edge, sz], axis=1)
        v, f = _grid_mesh(xs, np.array([0.0, 1.0]), zk, y_of=np.stack([side * kerb] * 2, 1))
        f = f if side > 0 else f[:, ::-1]
        out.append(((v, f), mid("concrete")))
        y_s = np.stack([side * kerb, side * (kerb + sw)], axis=1)
        y_s = np.sort(y_s, axis=1)
        out.append((_grid_mesh(xs, np.array([0.0, 1.0]), np.stack([sz, sz], axis=1), y_of=y_s),
                    mid("concrete")))
        # Roadside: grass (soil on steep slopes is still grass-coloured to the laser).
        u = _roadside_u(extent)
        xr = _with_breaks(np.arange(x0, x1 + 1e-9, 1.0), t, x0, x1)
        gxr, gu = np.meshgrid(xr, u, indexing="ij")
        z = t.sidewalk_z(gxr) + t.roadside_dz(side, gu, gxr)
        yy = side * (t.kerb(gxr) + sw + gu)
        if side > 0:
            out.append((_grid_mesh(xr, u, z, y_of=yy), mid("grass")))
        else:
            out.append((_grid_mesh(xr, u[::-1], z[:, ::-1], y_of=yy[:, ::-1]), mid("grass")))
    return out


def _with_breaks(xs: np.ndarray, t: Terrain, x0: float, x1: float) -> np.ndarray:
    """Sample positions plus the kerb line's corners, so a narrowing street's meshes bend there."""
    br = t.kerb_breaks(x0, x1)
    return xs if len(br) == 2 else np.unique(np.concatenate([xs, br]))
