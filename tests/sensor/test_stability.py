"""Numerical stability at the extremes, asserted: far offsets, range limits, grazing rays, vertices
and edges, degenerate triangles, yaw wrap-around, NLopt bounds, empty IoU, odd network inputs,
and maps with holes."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest
from embreex import rtcore_scene
from embreex.mesh_construction import TriangleMesh

from falsify.errors import ConfigError, FalsifyError
from falsify.results.metrics import class_scores, confusion
from falsify.results.miou_maps import miou_map
from falsify.sensor.lidar import load_sensor
from falsify.sensor.raycast import MeshCaster
from falsify.sensor.scanner import PlacedCar, place
from falsify.sensor.simulator import Simulator
from falsify.world.space import CarPose, parse_space
from tests.conftest import ROOT


def wall(x: float, half: float = 5.0, n: int = 8):
    """A vertical wall at distance x made of an n×n grid of quads (many shared edges)."""
    ys, zs = np.meshgrid(np.linspace(-half, half, n + 1), np.linspace(-half, half, n + 1),
                         indexing="ij")
    v = np.stack([np.full(ys.size, x), ys.ravel(), zs.ravel()], axis=1)
    idx = np.arange(ys.size).reshape(n + 1, n + 1)
    a, b, c, d = idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]
    f = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3),
                        np.stack([a, c, d], -1).reshape(-1, 3)]).astype(np.int32)
    return v, f


def fan_dirs(n: int = 400, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    d = np.stack([np.ones(n), rng.uniform(-0.3, 0.3, n), rng.uniform(-0.3, 0.3, n)], 1)
    return d / np.linalg.norm(d, axis=1, keepdims=True)


@pytest.mark.parametrize("offset", [1e3, 1e5, 1e6])
def test_recentred_float64_setup_beats_naive_float32(offset):
    """Our caster keeps ranges within 1 mm at any offset; casting raw world coordinates in
    float32 (what a naive set-up does) degrades with the offset."""
    v, f = wall(20.0371, half=7.013)
    shift = np.array([offset, -offset, 0.5 * offset]) * 1.2345678 + 0.0123  # not float32-exact
    dirs = fan_dirs()
    expected = 20.0371 / dirs[:, 0]
    t, prim = MeshCaster(v + shift, f).cast(shift, dirs, 100.0)
    assert (prim >= 0).all()
    np.testing.assert_allclose(t, expected, atol=1e-3)
    # Naive: float32 world coordinates straight into Embree.
    scene = rtcore_scene.EmbreeScene()
    TriangleMesh(scene, (v + shift).astype(np.float32), f)
    res = scene.run(np.tile(shift, (len(dirs), 1)).astype(np.float32), dirs.astype(np.float32),
                    output=1)
    naive_err = np.abs(np.where(res["primID"] >= 0, res["tfar"], np.inf) - expected).max()
    if offset >= 1e6:
        assert naive_err > 1e-2  # the naive path is off by centimetres or misses
    assert np.abs(t - expected).max() <= max(1e-3, naive_err)


def test_targets_near_and_at_max_range():
    v, f = wall(0.5, half=0.4)
    d = fan_dirs(50)
    d[:, 1:] *= 0.1
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    t, prim = MeshCaster(v, f).cast(np.zeros(3), d, 120.0)
    assert (prim >= 0).all()
    np.testing.assert_allclose(t, 0.5 / d[:, 0], atol=1e-5)
    centre = np.array([[1.0, 0.0, 0.0]])
    for x, hit in ((119.999, True), (120.0, True), (120.001, False), (500.0, False)):
        vv, ff = wall(x)
        t, prim = MeshCaster(vv, ff).cast(np.zeros(3), centre, 120.0)
        assert (prim[0] >= 0) == hit, x
        if hit:
            assert t[0] == pytest.approx(x, abs=1e-4)
            assert np.isfinite(t).all()


def test_sensor_min_range_drops_returns_inside_it():
    sensor = load_sensor("kitti-hdl64e-front")
    sim = Simulator(sensor)
    scan = sim.render(0, [PlacedCar("van", 3.4, 0.0, 0.0, 1)])
    r = scan.image[..., 4]
    assert r[r > 0].min() >= sensor.min_range


def test_grazing_rays_to_the_horizon():
    """Rays a hair below the horizon hit a flat ground plane at h / sin(angle), or not at all
    when that is past max range; never a NaN."""
    size = 4000.0
    v = np.array([[-size, -size, 0.0], [size, -size, 0.0], [size, size, 0.0],
                  [-size, size, 0.0]])
    f = np.array([[0, 1, 2], [0, 2, 3]], np.int32)
    caster = MeshCaster(v, f)
    angles = np.radians(np.array([-30.0, -5.0, -1.0, -0.2, -0.1, -0.05, -0.01, 0.0, 0.01]))
    d = np.stack([np.cos(angles), np.zeros_like(angles), np.sin(angles)], 1)
    h = 1.73
    t, prim = caster.cast(np.array([0.0, 0.0, h]), d, 3000.0)
    assert not np.isnan(t).any()
    with np.errstate(divide="ignore"):
        expected = np.where(angles < 0, h / np.sin(-angles), np.inf)
    expected[expected > 3000.0] = np.inf
    hit = np.isfinite(expected)
    assert ((prim >= 0) == hit).all()
    np.testing.assert_allclose(t[hit], expected[hit], rtol=1e-4)


def test_rays_through_a_shared_vertex_of_a_fan_do_not_leak():
    """Eight triangles meeting in one vertex; rays exactly at the vertex and along each edge."""
    k = 8
    ring = np.stack([np.full(k, 10.0), np.cos(np.arange(k) * 2 * np.pi / k),
                     np.sin(np.arange(k) * 2 * np.pi / k)], 1)
    v = np.vstack([[10.0, 0.0, 0.0], ring])
    f = np.array([[0, 1 + i, 1 + (i + 1) % k] for i in range(k)], np.int32)
    caster = MeshCaster(v, f)
    targets = np.vstack([v[0], v[0] + (ring - v[0]) * 0.5, v[0] + (ring - v[0]) * 1e-6])
    d = targets / np.linalg.norm(targets, axis=1, keepdims=True)
    t, prim = caster.cast(np.zeros(3), d, 50.0)
    assert (prim >= 0).all()
    np.testing.assert_allclose(t, np.linalg.norm(targets, axis=1), atol=1e-4)


def test_thin_and_degenerate_triangles_never_give_nan():
    v = np.array([[10, -1, -1], [10, 1, -1], [10, 1, 1], [10, -1, 1],
                  [9, 0, 0], [9, 0, 0], [9, 0, 0],            # a point triangle
                  [9.5, -2, 0], [9.5, 2, 0], [9.5, 0, 1e-9],  # a sliver
                  [9.2, -1, 0.5], [9.2, 1, 0.5], [9.2, 3, 0.5]], float)  # collinear
    f = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [7, 8, 9], [10, 11, 12]], np.int32)
    caster = MeshCaster(v, f)
    d = fan_dirs(2000, seed=3)
    targets = np.vstack([v[4], v[7:10].mean(0), v[10:13].mean(0)])
    d = np.vstack([d, targets / np.linalg.norm(targets, axis=1, keepdims=True)])
    t, prim = caster.cast(np.zeros(3), d, 100.0)
    assert not np.isnan(t).any()
    assert np.isfinite(t[prim >= 0]).all() and (t[prim >= 0] > 0).all()


def test_non_finite_meshes_are_rejected():
    v, f = wall(5.0)
    v[3, 1] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        MeshCaster(v, f)


@pytest.mark.parametrize("yaw", [0.0, 90.0, 180.0, -135.0])
def test_yaw_wraps_around_by_whole_turns(yaw):
    sim = Simulator(load_sensor("kitti-hdl64e-front"))
    ref = sim.render(1, [place(CarPose("suv", 1.0, 11.0, yaw), 1)]).image
    for turns in (-2, 1, 3):
        other = sim.render(1, [place(CarPose("suv", 1.0, 11.0, yaw + 360.0 * turns), 1)]).image
        assert other.tobytes() == ref.tobytes()


def test_nlopt_at_bounds_and_zero_width_bounds():
    from falsify.sampler import make_sampler
    space = parse_space({"dims": {"car_model": {"values": ["sedan"]},
                                  "x": {"min": -5.0, "max": 4.0, "step": 1.0},
                                  "y": {"values": [7.0]},
                                  "yaw": {"min": -180.0, "max": 180.0, "step": 45.0},
                                  "background": {"values": [0]}}})
    seen = []

    def evaluate(samples):
        out = []
        for s in samples:
            seen.append((s["x"], s["y"], s["yaw"]))
            out.append(0.1 + 0.01 * (s["x"] - 4.0) ** 2 + 1e-4 * (s["yaw"] + 180.0))
        return out

    for algo in ("LN_BOBYQA", "GN_DIRECT_L", "LN_COBYLA"):
        seen.clear()
        make_sampler(algo).run(space, evaluate, 40, 0)
        xs, ys, yaws = map(np.array, zip(*seen, strict=True))
        assert len(seen) <= 40
        assert xs.min() >= -5.0 and xs.max() <= 4.0 and (ys == 7.0).all()
        assert yaws.min() >= -180.0 and yaws.max() <= 180.0
        best = min(0.1 + 0.01 * (x - 4.0) ** 2 + 1e-4 * (w + 180.0)
                   for x, w in zip(xs, yaws, strict=True))
        assert best < 0.11  # the minimum sits on the corner x = 4, yaw = -180


def test_iou_with_empty_prediction_truth_or_both():
    label = np.zeros((4, 4), np.uint8)
    pred = np.zeros((4, 4), np.uint8)
    car = class_scores(confusion(pred, label))[1]
    assert car.iou is None and car.precision is None and car.recall is None and car.note
    label[0, 0] = 1
    car = class_scores(confusion(pred, label))[1]
    assert car.iou == 0.0 and car.recall == 0.0 and car.precision is None
    car = class_scores(confusion(label, np.zeros_like(label)))[1]
    assert car.iou == 0.0 and car.precision == 0.0 and car.recall is None


BUNDLED = ROOT / "models" / "weights" / "squeezeseg.onnx"


@pytest.mark.skipif(not BUNDLED.exists(), reason="bundled model not trained yet")
def test_network_on_empty_far_and_non_finite_scans():
    from falsify.models.runners import load_segmenter
    model = load_segmenter()
    empty = np.zeros((1, 64, 512, 6), np.float32)
    pred = model.predict(empty)
    assert (pred.classes == 0).all() and np.isfinite(pred.probabilities).all()
    sensor = load_sensor("kitti-hdl64e-front")
    far = np.zeros((1, 64, 512, 6), np.float32)
    far[0, ..., :3] = sensor.directions * sensor.max_range
    far[0, ..., 4] = sensor.max_range
    pred = model.predict(far)
    assert np.isfinite(pred.probabilities).all()
    for bad in (np.nan, np.inf, -np.inf):
        scan = far.copy()
        scan[0, 10, 20, 1] = bad
        with pytest.raises(FalsifyError, match="NaN|inf"):
            model.predict(scan)


def test_map_with_missing_cells_and_only_invalid_cells():
    space = parse_space({"dims": {"car_model": {"values": ["sedan"]},
                                  "x": {"min": 0.0, "max": 2.0, "step": 1.0},
                                  "y": {"min": 5.0, "max": 6.0, "step": 1.0},
                                  "background": {"values": [0, 1]}}})
    frame = pd.DataFrame([
        {"x": 0.0, "y": 5.0, "background": 0, "status": "ok", "car_iou": 0.5},
        {"x": 0.0, "y": 5.0, "background": 1, "status": "ok", "car_iou": 0.7},
        {"x": 1.0, "y": 5.0, "background": 0, "status": "invalid", "car_iou": None},
        {"x": 1.0, "y": 5.0, "background": 1, "status": "invalid", "car_iou": None},
        {"x": 2.0, "y": 6.0, "background": 0, "status": "undefined", "car_iou": None},
        {"x": 2.0, "y": 6.0, "background": 1, "status": "ok", "car_iou": 0.2},
        {"x": 1.99999999, "y": 6.0, "background": 1, "status": "ok", "car_iou": 0.4},
    ])
    cmap = miou_map(frame, space)
    assert cmap.miou[0, 0] == pytest.approx(0.6)
    assert math.isnan(cmap.miou[0, 1]) and cmap.invalid[0, 1] == 2 and cmap.samples[0, 1] == 0
    assert math.isnan(cmap.miou[1, 0]) and cmap.samples[1, 0] == 0  # no sample at all
    assert cmap.miou[1, 2] == pytest.approx(0.3) and cmap.undefined[1, 2] == 1
    blind = cmap.blind_spots(0.65)
    assert [(c.a, c.b) for c in blind] == [(2.0, 6.0), (0.0, 5.0)]
    assert all(c.miou is not None for c in blind)
    assert miou_map(frame.iloc[:0], space).samples.sum() == 0


def test_bad_threshold_and_unknown_sampler_are_clear_errors():
    from falsify.sampler import make_sampler
    with pytest.raises(ConfigError, match="allowed: grid, random, sobol"):
        make_sampler("GN_NOPE")
    with pytest.raises(ConfigError, match="threshold"):
        parse_space({"threshold": 0.0, "dims": {"car_model": {"values": ["sedan"]},
                                                "x": {"values": [0.0]}, "y": {"values": [5.0]},
                                                "background": {"values": [0]}}})
