"""The car library: built-in models at every level of detail, and user mesh loading."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from trimesh.ray.ray_pyembree import RayMeshIntersector

from falsify.errors import ConfigError
from falsify.world import cars
from falsify.world.cars import BUILTIN_MODELS, LOD_LEVELS, car_dimensions, car_mesh, load_user_car

EXPECTED = {  # length, width, height in metres
    "sedan": (4.7, 1.8, 1.45),
    "hatchback": (4.1, 1.75, 1.48),
    "suv": (4.7, 1.9, 1.75),
    "van": (5.0, 2.0, 2.0),
    "pickup": (5.3, 1.9, 1.8),
    "wagon": (4.8, 1.8, 1.5),
    "coupe": (4.5, 1.85, 1.3),
    "compact": (3.6, 1.66, 1.53),
    "roadster": (4.3, 1.8, 1.22),
}
MIRRORS = 0.45  # metres the door mirrors add to the width at lod >= 1


def test_required_models_exist():
    assert set(EXPECTED) <= set(BUILTIN_MODELS)
    assert LOD_LEVELS == (0, 1, 2)


@pytest.mark.parametrize("name", BUILTIN_MODELS)
@pytest.mark.parametrize("lod", LOD_LEVELS)
def test_builtin_shape(name, lod):
    mesh = car_mesh(name, lod)
    v = np.asarray(mesh.vertices)
    assert np.isfinite(v).all()
    assert mesh.faces.min() >= 0 and mesh.faces.max() < len(v)
    assert (mesh.area_faces > 1e-12).all(), "degenerate faces"
    length, width, height = car_dimensions(mesh)
    want_l, want_w, want_h = EXPECTED[name]
    assert abs(length - want_l) <= 0.1 * want_l and abs(height - want_h) <= 0.1 * want_h
    extra = MIRRORS if lod >= 1 else 0.0
    assert want_w * 0.9 <= width <= want_w * 1.1 + extra
    assert v[:, 2].min() == 0.0
    lo, hi = mesh.bounds
    assert np.allclose((lo[:2] + hi[:2]) / 2, 0.0, atol=1e-9)
    assert mesh.volume > 0, "normals should point outward"


@pytest.mark.parametrize("name", BUILTIN_MODELS)
def test_lod_triangle_counts(name):
    counts = [len(car_mesh(name, lod).faces) for lod in LOD_LEVELS]
    assert 100 <= counts[0] <= 500
    assert counts[0] < counts[1] < counts[2]
    assert 2_000 <= counts[2] <= 20_000


def test_deterministic_bytes():
    first = {n: (car_mesh(n).vertices.tobytes(), car_mesh(n).faces.tobytes())
             for n in BUILTIN_MODELS}
    cars.car_mesh.cache_clear()
    for n in BUILTIN_MODELS:
        assert car_mesh(n).vertices.tobytes() == first[n][0]
        assert car_mesh(n).faces.tobytes() == first[n][1]


def test_cached_object_is_shared():
    assert car_mesh("sedan", 1) is car_mesh("sedan", 1)


def test_wheels_touch_ground_under_a_raised_body():
    """Rays just above the ground hit the wheels; between the axles the body is clear of them."""
    mesh = car_mesh("sedan")
    inter = RayMeshIntersector(mesh)
    x = np.linspace(-2.6, 2.6, 53)
    origins = np.stack([x, np.full_like(x, 5.0), np.full_like(x, 0.1)], axis=1)
    hits = inter.intersects_first(origins, np.tile([0.0, -1.0, 0.0], (len(x), 1))) >= 0
    assert hits[np.abs(x - 1.42) < 0.15].all() and hits[np.abs(x + 1.40) < 0.15].all()
    assert not hits[np.abs(x) < 0.5].any()


def test_cabin_narrower_than_body():
    mesh = car_mesh("sedan")
    v = np.asarray(mesh.vertices)
    body = v[(v[:, 2] > 0.5) & (v[:, 2] < 0.9)]
    roof = v[v[:, 2] > 1.3]
    assert np.abs(roof[:, 1]).max() < np.abs(body[:, 1]).max() - 0.15


def _side_silhouette(mesh: trimesh.Trimesh) -> np.ndarray:
    u, w = np.meshgrid(np.linspace(-2.7, 2.7, 55), np.linspace(0.05, 2.1, 21))
    origins = np.stack([u.ravel(), np.full(u.size, 5.0), w.ravel()], axis=1)
    dirs = np.tile([0.0, -1.0, 0.0], (u.size, 1))
    return RayMeshIntersector(mesh).intersects_first(origins, dirs) >= 0


def test_models_differ_in_silhouette():
    sil = {n: _side_silhouette(car_mesh(n, 1)) for n in BUILTIN_MODELS}
    names = list(sil)
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            assert (sil[a] != sil[b]).sum() >= 25, (a, b)


def _marked_car() -> trimesh.Trimesh:
    """A 2 m (x) × 4 m (y) × 1 m box whose front is -y, marked by a post at the -y end."""
    body = trimesh.creation.box(extents=(2.0, 4.0, 1.0))
    post = trimesh.creation.box(extents=(0.2, 0.2, 1.0))
    post.apply_translation([0.0, -1.8, 1.0])
    mesh = trimesh.util.concatenate([body, post])
    mesh.apply_translation([10.0, 20.0, 30.0])
    return mesh


@pytest.mark.parametrize("ext", ["obj", "stl", "ply", "glb"])
def test_load_user_car_orientation_and_scale(tmp_path, ext):
    path = tmp_path / f"car.{ext}"
    _marked_car().export(path)
    mesh = load_user_car(path, scale=2.0, forward="-y")
    length, width, height = car_dimensions(mesh)
    assert np.allclose([length, width, height], [8.0, 4.0, 4.0], atol=1e-4)
    v = np.asarray(mesh.vertices)
    assert v[:, 2].min() == pytest.approx(0.0, abs=1e-9)
    lo, hi = mesh.bounds
    assert np.allclose((lo[:2] + hi[:2]) / 2, 0.0, atol=1e-6)
    top = v[v[:, 2] > 2.1]  # the post, at the front
    assert top[:, 0].min() > 2.9


def test_load_user_car_y_up_scene(tmp_path):
    """A GLB scene of several meshes with +y up is concatenated and stood on +z."""
    a = trimesh.creation.box(extents=(4.0, 1.5, 1.8))  # x length, y height, z width
    b = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    b.apply_translation([0.0, 1.25, 0.0])
    path = tmp_path / "scene.glb"
    trimesh.Scene([a, b]).export(path)
    mesh = load_user_car(path, forward="+x", up="+y")
    assert np.allclose(car_dimensions(mesh), [4.0, 1.8, 2.5], atol=1e-4)


def test_load_user_car_errors(tmp_path):
    good = tmp_path / "good.stl"
    _marked_car().export(good)
    cases = {}
    cases[tmp_path / "missing.obj"] = {}
    bad = tmp_path / "bad.glb"
    bad.write_bytes(b"\x00not a glb file at all" * 10)
    cases[bad] = {}
    empty = tmp_path / "points.obj"
    empty.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\n")
    cases[empty] = {}
    nan = tmp_path / "nan.obj"
    nan.write_text("v nan 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    cases[nan] = {}
    for path, kwargs in cases.items():
        with pytest.raises(ConfigError, match=path.name):
            load_user_car(path, **kwargs)
    for kwargs, key in (
        ({"scale": 0.0}, "scale"), ({"scale": -1.0}, "scale"), ({"scale": float("nan")}, "scale"),
        ({"scale": float("inf")}, "scale"), ({"forward": "x"}, r"\+x"), ({"up": "up"}, r"\+z"),
        ({"forward": "+z", "up": "-z"}, "parallel"), ({"forward": "+y", "up": "+y"}, "parallel"),
    ):
        with pytest.raises(ConfigError, match=key) as err:
            load_user_car(good, **kwargs)
        assert good.name in str(err.value)


def test_unknown_model_and_lod():
    with pytest.raises(ConfigError, match="sedan"):
        car_mesh("tank")
    with pytest.raises(ConfigError, match="lod"):
        car_mesh("sedan", 3)
