"""The car model library: procedural built-in cars at three levels of detail, and user meshes.

Car frame: metres, origin at the centre of the footprint on the ground, +x the car's front,
+y its left, +z up. Built-in cars are lofted from side profiles: a lower body with bonnet,
boot and wheel arches, a glasshouse narrower than the body that tapers toward the roof, and
four lathed wheels touching z = 0, so their LiDAR silhouettes differ model to model.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from falsify.errors import ConfigError
from falsify.world import shapes
from falsify.world.materials import mid

if TYPE_CHECKING:
    import trimesh

LOD_LEVELS: tuple[int, ...] = (0, 1, 2)

Profile = tuple[tuple[float, float], ...]


@dataclass(frozen=True)
class CarSpec:
    """Side-profile description of one built-in model (x forward from the car's centre)."""

    length: float
    width: float
    wheel_radius: float
    axles: tuple[float, float]  # x of the front and rear axle
    body_top: Profile  # (x, z) upper edge of the lower body, rear to front
    body_bottom: Profile  # (x, z) underside of the lower body before the arches are cut
    cabin_top: Profile  # (x, z) roof line; its first and last x bound the glasshouse
    cabin_taper: float = 0.22  # fraction of the cabin's half-width lost from belt to roof
    cabin_inset: float = 0.08  # metres the glass sits inside the body sides at the belt
    bed: tuple[float, float] | None = None  # pickup bed (x_rear, x_front) with walls to bed_top
    bed_top: float = 0.0


_SPECS: dict[str, CarSpec] = {
    "sedan": CarSpec(
        4.7, 1.8, 0.32, (1.42, -1.40),
        body_top=((-2.35, 0.78), (-2.28, 0.97), (-1.6, 1.0), (-1.3, 0.98), (1.05, 0.94),
                  (1.9, 0.84), (2.28, 0.74), (2.35, 0.6)),
        body_bottom=((-2.35, 0.45), (-2.15, 0.26), (-1.95, 0.18), (1.95, 0.18), (2.2, 0.26),
                     (2.35, 0.36)),
        cabin_top=((-1.45, 0.0), (-0.75, 1.43), (-0.3, 1.45), (0.2, 1.44), (1.1, 0.0)),
    ),
    "hatchback": CarSpec(
        4.1, 1.75, 0.31, (1.3, -1.25),
        body_top=((-2.05, 0.85), (-2.0, 1.0), (-1.85, 1.0), (1.0, 0.93), (1.75, 0.82),
                  (2.05, 0.6)),
        body_bottom=((-2.05, 0.42), (-1.9, 0.2), (1.8, 0.18), (2.05, 0.35)),
        cabin_top=((-1.97, 0.0), (-1.82, 1.40), (-1.6, 1.47), (0.05, 1.48), (1.0, 0.0)),
    ),
    "suv": CarSpec(
        4.7, 1.9, 0.37, (1.45, -1.40),
        body_top=((-2.35, 0.95), (-2.3, 1.1), (1.0, 1.08), (1.95, 1.0), (2.3, 0.9),
                  (2.35, 0.75)),
        body_bottom=((-2.35, 0.5), (-2.15, 0.3), (2.1, 0.3), (2.35, 0.48)),
        cabin_top=((-2.27, 0.0), (-2.12, 1.70), (-1.85, 1.75), (0.2, 1.75), (1.0, 0.0)),
        cabin_taper=0.14,
    ),
    "van": CarSpec(
        5.0, 2.0, 0.34, (1.65, -1.60),
        body_top=((-2.5, 1.0), (1.6, 1.0), (2.3, 0.95), (2.5, 0.8)),
        body_bottom=((-2.5, 0.4), (-2.4, 0.22), (2.3, 0.22), (2.5, 0.35)),
        cabin_top=((-2.49, 0.0), (-2.46, 1.98), (0.9, 2.0), (1.25, 1.85), (1.8, 0.0)),
        cabin_taper=0.06, cabin_inset=0.03,
    ),
    "pickup": CarSpec(
        5.3, 1.9, 0.38, (1.75, -1.55),
        body_top=((-2.65, 0.8), (-0.48, 0.8), (-0.46, 1.12), (1.2, 1.1), (2.1, 1.0),
                  (2.6, 0.9), (2.65, 0.75)),
        body_bottom=((-2.65, 0.5), (-2.5, 0.28), (2.3, 0.28), (2.65, 0.45)),
        cabin_top=((-0.47, 0.0), (-0.42, 1.78), (0.45, 1.8), (1.25, 0.0)),
        cabin_taper=0.12, bed=(-2.65, -0.47), bed_top=1.28,
    ),
    "wagon": CarSpec(
        4.8, 1.8, 0.32, (1.45, -1.45),
        body_top=((-2.4, 0.85), (-2.35, 1.0), (-2.1, 1.0), (1.05, 0.95), (1.95, 0.84),
                  (2.35, 0.7), (2.4, 0.6)),
        body_bottom=((-2.4, 0.42), (-2.2, 0.22), (2.1, 0.2), (2.4, 0.35)),
        cabin_top=((-2.3, 0.0), (-2.15, 1.46), (-1.9, 1.5), (0.2, 1.5), (1.08, 0.0)),
    ),
    "coupe": CarSpec(
        4.5, 1.85, 0.33, (1.4, -1.3),
        body_top=((-2.25, 0.78), (-2.18, 0.92), (-1.5, 0.95), (0.9, 0.88), (1.8, 0.76),
                  (2.25, 0.55)),
        body_bottom=((-2.25, 0.42), (-2.05, 0.22), (1.95, 0.16), (2.25, 0.3)),
        cabin_top=((-1.55, 0.0), (-0.5, 1.28), (0.05, 1.3), (1.0, 0.0)),
        cabin_taper=0.25,
    ),
    "compact": CarSpec(
        3.6, 1.66, 0.29, (1.18, -1.12),
        body_top=((-1.8, 0.86), (-1.76, 1.0), (-1.6, 1.0), (0.85, 0.95), (1.5, 0.84),
                  (1.8, 0.62)),
        body_bottom=((-1.8, 0.42), (-1.65, 0.2), (1.6, 0.18), (1.8, 0.36)),
        cabin_top=((-1.72, 0.0), (-1.62, 1.46), (-1.35, 1.52), (0.1, 1.53), (0.9, 0.0)),
        cabin_taper=0.16,
    ),
    "roadster": CarSpec(
        4.3, 1.8, 0.32, (1.35, -1.25),
        body_top=((-2.15, 0.76), (-2.1, 0.88), (-1.2, 0.9), (0.8, 0.84), (1.75, 0.7),
                  (2.15, 0.5)),
        body_bottom=((-2.15, 0.38), (-1.95, 0.16), (1.9, 0.14), (2.15, 0.28)),
        cabin_top=((-1.1, 0.0), (-0.45, 1.2), (0.0, 1.22), (0.75, 0.0)),
        cabin_taper=0.28,
    ),
}

BUILTIN_MODELS: tuple[str, ...] = tuple(_SPECS)

# Per level of detail: body stations, stations per wheel arch, ring points of the body and
# cabin cross-sections, cabin stations, wheel sections.
_LOD = {
    0: dict(body=9, arch=0, ring=8, cabin=5, cabin_ring=8, wheel=8),
    1: dict(body=26, arch=6, ring=12, cabin=14, cabin_ring=10, wheel=12),
    2: dict(body=70, arch=16, ring=28, cabin=40, cabin_ring=24, wheel=32),
}

_AXES = {"+x": (1, 0, 0), "-x": (-1, 0, 0), "+y": (0, 1, 0), "-y": (0, -1, 0),
         "+z": (0, 0, 1), "-z": (0, 0, -1)}


def _interp(profile: Profile, x: np.ndarray) -> np.ndarray:
    """Piecewise-linear profile height at stations ``x``."""
    p = np.asarray(profile, dtype=np.float64)
    return np.interp(x, p[:, 0], p[:, 1])


def _ring(n: int, exponent: float) -> tuple[np.ndarray, np.ndarray]:
    """Unit superellipse (cos-like, sin-like) points, CCW in the (y, z) plane, i.e. about +x."""
    t = np.linspace(-np.pi / 2, 1.5 * np.pi, n, endpoint=False) + np.pi / n
    c, s = np.cos(t), np.sin(t)
    e = 2.0 / exponent
    return np.sign(c) * np.abs(c) ** e, np.sign(s) * np.abs(s) ** e


def _section_rings(x: np.ndarray, bottom: np.ndarray, top: np.ndarray, half_width: np.ndarray,
                   taper: float, n: int, exponent: float) -> np.ndarray:
    """Rings (S, n, 3) of rounded-rectangle cross-sections, narrower toward their top."""
    cy, cz = _ring(n, exponent)
    cy = cy / np.abs(cy).max()  # reach the full half-width despite the ring's sampling
    zc = (bottom + top) / 2
    hz = (top - bottom) / 2
    z = zc[:, None] + hz[:, None] * cz[None]
    frac = (cz[None] + 1.0) / 2.0  # 0 at the bottom of a section, 1 at the top
    y = half_width[:, None] * (1.0 - taper * frac) * cy[None]
    return np.stack([np.broadcast_to(x[:, None], y.shape), y, z], axis=-1)


def _plan_factor(x: np.ndarray, length: float, radius: float) -> np.ndarray:
    """Width factor rounding the nose and tail corners in plan view (1 along the middle)."""
    d = np.clip(np.abs(x) - (length / 2 - radius), 0.0, None) / radius
    return 0.82 + 0.18 * np.sqrt(np.clip(1.0 - d**2, 0.0, 1.0))


def _body(spec: CarSpec, lod: dict) -> shapes.Mesh:
    """Lower body lofted front to back along x, wheel arches cut out of its underside."""
    half_l = spec.length / 2
    xs = [np.linspace(-half_l, half_l, lod["body"] + 1)]
    arch_r = spec.wheel_radius + 0.06
    if lod["arch"]:
        for ax in spec.axles:
            xs.append(ax + arch_r * np.cos(np.linspace(np.pi, 0.0, lod["arch"] + 1)))
            xs.append(np.array([ax - arch_r - 1e-3, ax + arch_r + 1e-3]))
    x = np.unique(np.clip(np.concatenate(xs), -half_l, half_l))
    top = _interp(spec.body_top, x)
    bottom = _interp(spec.body_bottom, x)
    if lod["arch"]:
        for ax in spec.axles:
            dx = x - ax
            inside = np.abs(dx) <= arch_r
            arch = spec.wheel_radius + np.sqrt(np.clip(arch_r**2 - dx**2, 0.0, None))
            bottom = np.where(inside, np.maximum(bottom, arch), bottom)
    bottom = np.minimum(bottom, top - 0.05)
    half_w = spec.width / 2 * _plan_factor(x, spec.length, 0.45)
    rings = _section_rings(x, bottom, top, half_w, 0.06, lod["ring"], 6.0)
    return shapes.loft(rings)


def _cabin(spec: CarSpec, lod: dict) -> shapes.Mesh:
    """Glasshouse: set in from the body sides, tapering to the roof, sloped at both ends."""
    x0, x1 = spec.cabin_top[0][0], spec.cabin_top[-1][0]
    # Denser stations near the ends so the windscreen and rear-window slopes stay straight.
    u = np.linspace(0.0, 1.0, lod["cabin"] + 1)
    x = x0 + (x1 - x0) * (0.5 - 0.5 * np.cos(np.pi * u))
    keys = np.array([p[0] for p in spec.cabin_top[1:-1]])
    x = np.unique(np.concatenate([x, keys]))
    belt = _interp(spec.body_top, x) - 0.03
    roof_profile = tuple((px, pz if pz > 0 else float(_interp(spec.body_top, np.array([px]))[0]))
                         for px, pz in spec.cabin_top)
    top = np.maximum(_interp(roof_profile, x), belt + 0.04)
    half_w = (spec.width / 2 - spec.cabin_inset) * _plan_factor(x, spec.length, 0.45)
    rings = _section_rings(x, belt, top, half_w, spec.cabin_taper, lod["cabin_ring"], 8.0)
    return shapes.loft(rings)


def _wheels(spec: CarSpec, lod: dict) -> list[shapes.Mesh]:
    """Four lathed wheels (tyre with a recessed rim at full detail) on the ground."""
    r, h = spec.wheel_radius, 0.11
    if lod["arch"]:
        prof = np.array([[0.0, -h], [0.95 * r, -h], [r, -h + 0.03], [r, h - 0.03],
                         [0.95 * r, h], [0.68 * r, h], [0.64 * r, h - 0.03], [0.0, h - 0.03]])
    else:
        prof = np.array([[0.0, -h], [r, -h], [r, h], [0.0, h]])
    out = []
    y_off = spec.width / 2 - 0.05 - h
    for ax in spec.axles:
        for side in (1.0, -1.0):
            # Profile runs -axis to +axis; the axis points outward so the rim faces out.
            out.append(shapes.revolve(prof, lod["wheel"], [ax, side * y_off, r],
                                      [0.0, side, 0.0]))
    return out


def _bed(spec: CarSpec) -> list[shapes.Mesh]:
    """Pickup bed walls: two sides, the tailgate and the front wall against the cab."""
    assert spec.bed is not None
    x0, x1 = spec.bed
    w, t, z0, z1 = spec.width / 2 * 0.97, 0.06, 0.7, spec.bed_top
    lo = np.array([[x0, w - t, z0], [x0, -w, z0], [x0, -w, z0], [x1 - t, -w, z0]])
    hi = np.array([[x1, w, z1], [x1, -w + t, z1], [x0 + t, w, z1], [x1, w, z1]])
    return [shapes.boxes(lo, hi)]


@functools.lru_cache(maxsize=64)
def car_mesh(name: str, lod: int = 2) -> trimesh.Trimesh:
    """Built-in car ``name`` at level of detail ``lod`` (2 full, 0 coarse hull), in the car frame,
    as a trimesh mesh (for users and the naive paths; the simulator takes `car_parts`' arrays
    and never imports trimesh, which with scipy costs a worker some 65 MB).

    Cached: every call with the same arguments returns the SAME object; do not mutate it
    (copy it, or transform copies of its vertices).
    """
    import trimesh

    v, f, _ = car_parts(name, lod)
    return trimesh.Trimesh(vertices=v, faces=f.astype(np.int64), process=False)


@functools.lru_cache(maxsize=64)
def car_parts(name: str, lod: int = 2) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Vertices, faces and per-face material of built-in car ``name``: paint body, glass
    windows (the cabin's sides and screens), rubber tyres, and at lod >= 1 mirrors and the
    seats a ray through the glass ends on. Same face order as ``car_mesh``."""
    if name not in _SPECS:
        raise ConfigError(f"car_model: unknown model {name!r}; allowed: {', '.join(_SPECS)}")
    if isinstance(lod, bool) or lod not in LOD_LEVELS:
        raise ConfigError(f"lod: {lod!r} is not a level of detail; allowed: {LOD_LEVELS}")
    spec = _SPECS[name]
    params = _LOD[lod]
    paint, glass, rubber = mid("paint mid"), mid("glass"), mid("rubber")
    cv, cf = _cabin(spec, params)
    tri = cv[cf]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    nz = np.abs(n[:, 2]) / np.maximum(np.linalg.norm(n, axis=1), 1e-12)
    cen = tri.mean(axis=1)
    belt = _interp(spec.body_top, cen[:, 0])
    cabin_mat = np.where((nz < 0.8) & (cen[:, 2] > belt + 0.04), glass, paint)
    parts = [(*_body(spec, params), paint), (cv, cf, cabin_mat)]
    parts += [(*w, rubber) for w in _wheels(spec, params)]
    if spec.bed is not None:
        parts += [(*b, paint) for b in _bed(spec)]
    if lod >= 1:
        parts += _mirrors_and_seats(spec)
    verts, faces, mats, offset = [], [], [], 0
    for v, f, m in parts:
        verts.append(v)
        faces.append(np.asarray(f, np.int64) + offset)
        mats.append(np.broadcast_to(np.asarray(m, np.uint8), (len(f),)))
        offset += len(v)
    v = np.concatenate(verts).astype(np.float64)
    f = np.concatenate(faces)
    mat = np.concatenate(mats)
    keep = shapes.drop_degenerate(v, f)
    v = _to_footprint_frame(v)
    f, mat = f[keep], np.ascontiguousarray(mat[keep])
    for a in (v, f, mat):
        a.setflags(write=False)
    return v, f, mat


def _mirrors_and_seats(spec: CarSpec) -> list:
    """Door mirrors at the windscreen's foot and a seat block inside the glasshouse."""
    x0, x1 = spec.cabin_top[0][0], spec.cabin_top[-1][0]
    belt = float(_interp(spec.body_top, np.array([x1]))[0])
    hw = spec.width / 2
    out = []
    for s in (1.0, -1.0):
        lo = [x1 - 0.2, s * (hw + 0.02) - (0.2 if s < 0 else 0.0), belt + 0.02]
        hi = [x1 - 0.08, s * (hw + 0.02) + (0.2 if s > 0 else 0.0), belt + 0.16]
        out.append((*shapes.boxes(lo, hi), mid("paint mid")))
    seat_belt = float(_interp(spec.body_top, np.array([(x0 + x1) / 2]))[0])
    out.append((*shapes.boxes([x0 + 0.35, -hw + 0.3, seat_belt - 0.45],
                              [x1 - 0.45, hw - 0.3, seat_belt + 0.3]), mid("interior")))
    return out


def _to_footprint_frame(v: np.ndarray) -> np.ndarray:
    """Translate so the bounding footprint is centred on the origin and the lowest point is 0."""
    lo, hi = v.min(axis=0), v.max(axis=0)
    return v - np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, lo[2]])


def car_dimensions(mesh: trimesh.Trimesh) -> tuple[float, float, float]:
    """Length (x), width (y) and height (z) of a mesh's axis-aligned bounds, in metres."""
    ext = np.asarray(mesh.bounds[1] - mesh.bounds[0], dtype=np.float64)
    return float(ext[0]), float(ext[1]), float(ext[2])


def load_user_car(path: str | Path, scale: float = 1.0, forward: str = "+x",
                  up: str = "+z", key: str = "") -> trimesh.Trimesh:
    """Load a user mesh (OBJ, STL, PLY, GLB...) and bring it into the car frame.

    ``forward`` and ``up`` name the file's axes that point to the car's front and top; the mesh
    is turned so they become +x and +z, scaled by ``scale``, and moved so its footprint is
    centred on the origin with its lowest point at z = 0. Errors name the file by the config's
    ``key`` when given ("cfg.toml: actors.mine.file"), else as a car model file.
    """
    path = Path(path)
    named = f"{key}.file {path}" if key else f"car model file {path}"
    try:
        scale_f = float(scale)
    except (TypeError, ValueError):
        scale_f = math.nan
    if not math.isfinite(scale_f) or scale_f <= 0:
        raise ConfigError(f"scale: {scale!r} for car model {path} must be a finite number > 0")
    for key, value in (("forward", forward), ("up", up)):
        if value not in _AXES:
            raise ConfigError(f"{key}: {value!r} for car model {path} is not an axis; "
                              f"allowed: {', '.join(_AXES)}")
    f_axis = np.array(_AXES[forward], dtype=np.float64)
    u_axis = np.array(_AXES[up], dtype=np.float64)
    if abs(float(f_axis @ u_axis)) > 0.5:
        raise ConfigError(f"forward={forward!r} and up={up!r} for car model {path} are "
                          "parallel; they must be two different axes")
    if not path.is_file():
        raise ConfigError(f"{named}: not found")
    try:
        import trimesh

        loaded = trimesh.load(str(path), force="mesh", process=False)
    except Exception as exc:  # trimesh raises many types for unreadable files
        raise ConfigError(f"{named}: cannot be loaded as a mesh ({exc})") from exc
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        raise ConfigError(f"{named}: contains no triangles")
    vertices = np.asarray(loaded.vertices, dtype=np.float64)
    if not np.isfinite(vertices).all():
        raise ConfigError(f"{named}: has non-finite (NaN or inf) vertices")
    rot = np.stack([f_axis, np.cross(u_axis, f_axis), u_axis])  # rows: new x, y, z
    vertices = _to_footprint_frame(vertices @ rot.T * scale_f)
    return trimesh.Trimesh(vertices=vertices, faces=np.asarray(loaded.faces), process=False)
