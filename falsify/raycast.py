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
        self.n_faces = len(faces)
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
