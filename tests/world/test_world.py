"""The richer world: seeded generators, porous and glass surfaces, terrain-following poses and
the fitted sensor return model."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys

import numpy as np
import pytest

from falsify.sensor.lidar import SensorPose, load_sensor
from falsify.sensor.raycast import MeshCaster, cast_through, unit_hash
from falsify.sensor.returns import load_return_model
from falsify.sensor.scanner import PlacedCar
from falsify.sensor.simulator import Simulator
from falsify.world import buildings, road_users, terrain, vegetation
from falsify.world.materials import MATERIAL_ID, MATERIALS, PASS_PROB
from falsify.world.street_layout import _layout, _Street
from falsify.world.streets import build_background
from tests.conftest import ROOT


def _terrain(seed: int = 3) -> terrain.Terrain:
    return terrain.draw_terrain(np.random.default_rng(seed), 10.0, 0.15, (3.0, 4.0))


def _bytes(st: _Street) -> bytes:
    return b"".join(v.tobytes() + f.tobytes() for v, f in st.meshes) + b"".join(
        m.tobytes() for m in st.mat)


GENERATORS = {
    "bushes": lambda st, t, r: vegetation.bushes(st, t, r, 1, (0.5, 20.0), (-40.0, 60.0), 0.05),
    "hedge": lambda st, t, r: vegetation.hedge(st, t, r, -30.0, 30.0, 16.0, 1, "h"),
    "tree": lambda st, t, r: vegetation.tree(st, t, r, 5.0, 16.0, 2.0, False, "t"),
    "tree band": lambda st, t, r: vegetation.tree_band(st, t, r, -1, 20.0, (-50.0, 50.0), 12.0,
                                                       6.0),
    "wall": lambda st, t, r: buildings.wall(st, t, r, -30.0, 30.0, 14.0, 1, "w"),
    "fence": lambda st, t, r: buildings.fence(st, t, r, -30.0, 30.0, 14.0, 1, "f"),
    "railing": lambda st, t, r: buildings.railing(st, t, r, -30.0, 30.0, 14.0, 1, "r"),
    "guard rail": lambda st, t, r: buildings.guard_rail(st, t, r, -30.0, 30.0, -10.5, -1, "g"),
    "sign": lambda st, t, r: buildings.sign(st, t, r, 30.0, -10.6, -1, "s"),
    "building": lambda st, t, r: buildings.building(st, t, r, 30.0, 55.0, 20.0, 12.0, 15.0,
                                                     1, "b"),
}


@pytest.mark.parametrize("name", list(GENERATORS))
def test_generators_are_seeded_and_deterministic(name):
    def run(seed):
        st = _Street()
        GENERATORS[name](st, _terrain(), np.random.default_rng(seed))
        return st
    a, b, c = run(1), run(1), run(2)
    assert a.meshes, f"{name} built nothing"
    assert _bytes(a) == _bytes(b)
    if name != "guard rail":  # standard rail: drawn from nothing but its span
        assert _bytes(a) != _bytes(c)
    for (v, f), m in zip(a.meshes, a.mat, strict=True):
        assert np.isfinite(v).all() and f.max() < len(v) and len(m) == len(f)


@pytest.mark.parametrize("kind", road_users.OTHER_VEHICLES)
def test_other_vehicles_are_seeded_with_materials(kind):
    a = road_users.merge_parts(road_users.vehicle_parts(kind, np.random.default_rng(5)))
    b = road_users.merge_parts(road_users.vehicle_parts(kind, np.random.default_rng(5)))
    for x, y in zip(a, b, strict=True):
        assert x.tobytes() == y.tobytes()
    v, f, mat = a
    assert v[:, 2].min() == 0.0 and len(mat) == len(f)
    ext = np.ptp(v, axis=0)
    assert ext[0] > 3.4 and ext[2] > 1.1  # longer or taller than any car model
    if kind != "trailer":
        assert (mat == MATERIAL_ID["glass"]).any()


def test_pedestrian_poses_vary_and_repeat():
    shapes_ = [road_users.merge_parts(road_users.pedestrian_parts(np.random.default_rng(s)))[0]
               for s in range(12)]
    heights = [float(np.ptp(v[:, 2])) for v in shapes_]
    assert min(heights) < 1.5 < max(heights)  # children and adults
    assert len({v.tobytes() for v in shapes_}) == 12
    again = road_users.merge_parts(road_users.pedestrian_parts(np.random.default_rng(3)))[0]
    assert again.tobytes() == shapes_[3].tobytes()


def test_terrain_is_seeded_and_not_a_plane():
    assert _terrain(4) == _terrain(4)
    kinds = {s.kind for i in range(40) for s in _terrain(i).sides}
    assert kinds == set(terrain.ROADSIDE_KINDS)
    t = next(_terrain(i) for i in range(40) if _terrain(i).grade != 0.0)
    x = np.linspace(-50, 50, 11)
    assert np.ptp(t.road_z(x)) > 0.05  # grade and crests
    # Camber: the crown is higher than the road edge.
    assert t.height(0.0, 0.0) > t.height(0.0, t.half_width - 0.01)


def test_poses_follow_the_terrain():
    """The ego's sensor rides on the ground's height and slope; a settled car's wheels touch it."""
    sensor = load_sensor("kitti-hdl64e-front")
    sim = Simulator(sensor)
    bg_id = next(i for i in range(20) if abs(_layout(i).terrain.grade) > 0.01)
    t = build_background(bg_id).terrain
    pose = sim.ego_pose(bg_id, SensorPose(30.0, -3.0, 0.0))
    assert pose.z == pytest.approx(float(t.height(30.0, -3.0)), abs=0.05)
    assert math.tan(math.radians(-pose.pitch_deg)) == pytest.approx(t.grade, abs=0.035)
    assert pose.origin(sensor)[2] == pytest.approx(pose.z + sensor.mount_height)
    car = sim.settle(bg_id, PlacedCar("sedan", 15.0, 2.0, 0.0, 1))
    v = np.asarray(sim.car_mesh("sedan").vertices) @ car.rotation().T + car.translation()
    low = v[v[:, 2] < v[:, 2].min() + 0.02]  # the tyres' contact patches
    ground = t.height(low[:, 0], low[:, 1])
    assert np.abs(low[:, 2] - ground).max() < 0.06


def _slab_scene(material: str, n: int = 40_000):
    """A 10 × 10 m quad of `material` at x = 5 in front of a concrete wall at x = 10; rays
    from the origin, each with its own id."""
    v = np.array([[5, -5, -5], [5, 5, -5], [5, 5, 5], [5, -5, 5],
                  [10, -9, -9], [10, 9, -9], [10, 9, 9], [10, -9, 9]], dtype=np.float64)
    f = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]])
    mats = np.array([MATERIAL_ID[material]] * 2 + [MATERIAL_ID["concrete"]] * 2)
    rng = np.random.default_rng(0)
    d = np.column_stack([np.ones(n), rng.uniform(-0.8, 0.8, (n, 2))])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    t, prim = cast_through(MeshCaster(v, f), np.zeros(3), d, 100.0, PASS_PROB[mats],
                           np.arange(n), seed=11)
    return t, prim, d


@pytest.mark.parametrize("material", ["foliage", "hedge", "chain-link"])
def test_porous_surface_returns_with_its_probability(material):
    """Over many rays the fraction stopped by one porous crossing is 1 - pass_prob, within
    4 binomial standard deviations; the others end on the wall behind at the right range."""
    t, prim, d = _slab_scene(material)
    p_return = 1.0 - MATERIALS[MATERIAL_ID[material]].pass_prob
    n = len(t)
    on_slab = prim < 2
    sd = math.sqrt(p_return * (1 - p_return) / n)
    assert abs(on_slab.mean() - p_return) < 4 * sd
    assert (prim >= 0).all()
    np.testing.assert_allclose(t[on_slab], 5.0 / d[on_slab, 0], rtol=1e-5)
    np.testing.assert_allclose(t[~on_slab], 10.0 / d[~on_slab, 0], rtol=1e-5)


def test_glass_never_returns_in_the_caster_or_the_scan():
    t, prim, _ = _slab_scene("glass", 5_000)
    assert (prim >= 2).all()  # every ray passed the glass to the wall
    sensor = load_sensor("kitti-hdl64e-front")
    sim = Simulator(sensor)
    cars = [sim.settle(0, PlacedCar(m, x, y, 0.0, i + 1))
            for i, (m, x, y) in enumerate([("sedan", 8.0, 0.0), ("van", 14.0, -3.0)])]
    layer = sim.background_hits(0, sim.ego_pose(0)).copy()
    for c in cars:
        sim.cast_car(layer, c, sim.ego_pose(0))
    assert not (layer.mat == MATERIAL_ID["glass"]).any()
    # Seats behind the windows are hit through the glass.
    assert ((layer.mat == MATERIAL_ID["interior"]) & (layer.inst >= 1)).any()


def test_hash_is_uniform_and_reproducible():
    u = unit_hash(np.arange(100_000), np.full(100_000, 7), 3)
    assert u.min() >= 0.0 and u.max() < 1.0
    assert abs(u.mean() - 0.5) < 4 * math.sqrt(1 / 12 / len(u))
    assert (u == unit_hash(np.arange(100_000), np.full(100_000, 7), 3)).all()
    assert (u != unit_hash(np.arange(100_000), np.full(100_000, 7), 4)).mean() > 0.99


def test_return_model_loads_and_is_bounded():
    m = load_return_model("kitti-hdl64e")
    cfg = json.loads((ROOT / "configs" / "returns" / "kitti-hdl64e.json").read_text())
    assert cfg["fitted_on"] == ["000000.bin", "000001.bin", "000002.bin"]
    i = m.intensity(np.arange(len(MATERIALS)), np.linspace(0, 1, len(MATERIALS)),
                    np.linspace(0, 120, len(MATERIALS)))
    assert ((i >= 0) & (i <= 1)).all()
    p = m.p_return(np.linspace(0, 1, 50))
    assert ((p >= 0) & (p <= 1)).all()
    keep = m.keep_map(64, load_sensor("kitti-hdl64e-360").azimuths_deg)
    assert keep.shape == (64, 2048) and keep[:40].min() > 0.5 and keep[-1].min() < 0.2


def test_scans_are_deterministic_with_returns_and_intensity():
    sensor = load_sensor("kitti-hdl64e-front", range_noise=0.02)
    sim = Simulator(sensor)
    cars = [sim.settle(2, PlacedCar("sedan", 12.0, 1.0, 10.0, 1))]
    a = sim.render(2, cars, sim.ego_pose(2), np.random.default_rng(9))
    b = Simulator(sensor).render(2, cars, sim.ego_pose(2), np.random.default_rng(9))
    assert a.image.tobytes() == b.image.tobytes()
    valid = a.valid
    assert (a.image[..., 3][valid] > 0).mean() > 0.9  # intensity rendered
    assert 0.80 < valid.mean() < 0.95  # KITTI's object frames: 0.86-0.91 in the front 90°


def test_fit_refuses_evaluation_scans(tmp_path):
    """A frame that $FALSIFY_HOLDOUT's manifest holds out is refused, whatever its folder."""
    scan = tmp_path / "object" / "velodyne" / "x.bin"
    scan.parent.mkdir(parents=True)
    scan.write_bytes(np.ones((100, 4), np.float32).tobytes())
    manifest = tmp_path / "eval.toml"
    assert subprocess.run([sys.executable, "-m", "falsify", "holdout", str(scan), "--out",
                           str(manifest)], capture_output=True, cwd=ROOT).returncode == 0
    r = subprocess.run([sys.executable, "-m", "falsify", "fit-returns", str(scan), "--out",
                        str(tmp_path / "o.json")], capture_output=True, text=True, cwd=ROOT,
                       env={**os.environ, "FALSIFY_HOLDOUT": str(manifest)})
    assert r.returncode == 2 and "x.bin: a held-out scan" in r.stderr, r.stderr
    assert not (tmp_path / "o.json").exists()
    r = subprocess.run([sys.executable, "-m", "falsify", "fit-returns", "nosuch.bin", "--out",
                        str(tmp_path / "o.json")], capture_output=True, text=True, cwd=tmp_path)
    assert r.returncode == 2 and "nosuch.bin: no such file" in r.stderr


@pytest.mark.parametrize("bad", ["nope", 3])
def test_unknown_return_model_names_the_key(bad):
    from falsify.errors import ConfigError
    with pytest.raises(ConfigError, match="returns: .*kitti-hdl64e"):
        load_sensor("kitti-hdl64e-front", returns=bad)
