"""Scans from scenes: analytic geometry, composition against a full re-cast, and the extremes."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import trimesh

from falsify.sensor.lidar import SensorPose, load_sensor
from falsify.sensor.raycast import MeshCaster, cast_through
from falsify.sensor.scanner import InvalidSample, PlacedCar, place
from falsify.sensor.simulator import Simulator, porosity_seed
from falsify.world.cars import car_mesh, car_parts
from falsify.world.materials import MATERIAL_ID, PASS_PROB
from falsify.world.space import CarPose, parse_space
from falsify.world.streets import build_background
from tests.conftest import CONFIGS


@pytest.fixture(scope="module")
def kitti():
    return load_sensor("kitti-hdl64e-front")


@pytest.fixture(scope="module")
def sim(kitti):
    return Simulator(kitti)


def ground_only(size: float = 4000.0):
    """A flat ground plane as a background: two big triangles, class 0."""
    h = size / 2
    v = np.array([[-h, -h, 0.0], [h, -h, 0.0], [h, h, 0.0], [-h, h, 0.0]])
    f = np.array([[0, 1, 2], [0, 2, 3]], dtype=np.int32)
    bg = build_background(0)
    return dataclasses.replace(bg, vertices=v, faces=f, face_class=np.zeros(2, np.uint8),
                               face_instance=np.zeros(2, np.int32), obstacles=(),
                               face_material=None, terrain=None)


def full_recast(sensor, bg, cars: list[PlacedCar], pose=SensorPose(), lod=2):
    """The naive reference: merge background and cars into one mesh and cast every ray, passing
    porous and glass triangles with the same hash-decided probabilities."""
    verts, faces, cls, inst = [bg.vertices], [bg.faces], [bg.face_class], [bg.face_instance]
    mats = [bg.materials()]
    n = len(bg.vertices)
    for c in cars:
        m = car_mesh(c.model, lod)
        v = np.asarray(m.vertices) @ c.rotation().T + c.translation()
        verts.append(v)
        faces.append(np.asarray(m.faces) + n)
        cls.append(np.full(len(m.faces), 1, np.uint8))
        inst.append(np.full(len(m.faces), c.instance, np.int32))
        mats.append(car_parts(c.model, lod)[2])
        n += len(v)
    caster = MeshCaster(np.concatenate(verts), np.concatenate(faces))
    rot = pose.rotation(sensor)
    dirs = sensor.directions.reshape(-1, 3) @ rot.T
    # each ray from its row's origin: dz up the sensor's own z axis (none: all at the origin)
    dz = np.repeat(np.asarray(sensor.ring_offsets_m or [0.0] * sensor.rows), sensor.columns)
    starts = pose.origin(sensor) + dz[:, None] * rot[:, 2]
    t, prim = cast_through(caster, starts, dirs, sensor.max_range,
                           PASS_PROB[np.concatenate(mats)], np.arange(len(dirs)),
                           porosity_seed(bg.bg_id))
    hit = prim >= 0
    c_all, i_all = np.concatenate(cls), np.concatenate(inst)
    out_cls = np.zeros(t.shape, np.uint8)
    out_inst = np.zeros(t.shape, np.int32)
    out_cls[hit], out_inst[hit] = c_all[prim[hit]], i_all[prim[hit]]
    t = np.where(hit & (t >= sensor.min_range), t, 0.0)
    valid = t > 0
    # the range channel is the point's distance from the sensor origin, as in KITTI's scans
    point = dirs @ rot * t[:, None] + np.where(valid, dz, 0.0)[:, None] * [0.0, 0.0, 1.0]
    t = np.linalg.norm(point, axis=1)
    return (t.reshape(sensor.shape), np.where(valid, out_cls, 0).reshape(sensor.shape),
            np.where(valid, out_inst, 0).reshape(sensor.shape))


def assert_same_as_full(sim, bg_id, cars, pose=SensorPose()):
    scan = sim.render(bg_id, cars, pose)
    rng, cls, inst = full_recast(sim.sensor, sim.background(bg_id)[1], cars, pose, sim.lod)
    np.testing.assert_array_equal(scan.image[..., 5].astype(np.uint8), cls)
    np.testing.assert_array_equal(scan.instance, inst)
    # 1 mm: a ray re-cast past glass or foliage starts from a float32 point (in the car's frame
    # for the composed scan, the street's for the full re-cast); 20x below the range noise.
    np.testing.assert_allclose(scan.image[..., 4], rng, atol=1e-3, rtol=0)
    return scan


def test_pose_matrix_is_rotation_then_translation():
    car = place(CarPose("box", -2.0, 10.0, 30.0), 1)
    pts = np.array([[1.0, 0.0, 0.0], [0.5, -2.0, 1.5]])
    moved = trimesh.transform_points(pts, car.matrix())
    assert moved == pytest.approx(pts @ car.rotation().T + car.translation())
    assert moved[0] == pytest.approx([10.0 + np.cos(np.radians(30.0)), 2.0
                                      + np.sin(np.radians(30.0)), 0.0])


def test_composed_scan_equals_full_recast_pixel_for_pixel(sim):
    cars = [PlacedCar("sedan", 10.0, 1.0, 0.0, 1), PlacedCar("van", 14.0, -0.5, 30.0, 2),
            PlacedCar("pickup", 22.0, 3.0, -100.0, 3), PlacedCar("coupe", 40.0, -6.0, 180.0, 4)]
    cars = [sim.settle(3, c) for c in cars]  # standing on the street's camber and grade
    scan = assert_same_as_full(sim, 3, cars, sim.ego_pose(3))
    # The van stands partly behind the sedan: both are seen, and occlusion is by nearest hit.
    assert {1, 2, 3} <= set(np.unique(scan.instance).tolist())


def test_composition_sees_through_glass_and_foliage_like_a_full_recast(sim):
    """Rays pass car glass into the cabin and through tree crowns; the composed scan still
    equals the full re-cast, and the scene really holds both kinds of pass-through."""
    bg = sim.background(0)[1]
    mats = bg.materials()
    assert (mats == MATERIAL_ID["foliage"]).any() and (mats == MATERIAL_ID["glass"]).any()
    cars = [sim.settle(0, PlacedCar(m, x, y, h, i + 1)) for i, (m, x, y, h) in enumerate(
        [("suv", 8.0, 2.0, 90.0), ("compact", 12.0, -3.0, 0.0), ("roadster", 18.0, 1.0, 45.0)])]
    pose = sim.ego_pose(0)
    scan = assert_same_as_full(sim, 0, cars, pose)
    layer = sim.background_hits(0, pose)
    hit_foliage = layer.mat == MATERIAL_ID["foliage"]
    assert hit_foliage.any()
    assert (scan.instance == 1).sum() > 100

def test_composition_on_360_sensor_and_posed_ego():
    sensor = load_sensor("kitti-hdl64e-360")
    sim = Simulator(sensor)
    pose = SensorPose(12.0, -2.0, 170.0)
    cars = [PlacedCar("suv", 5.0, -2.5, 90.0, 1), PlacedCar("wagon", 20.0, 2.0, 0.0, 2),
            PlacedCar("hatchback", 12.0, 2.6, 10.0, 3)]  # beside the ego, across the seam
    assert_same_as_full(sim, 7, cars, pose)


def offset_sensor(name: str = "kitti-hdl64e-front"):
    """A KITTI preset with the real HDL-64E's ring origins: upper block 0.2 m above the origin,
    lower block 0.11 m (the object frames' fit)."""
    base = load_sensor(name)
    return dataclasses.replace(base, ring_offsets_m=(0.2,) * 32 + (0.11,) * 32)


def test_composition_with_ring_origins_equals_full_recast():
    """Rays from per-row origins: the cached background plus windowed car casts still equal a
    full re-cast, cars close by included (where the offset moves a ring's elevation most)."""
    sim = Simulator(offset_sensor())
    cars = [PlacedCar("sedan", 3.6, 0.0, 0.0, 1), PlacedCar("van", 9.0, -2.5, 20.0, 2),
            PlacedCar("suv", 25.0, 3.0, 90.0, 3)]
    cars = [sim.settle(3, c) for c in cars]
    scan = assert_same_as_full(sim, 3, cars, sim.ego_pose(3))
    assert {1, 2, 3} <= set(np.unique(scan.instance).tolist())
    sim360 = Simulator(offset_sensor("kitti-hdl64e-360"))
    assert_same_as_full(sim360, 7, [PlacedCar("hatchback", 12.0, 2.6, 10.0, 1)],
                        SensorPose(12.0, -2.0, 170.0))


def test_ring_origins_on_a_plane_give_the_analytic_ranges():
    """On flat ground every return's z is -mount_height, and row k meets the ground at the
    horizontal range (h + dz_k) / tan(-elevation_k): the model the ring fit recovers."""
    sensor = offset_sensor()
    scan = Simulator(sensor, background_source=lambda _id: ground_only()).render(0, [])
    img = scan.image
    hits = img[..., 4] > 0
    el = np.radians(np.asarray(sensor.elevations_deg))
    dz = np.asarray(sensor.ring_offsets_m)
    np.testing.assert_allclose(img[..., 2][hits], -sensor.mount_height, atol=1e-4)
    for r in np.flatnonzero(hits.any(axis=1)):
        horizontal = np.hypot(img[r, :, 0], img[r, :, 1])[hits[r]]
        want = (sensor.mount_height + dz[r]) / np.tan(-el[r])
        np.testing.assert_allclose(horizontal, want, rtol=1e-4)
        # the elevation seen from the origin is the ring's plus about dz / range
        seen = np.arctan2(img[r, :, 2], np.hypot(img[r, :, 0], img[r, :, 1]))[hits[r]]
        assert np.all(seen > el[r]) and np.allclose(
            seen, np.arctan2(-sensor.mount_height, want), atol=1e-6)
    # all zeros is the single-origin sensor: the same bytes as none at all
    flat = dataclasses.replace(sensor, ring_offsets_m=(0.0,) * 64)
    plain = dataclasses.replace(sensor, ring_offsets_m=())
    a = Simulator(flat).render(2, [PlacedCar("sedan", 9.0, 1.0, 0.0, 1)])
    b = Simulator(plain).render(2, [PlacedCar("sedan", 9.0, 1.0, 0.0, 1)])
    assert a.image.tobytes() == b.image.tobytes()


def test_box_car_ranges_match_analytic_distance(tmp_path, kitti):
    """A user car that is a box: every car pixel's range equals the ray-box distance (1 cm)."""
    box = trimesh.creation.box((4.0, 2.0, 1.5))
    box.apply_translation((0.0, 0.0, 0.75 + 0.3))  # floating 0.3 m up: rays pass under it
    path = tmp_path / "box.stl"
    box.export(path)
    space = parse_space({"dims": {"car_model": {"values": ["box"]}, "x": {"values": [0.5]},
                                  "y": {"values": [9.0]}, "background": {"values": [0]}},
                         "car_models": {"box": {"file": str(path)}}})
    sim = Simulator(kitti, space.user_cars)
    sample = space.make({})
    scan = sim.scan(sample)
    car = scan.instance == 1  # the sampled car (parked cars of the background are 1000+)
    assert car.sum() > 300
    # Slab test in the car's frame, where the box spans x -2..2, y -1..1, z 0..1.5 after
    # load_user_car drops it to the ground; the car and the ego stand on the street's terrain.
    lo, hi = np.array([-2.0, -1.0, 0.0]), np.array([2.0, 1.0, 1.5])
    placed = sim.placed_cars(sample)[0]
    pose = sim.ego_pose(sample.background)
    rot = placed.rotation()
    d = kitti.directions[car] @ pose.rotation(kitti).T @ rot
    o = (pose.origin(kitti) - placed.translation()) @ rot
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (lo - o) / d, (hi - o) / d
    t_near = np.minimum(t1, t2).max(axis=1)
    np.testing.assert_allclose(scan.image[..., 4][car], t_near, atol=0.01)


def test_builtin_car_ranges_match_an_exact_float64_cast(sim):
    """Every sampled-car pixel's range equals trimesh's exact (float64) intersection."""
    car = place(CarPose("sedan", -1.0, 12.0, 25.0), 1)
    scan = sim.render(0, [car])
    mask = scan.instance == 1
    assert mask.sum() > 500
    dirs = sim.sensor.directions[mask] @ car.rotation()  # into the car frame
    origin = (np.array([0.0, 0.0, sim.sensor.mount_height]) - car.translation()) @ car.rotation()
    pick = np.arange(0, len(dirs), 11)
    # Glass always lets the ray through: the first return is the first non-glass triangle.
    opaque = car_parts("sedan")[2] != MATERIAL_ID["glass"]
    exact = moller_trumbore(car_mesh("sedan").submesh([opaque], append=True), origin,
                            dirs[pick])
    np.testing.assert_allclose(scan.image[..., 4][mask][pick], exact, atol=0.01)


def moller_trumbore(mesh, origin: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """Nearest hit distance of each ray against every triangle, in float64 (reference only)."""
    tri = np.asarray(mesh.triangles, dtype=np.float64)
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    s = origin - tri[:, 0]
    out = np.full(len(dirs), np.inf)
    for i, d in enumerate(dirs):
        p = np.cross(d, e2)
        det = (e1 * p).sum(1)
        ok = np.abs(det) > 1e-12
        inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
        u = (s * p).sum(1) * inv
        q = np.cross(s, e1)
        v = (q @ d) * inv
        t = (e2 * q).sum(1) * inv
        hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0)
        if hit.any():
            out[i] = t[hit].min()
    return out


def test_models_give_visibly_different_scans(sim):
    counts = {}
    for model in ("sedan", "van", "pickup"):
        scan = sim.render(0, [PlacedCar(model, 10.0, 0.0, 0.0, 1)])
        counts[model] = (scan.image[..., 5] == 1).sum(axis=0)
    assert abs(int(counts["van"].sum()) - int(counts["sedan"].sum())) > 100
    assert (counts["pickup"] != counts["sedan"]).sum() > 20


def test_same_sample_gives_same_bytes(kitti):
    space = parse_space({"dims": {"car_model": {"values": ["suv"]}, "x": {"values": [1.0]},
                                  "y": {"values": [12.0]}, "background": {"values": [2]}}})
    a = Simulator(kitti).scan(space.make({}))
    b = Simulator(kitti).scan(space.make({}))
    assert a.image.tobytes() == b.image.tobytes()
    assert a.instance.tobytes() == b.instance.tobytes()


def test_yaw_wraps_around(sim):
    scans = [sim.render(0, [place(CarPose("pickup", 1.0, 10.0, yaw), 1)]).image
             for yaw in (-180.0, 180.0, 540.0, -540.0)]
    for s in scans[1:]:
        assert s.tobytes() == scans[0].tobytes()


def test_max_range_edge_and_beyond():
    sensor = load_sensor("kitti-hdl64e-front", max_range=40.0)
    sim = Simulator(sensor, background_source=lambda _id: ground_only())
    inside = sim.render(0, [PlacedCar("van", 38.0, 0.0, 0.0, 1)])
    assert (inside.image[..., 5] == 1).sum() > 0
    assert inside.image[..., 4].max() <= 40.0
    beyond = sim.render(0, [PlacedCar("van", 43.0, 0.0, 0.0, 1)])
    assert (beyond.image[..., 5] == 1).sum() == 0
    # A car wholly beyond max range is not in the scene: no ray is cast at it.
    layer = sim.background_hits(0, SensorPose())
    copy = layer.copy()
    assert sim.cast_car(copy, PlacedCar("van", 200.0, 0.0, 0.0, 1), SensorPose()) == 0


def test_car_partly_outside_the_fov(sim):
    car = PlacedCar("sedan", 8.0, 8.5, 0.0, 1)  # on the 45 degree edge of the front view
    scan = assert_same_as_full(sim, 0, [car])
    cols = np.flatnonzero((scan.image[..., 5] == 1).any(axis=0))
    assert len(cols) > 0 and cols.min() == 0
    outside = PlacedCar("sedan", -5.0, 10.0, 0.0, 1)  # behind-left: no ray of the front view
    layer = sim.background_hits(0, SensorPose())
    copy = layer.copy()
    assert sim.cast_car(copy, outside, SensorPose()) == 0


def test_car_one_metre_from_the_sensor(sim):
    # The rear of a sedan (half length 2.35 m) 1 m ahead of the sensor.
    car = PlacedCar("sedan", 3.35, 0.0, 0.0, 1)
    scan = assert_same_as_full(sim, 0, [car])
    near = scan.image[..., 4][scan.instance == 1]
    assert near.size > 3000 and 1.0 <= near.min() < 2.5
    # As a sample, a car there overlaps the ego vehicle and is invalid with a reason.
    space = parse_space({"dims": {"car_model": {"values": ["sedan"]}, "x": {"values": [0.0]},
                                  "y": {"values": [3.35]}, "background": {"values": [0]}}})
    with pytest.raises(InvalidSample, match="ego vehicle"):
        sim.scan(space.make({}))


def test_sample_overlapping_cars_or_background_is_invalid(sim):
    space = parse_space({"dims": {"car_model": {"values": ["sedan"]}, "x": {"values": [0.0]},
                                  "y": {"values": [10.0]}, "count": {"values": [2]},
                                  "x_2": {"values": [0.5]}, "y_2": {"values": [11.0]},
                                  "background": {"values": [0]}}})
    with pytest.raises(InvalidSample, match="intersects car 1"):
        sim.scan(space.make({}))
    bg = build_background(0)
    curb_y = bg.road_half_width
    space = parse_space({"dims": {"car_model": {"values": ["sedan"]},
                                  "x": {"values": [-curb_y]}, "y": {"values": [40.0]},
                                  "background": {"values": [0]}}})
    with pytest.raises(InvalidSample, match="background"):
        sim.scan(space.make({}))


def test_world_shifted_by_1e5_gives_same_ranges(kitti):
    offset = np.array([1e5, -1e5, 0.0])
    base = build_background(4)
    shifted = dataclasses.replace(base, vertices=base.vertices + offset)
    near, far = Simulator(kitti), Simulator(kitti, background_source=lambda _id: shifted)
    cars = [PlacedCar("sedan", 11.0, -1.0, 15.0, 1)]
    cars_far = [dataclasses.replace(c, x=c.x + offset[0], y=c.y + offset[1]) for c in cars]
    a = near.render(4, cars)
    b = far.render(4, cars_far, SensorPose(offset[0], offset[1], 0.0))
    np.testing.assert_array_equal(a.image[..., 5], b.image[..., 5])
    np.testing.assert_allclose(a.image[..., 4], b.image[..., 4], atol=1e-3)


def test_grazing_ground_rays_match_the_plane():
    sensor = load_sensor("kitti-hdl64e-front")
    sim = Simulator(sensor, background_source=lambda _id: ground_only())
    scan = sim.render(0, [])
    el = np.radians(np.asarray(sensor.elevations_deg))
    expected = sensor.mount_height / np.sin(-el)  # range to the plane along each ray
    hits = scan.image[..., 4] > 0
    for r in range(sensor.rows):
        if el[r] >= 0:
            assert not hits[r].any()  # looking up: nothing to hit
        elif expected[r] > sensor.max_range:
            assert not hits[r].any()  # the plane is there but beyond max range
        else:
            assert hits[r].all()
            np.testing.assert_allclose(scan.image[r, :, 4] * np.cos(np.radians(
                sensor.azimuths_deg * 0)), expected[r], atol=0.01)


def test_rays_through_vertices_and_edges_do_not_leak():
    # A wall of 40x40 quads at x = 10; aim one ray at every vertex and every edge midpoint.
    n = 40
    ys, zs = np.meshgrid(np.linspace(-5, 5, n + 1), np.linspace(-5, 5, n + 1), indexing="ij")
    v = np.stack([np.full(ys.size, 10.0), ys.ravel(), zs.ravel()], axis=1)
    idx = np.arange(ys.size).reshape(n + 1, n + 1)
    a, b, c, d = idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]
    faces = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3),
                            np.stack([a, c, d], -1).reshape(-1, 3)]).astype(np.int32)
    caster = MeshCaster(v, faces)
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    targets = np.concatenate([v, (v[edges[:, 0]] + v[edges[:, 1]]) / 2])
    inner = (np.abs(targets[:, 1]) < 5) & (np.abs(targets[:, 2]) < 5)
    targets = targets[inner]
    dirs = targets / np.linalg.norm(targets, axis=1, keepdims=True)
    t, prim = caster.cast(np.zeros(3), dirs, 100.0)
    assert (prim >= 0).all(), f"{(prim < 0).sum()} of {len(prim)} rays leaked"
    np.testing.assert_allclose(t, np.linalg.norm(targets, axis=1), atol=1e-4)


def test_image_only_dims_do_not_change_the_scan(kitti):
    space = parse_space({"dims": {"car_model": {"values": ["sedan"]}, "x": {"values": [0.0]},
                                  "y": {"values": [9.0]}, "background": {"values": [1]},
                                  "colour": {"values": ["red", "white"]},
                                  "weather": {"values": ["sun", "rain"]}}})
    sim = Simulator(kitti)
    a = sim.scan(space.make({"colour": "red", "weather": "sun"}))
    b = sim.scan(space.make({"colour": "white", "weather": "rain"}))
    assert a.image.tobytes() == b.image.tobytes()
    assert space.make({"colour": "red"}).scene_key() == space.make({"colour": "white"}).scene_key()


def test_paper_config_first_sample_scans(sim):
    from falsify.world.space import load_space
    space = load_space(CONFIGS / "paper.toml")
    scan = sim.scan(space.grid()[0])
    assert scan.image.shape == (64, 512, 6) and scan.image.dtype == np.float32
    assert scan.count(1) > 200
