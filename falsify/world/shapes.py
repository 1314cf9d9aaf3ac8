"""Small vectorised mesh builders shared by the car library and the street backgrounds.

Every builder returns ``(vertices, faces)``: float64 (N, 3) and int64 (M, 3), faces wound so
their normals point outward. Rings and lofts may contain collapsed (zero-area) triangles by
construction; ``merge`` drops them, so call it (or ``drop_degenerate``) before using a result.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

Mesh = tuple[np.ndarray, np.ndarray]

# Unit cube corners and outward-wound faces (two triangles per side).
_CUBE_V = np.array(
    [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]],
    dtype=np.float64,
)
_CUBE_F = np.array(
    [
        [0, 2, 1], [0, 3, 2],  # bottom (-z)
        [4, 5, 6], [4, 6, 7],  # top (+z)
        [0, 1, 5], [0, 5, 4],  # -y
        [2, 3, 7], [2, 7, 6],  # +y
        [1, 2, 6], [1, 6, 5],  # +x
        [3, 0, 4], [3, 4, 7],  # -x
    ],
    dtype=np.int64,
)


def drop_degenerate(vertices: np.ndarray, faces: np.ndarray, eps: float = 1e-12) -> np.ndarray:
    """Boolean mask of faces whose area is above ``eps`` (m²); collapsed triangles are False."""
    tri = vertices[faces]
    area2 = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    return area2 > 2.0 * eps


def merge(meshes: list[Mesh]) -> Mesh:
    """Concatenate meshes into one vertex/face array pair and drop zero-area faces."""
    verts, faces, offset = [], [], 0
    for v, f in meshes:
        verts.append(v)
        faces.append(f + offset)
        offset += len(v)
    v = np.concatenate(verts).astype(np.float64)
    f = np.concatenate(faces).astype(np.int64)
    return v, f[drop_degenerate(v, f)]


def boxes(lo: np.ndarray, hi: np.ndarray) -> Mesh:
    """Axis-aligned boxes from corner arrays ``lo``/``hi`` of shape (n, 3) or (3,)."""
    lo = np.atleast_2d(np.asarray(lo, dtype=np.float64))
    hi = np.atleast_2d(np.asarray(hi, dtype=np.float64))
    v = lo[:, None, :] + _CUBE_V[None] * (hi - lo)[:, None, :]
    f = _CUBE_F[None] + 8 * np.arange(len(lo))[:, None, None]
    return v.reshape(-1, 3), f.reshape(-1, 3)


def oriented_box(center, extents, yaw: float = 0.0) -> Mesh:
    """One box of ``extents`` (dx, dy, dz) centred at ``center`` and turned by ``yaw`` about z."""
    ext = np.asarray(extents, dtype=np.float64)
    v, f = boxes(-ext / 2, ext / 2)
    return rotate_z(v, yaw) + np.asarray(center, dtype=np.float64), f


def rotate_z(vertices: np.ndarray, yaw: float) -> np.ndarray:
    """Rotate points counter-clockwise by ``yaw`` radians about the z axis."""
    c, s = np.cos(yaw), np.sin(yaw)
    out = vertices.copy()
    out[:, 0] = c * vertices[:, 0] - s * vertices[:, 1]
    out[:, 1] = s * vertices[:, 0] + c * vertices[:, 1]
    return out


def _basis(axis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors u, v with u × v = axis (unit), so (cos t) u + (sin t) v turns CCW."""
    helper = np.array([0.0, 0.0, 1.0]) if abs(axis[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    u = np.cross(helper, axis)
    u /= np.linalg.norm(u)
    return u, np.cross(axis, u)


def loft(rings: np.ndarray, cap_start: bool = True, cap_end: bool = True,
         closed: bool = False) -> Mesh:
    """Skin rings (S, M, 3) into quads; rings must turn CCW about the direction of travel.

    Caps are triangle fans around each end ring's centroid; ``closed`` joins the last ring
    back to the first (a torus) and then no caps are made.
    """
    s_count, m_count, _ = rings.shape
    verts = [rings.reshape(-1, 3)]
    n_seg = s_count if closed else s_count - 1
    s = np.arange(n_seg)[:, None]
    m = np.arange(m_count)[None, :]
    s1 = (s + 1) % s_count
    a = s * m_count + m
    b = s * m_count + (m + 1) % m_count
    c = s1 * m_count + (m + 1) % m_count
    d = s1 * m_count + m
    faces = [np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)]
    n = s_count * m_count
    ring_idx = np.arange(m_count)
    if not closed and cap_start:
        verts.append(rings[0].mean(axis=0, keepdims=True))
        faces.append(np.stack([np.full(m_count, n), (ring_idx + 1) % m_count, ring_idx], -1))
        n += 1
    if not closed and cap_end:
        base = (s_count - 1) * m_count
        verts.append(rings[-1].mean(axis=0, keepdims=True))
        faces.append(np.stack([np.full(m_count, n), base + ring_idx,
                               base + (ring_idx + 1) % m_count], -1))
    return np.concatenate(verts), np.concatenate(faces).astype(np.int64)


def revolve(profile: np.ndarray, sections: int, center, axis) -> Mesh:
    """Lathe a (radius, axial offset) profile around ``axis`` through ``center``.

    The profile should run from the -axis end to the +axis end; radius-0 points close the ends.
    """
    axis = np.asarray(axis, dtype=np.float64)
    axis = axis / np.linalg.norm(axis)
    u, v = _basis(axis)
    t = np.linspace(0.0, 2 * np.pi, sections, endpoint=False)
    circle = np.cos(t)[:, None] * u + np.sin(t)[:, None] * v  # (sections, 3)
    prof = np.asarray(profile, dtype=np.float64)
    rings = (np.asarray(center, dtype=np.float64) + prof[:, 1, None, None] * axis
             + prof[:, 0, None, None] * circle[None])
    return loft(rings, cap_start=False, cap_end=False)


def cylinder(p0, p1, radius: float, sections: int = 8, radius1: float | None = None) -> Mesh:
    """Closed (optionally tapered) cylinder from point ``p0`` to ``p1``."""
    p0 = np.asarray(p0, dtype=np.float64)
    p1 = np.asarray(p1, dtype=np.float64)
    axis = p1 - p0
    length = float(np.linalg.norm(axis))
    r1 = radius if radius1 is None else radius1
    prof = np.array([[0.0, 0.0], [radius, 0.0], [r1, length], [0.0, length]])
    return revolve(prof, sections, p0, axis / length)


def torus(center, axis, major: float, minor: float, major_sections: int = 24,
          minor_sections: int = 6) -> Mesh:
    """Torus (e.g. a bicycle tyre) around ``axis`` through ``center``."""
    axis = np.asarray(axis, dtype=np.float64)
    axis = axis / np.linalg.norm(axis)
    u, v = _basis(axis)
    t = np.linspace(0.0, 2 * np.pi, major_sections, endpoint=False)
    radial = np.cos(t)[:, None] * u + np.sin(t)[:, None] * v  # (S, 3)
    p = np.linspace(0.0, 2 * np.pi, minor_sections, endpoint=False)
    # Minor circle in the (radial, -axis) plane: radial × (-axis) = axis × radial, the
    # direction of travel, so each ring turns CCW about it.
    ring = (np.cos(p)[None, :, None] * radial[:, None, :]
            - np.sin(p)[None, :, None] * axis[None, None, :])
    rings = np.asarray(center, dtype=np.float64) + major * radial[:, None, :] + minor * ring
    return loft(rings, closed=True)


def icosphere(center, radii, subdivisions: int = 1) -> Mesh:
    """Ellipsoid from a subdivided icosahedron, semi-axes ``radii`` (scalar or 3-vector)."""
    v, f = _unit_icosphere(subdivisions)
    return v * np.asarray(radii, dtype=np.float64) + np.asarray(center, dtype=np.float64), f


_ICO_CACHE: dict[int, Mesh] = {}
# trimesh.creation.icosphere(subdivisions=s) for s = 0..3, stored so that building a street never
# imports trimesh (with scipy, some 65 MB in every worker); tests/world/test_shapes.py holds them to
# trimesh's own.
ICOSPHERES = Path(__file__).with_name("icospheres.npz")


def _unit_icosphere(subdivisions: int) -> Mesh:
    """Unit icosphere (cached; callers get copies via arithmetic, never the cached arrays)."""
    if subdivisions not in _ICO_CACHE:
        with np.load(ICOSPHERES) as stored:
            if f"faces{subdivisions}" not in stored:
                raise ValueError(f"icosphere subdivisions {subdivisions}: stored are 0-3")
            _ICO_CACHE[subdivisions] = (stored[f"vertices{subdivisions}"],
                                        stored[f"faces{subdivisions}"])
    return _ICO_CACHE[subdivisions]


def person(height: float = 1.75, stride: float = 0.3, arm_swing: float = 0.2,
           sections: int = 8) -> Mesh:
    """A standing or walking person facing +x, feet at z = 0, centred on the origin."""
    s = height / 1.75
    hip_z, shoulder_z, head_z = 0.9 * s, 1.45 * s, 1.62 * s
    hip_y, shoulder_y = 0.1 * s, 0.2 * s
    parts: list[Mesh] = []
    for side, sgn in ((1.0, 1.0), (-1.0, -1.0)):
        foot = np.array([sgn * stride / 2, side * hip_y, 0.0])
        parts.append(cylinder(foot, [0.0, side * hip_y, hip_z], 0.06 * s, sections, 0.085 * s))
        hand = np.array([-sgn * arm_swing, side * (shoulder_y + 0.04 * s), hip_z - 0.05 * s])
        parts.append(cylinder([0.0, side * shoulder_y, shoulder_z - 0.03 * s], hand,
                              0.05 * s, sections, 0.04 * s))
    parts.append(oriented_box([0.0, 0.0, (hip_z + shoulder_z) / 2],
                              [0.24 * s, 0.38 * s, shoulder_z - hip_z + 0.08 * s]))
    parts.append(cylinder([0.0, 0.0, shoulder_z], [0.0, 0.0, head_z - 0.06 * s], 0.05 * s, 6))
    parts.append(icosphere([0.0, 0.0, head_z], [0.1 * s, 0.085 * s, 0.115 * s], 1))
    v, f = merge(parts)
    v[:, 2] -= v[:, 2].min()  # tilted leg caps dip a few mm below the soles
    return v, f


def cyclist(height: float = 1.75, sections: int = 6) -> Mesh:
    """A bicycle with its rider, travelling toward +x, wheels on z = 0, centred on the origin."""
    s = height / 1.75
    r = 0.34
    rear, front = np.array([-0.52, 0.0, r]), np.array([0.52, 0.0, r])
    crank = np.array([-0.05, 0.0, 0.3])
    seat = np.array([-0.22, 0.0, 0.92])
    bar = np.array([0.42, 0.0, 1.0])
    parts: list[Mesh] = [
        torus(rear, [0, 1, 0], r - 0.02, 0.02, 20, 6),
        torus(front, [0, 1, 0], r - 0.02, 0.02, 20, 6),
    ]
    tube = 0.018
    for a, b in ((rear, crank), (rear, seat), (crank, seat), (crank, bar - [0.05, 0, 0.1]),
                 (seat, bar - [0.05, 0, 0.1]), (front, bar)):
        parts.append(cylinder(a, b, tube, sections))
    parts.append(cylinder([0.42, -0.28, 1.0], [0.42, 0.28, 1.0], tube, sections))
    # Rider: legs from the saddle to the pedals, leaning torso, arms to the bar, head.
    hip = seat + [0.0, 0.0, 0.06]
    shoulder = hip + np.array([0.32, 0.0, 0.5]) * s
    for side, pedal_x, pedal_z in ((1.0, 0.1, 0.42), (-1.0, -0.2, 0.2)):
        knee = np.array([hip[0] + 0.3, side * 0.11, hip[2] - 0.15 * s])
        pedal = np.array([pedal_x, side * 0.12, pedal_z])
        parts.append(cylinder(hip + [0, side * 0.1, 0], knee, 0.075 * s, sections, 0.06 * s))
        parts.append(cylinder(knee, pedal, 0.055 * s, sections, 0.045 * s))
        parts.append(cylinder(shoulder + [0, side * 0.19 * s, 0], bar + [0, side * 0.25, 0],
                              0.045 * s, sections, 0.04 * s))
    mid = (hip + shoulder) / 2
    lean = np.arctan2(shoulder[2] - hip[2], shoulder[0] - hip[0])
    length = float(np.linalg.norm(shoulder - hip)) + 0.1
    torso_v, torso_f = oriented_box([0, 0, 0], [length, 0.36 * s, 0.22 * s])
    c, sn = np.cos(lean), np.sin(lean)
    rot = np.array([[c, 0.0, -sn], [0.0, 1.0, 0.0], [sn, 0.0, c]])
    parts.append((torso_v @ rot.T + mid, torso_f))
    parts.append(icosphere(shoulder + np.array([0.12, 0.0, 0.2]) * s, 0.11 * s, 1))
    v, f = merge(parts)
    lo, hi = v.min(axis=0), v.max(axis=0)
    v = v - [(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, lo[2]]
    return v, f
