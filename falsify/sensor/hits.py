"""Per-pixel nearest hits and what casting needs per triangle: the `HitLayer` a scan is composed
in, and a `Caster`, a BVH with each triangle's material, pass probability and normal."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from falsify.sensor.raycast import MeshCaster
from falsify.world.materials import PASS_PROB


@dataclass
class HitLayer:
    """Per-pixel nearest hit so far: range (inf = none), class, instance, material, the
    cosine of the incidence angle (for the sensor's return model), the surface's unit normal
    in the sensor frame, turned to face the sensor (H×W×3, zero where nothing is hit; for
    weather and ego motion), and the raw SemanticKITTI id (uint16, 0 where nothing is hit)."""

    dist: np.ndarray
    cls: np.ndarray
    inst: np.ndarray
    mat: np.ndarray
    cos: np.ndarray
    normal: np.ndarray | None
    semantic: np.ndarray

    def copy(self, normals: bool = True) -> HitLayer:
        """A writable copy; without `normals` its normal is None (a clear scan needs none, and
        copying them would cost every scan)."""
        normal = self.normal.copy() if normals and self.normal is not None else None
        return HitLayer(self.dist.copy(), self.cls.copy(), self.inst.copy(), self.mat.copy(),
                      self.cos.copy(), normal, self.semantic.copy())


def face_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Unit normals per triangle (float64; zero for degenerate ones)."""
    tri = np.asarray(vertices, np.float64)[faces]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)


@dataclass(frozen=True)
class Caster:
    """A BVH with what the sensor model needs per triangle: material, pass probability, normal."""

    bvh: MeshCaster
    material: np.ndarray
    face_pass: np.ndarray
    normals: np.ndarray

    @classmethod
    def of(cls, vertices, faces, material, anchor=None) -> Caster:
        mat = np.asarray(material, np.uint8)
        return cls(MeshCaster(vertices, faces, anchor=anchor), mat, PASS_PROB[mat],
                   face_normals(vertices, faces))
