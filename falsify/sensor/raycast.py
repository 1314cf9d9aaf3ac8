"""Embree ray casting of one triangle mesh, re-centred so float32 stays exact far from the origin.

Embree works in float32. A mesh is stored relative to an anchor (the centre of its bounds, kept
in float64), and every ray origin is moved into that frame in float64 before the cast, so a
street 1e5 m from the world origin is cast as precisely as one at the origin.
"""

from __future__ import annotations

import numpy as np
from embreex import rtcore_scene
from embreex.mesh_construction import TriangleMesh

MISS = np.inf


class MeshCaster:
    """A BVH over one triangle mesh; `cast` returns hit distance and triangle id per ray."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, anchor: np.ndarray | None = None):
        vertices = np.asarray(vertices, dtype=np.float64)
        faces = np.ascontiguousarray(faces, dtype=np.int32)
        if len(faces) == 0:
            raise ValueError("cannot build a BVH over an empty mesh")
        if not np.isfinite(vertices).all():
            raise ValueError("mesh has non-finite vertices")
        if anchor is None:
            anchor = (vertices.min(axis=0) + vertices.max(axis=0)) / 2
        self.anchor = np.asarray(anchor, dtype=np.float64)
        self._scene = rtcore_scene.EmbreeScene()
        local = np.ascontiguousarray(vertices - self.anchor, dtype=np.float32)
        # Keep the arrays alive as long as the scene: Embree may share their memory.
        self._buffers = (local, faces)
        TriangleMesh(self._scene, local, faces)

    def cast(self, origins: np.ndarray, directions: np.ndarray,
             max_dist: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
        """Cast rays (float64, frame of the mesh's vertices); misses get inf and id -1.

        Directions must be unit vectors so that the returned distance is the range in metres.
        """
        t, prim, _ = self.cast_with_normals(origins, directions, max_dist)
        return t, prim

    def cast_with_normals(self, origins: np.ndarray, directions: np.ndarray,
                          max_dist: np.ndarray | float
                          ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """As `cast`, plus each hit's unnormalised geometric normal (N×3 float32, the camera
        shades with it)."""
        n = len(directions)
        if n == 0:
            return np.empty(0), np.empty(0, dtype=np.int32), np.empty((0, 3), np.float32)
        o = np.ascontiguousarray(np.broadcast_to(origins - self.anchor, (n, 3)), dtype=np.float32)
        d = np.ascontiguousarray(directions, dtype=np.float32)
        dist = np.ascontiguousarray(np.broadcast_to(max_dist, (n,)), dtype=np.float32)
        res = self._scene.run(o, d, dists=dist, output=1)
        prim = res["primID"]
        t = res["tfar"].astype(np.float64)
        hit = prim >= 0
        t[~hit] = MISS
        return t, prim, res["Ng"]


# -- porous and glass surfaces ----------------------------------------------------------------
# Whether a ray passes a porous triangle is decided by a hash of (ray index, triangle id, seed),
# so a scan is reproducible and a composed scan (background cache plus windowed cars) makes
# exactly the decisions a full re-cast of the merged scene makes.
MAX_LAYERS = 8  # porous surfaces a ray may pass before the caster stops (then it misses)
STEP = 2e-3  # metres a re-cast starts beyond the surface it passed


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
