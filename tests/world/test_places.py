"""Streets fitted to real places: the place a labelled scan shows, which place a street takes,
the street it builds (deterministic, free zone kept, roadside and pose from the place), the
profile that carries places, and the space key that asks for them."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from falsify.errors import ConfigError
from falsify.jobs.fit_world import place_of, road_edges, scene_stats
from falsify.semantic import RAW_ID, join_label
from falsify.sensor.lidar import load_sensor
from falsify.sensor.scanner import InvalidSample
from falsify.sensor.simulator import Simulator
from falsify.world.places import (
    BANDS_M,
    GROUPS,
    ROAD_HALF_M,
    Place,
    place_index,
    place_street,
    road_half_width,
    road_offset,
)
from falsify.world.profile import PROFILE_VERSION, WorldProfile, load_profile
from falsify.world.space import Sample, load_space
from falsify.world.streets import FREE_ZONE, SENSOR_CLEARANCE, build_background

ROOT = Path(__file__).resolve().parents[2]


def _place(name: str = "p", pitch: float = 1.5, green: float = 0.4, unlabeled: float = 0.05,
           near: float = 4.0, edges: tuple[float, float] | None = None) -> Place:
    shares = {g: (0.0, 0.0, 0.0) for g in GROUPS}
    shares["vegetation"] = (green, green, green)
    shares["unlabeled"] = (unlabeled, unlabeled, unlabeled)
    shares["fence"] = (0.05, 0.05, 0.05)
    return Place(name=name, pitch_deg=pitch, height_m=1.8,
                 shares=tuple(shares[g] for g in GROUPS), clutter_left_m=near,
                 clutter_right_m=near, edge_left_m=edges and edges[0],
                 edge_right_m=edges and edges[1])


def _profile(places: tuple[Place, ...]) -> WorldProfile:
    n = len(places)
    return WorldProfile(name="places", scans=tuple(p.name for p in places),
                        pitch_deg=tuple(p.pitch_deg for p in places),
                        height_m=tuple(p.height_m for p in places), cars_front=(1,) * n,
                        base_pitch_deg=0.0, base_height_m=1.73, pitch_jitter_deg=0.0,
                        height_jitter_m=0.0, places=places)


def test_place_of_counts_shares_per_band_and_the_nearest_clutter():
    # 100 road points at 10 m, 100 vegetation at 20 m (3 m to the right), 50 unlabeled at 40 m.
    pts = np.concatenate([np.tile([10.0, 0.0, -1.7, 0.0], (100, 1)),
                          np.tile([20.0, -3.0, 0.0, 0.0], (100, 1)),
                          np.tile([40.0, 5.0, 0.0, 0.0], (50, 1))]).astype(np.float32)
    pts[:100, 0] += np.linspace(0, 1, 100)           # the road is a plane, not one point
    pts[:100, 1] += np.linspace(-1, 1, 100)
    sem = np.array([RAW_ID["road"]] * 100 + [RAW_ID["vegetation"]] * 100
                   + [RAW_ID["unlabeled"]] * 50, np.uint32)
    labels = join_label(sem, np.zeros_like(sem)).astype(np.uint32)
    place = place_of("s", pts, labels, scene_stats("s", pts, labels))
    assert place.share("road") == (1.0, 0.0, 0.0)
    assert place.share("vegetation") == (0.0, 1.0, 0.0)
    assert place.share("unlabeled") == (0.0, 0.0, 1.0)
    assert place.clutter_right_m == pytest.approx(3.0)
    assert place.clutter_left_m == 30.0                 # none on the left within 5..30 m ahead
    assert len(BANDS_M) - 1 == len(place.share("car"))


def test_road_edges_are_where_the_roadside_starts_on_each_side():
    # Roadside from 3 m on the left and 4 m on the right to 12 m, spread evenly (the 10th
    # percentile: 3.9 and 4.8 m), and a bend's terrain on the road in two of the ten slices.
    rng = np.random.default_rng(0)
    x = rng.uniform(5.0, 14.0, 4000)
    y = rng.uniform(-12.0, 12.0, 4000)
    roadside = (y > 3.0) | (y < -4.0)
    bend = (x > 5.0) & (x < 7.0) & (np.abs(y) < 1.0)
    left, right = road_edges(x, y, roadside | bend)
    assert left == pytest.approx(3.9, abs=0.15) and right == pytest.approx(4.8, abs=0.15)
    assert road_edges(x, y, np.zeros_like(roadside)) == (25.0, 25.0)


def test_place_index_takes_every_place_once_over_n_streets():
    for n in (1, 2, 7, 21, 30):
        assert sorted(place_index(i, n) for i in range(n)) == list(range(n))
        assert sorted(place_index(i + 1000, n) for i in range(n)) == list(range(n))


def test_place_json_round_trip_and_errors_name_the_key():
    p = _place()
    assert Place.from_json(json.loads(json.dumps(p.to_json())), "w") == p
    raw = p.to_json()
    with pytest.raises(ConfigError, match="missing key 'pitch_deg'"):
        Place.from_json({k: v for k, v in raw.items() if k != "pitch_deg"}, "w")
    with pytest.raises(ConfigError, match="unknown key 'colour'"):
        Place.from_json({**raw, "colour": 1}, "w")
    with pytest.raises(ConfigError, match="not 'trees'"):
        Place.from_json({**raw, "shares": {**raw["shares"], "trees": [0, 0, 0]}}, "w")
    bad = {**raw["shares"], "road": [0.5, 2.0, 0.1]}
    with pytest.raises(ConfigError, match="shares.road"):
        Place.from_json({**raw, "shares": bad}, "w")
    assert "edge_left_m" not in raw                      # a place measured without its edges
    edged = _place(edges=(3.0, 6.5))
    assert Place.from_json(json.loads(json.dumps(edged.to_json())), "w") == edged
    with pytest.raises(ConfigError, match="edge_left_m and edge_right_m go together"):
        Place.from_json({**raw, "edge_left_m": 3.0}, "w")
    with pytest.raises(ConfigError, match="edge_right_m must be a distance"):
        Place.from_json({**raw, "edge_left_m": 3.0, "edge_right_m": -1.0}, "w")


def test_a_place_street_is_deterministic_keeps_the_free_zone_and_adds_roadside():
    place = _place()
    a = place_street(3, place, (1.2, 0.07))
    b = place_street(3, place, (1.2, 0.07))
    assert a.vertices.tobytes() == b.vertices.tobytes()
    assert a.face_semantic.tobytes() == b.face_semantic.tobytes()
    assert (a.ego_pitch_deg, a.ego_dz) == (1.2, 0.07)
    (x0, x1), (y0, y1) = FREE_ZONE
    for fp in a.obstacles:
        if fp.label.startswith("curb"):
            continue
        lo, hi = fp.polygon.min(axis=0), fp.polygon.max(axis=0)
        assert not (hi[0] > x0 and lo[0] < x1 and hi[1] > y0 and lo[1] < y1), fp.label
    plain = build_background(3)
    assert sum(o.label.startswith("clutter") for o in a.obstacles) > 0
    green = RAW_ID["vegetation"]
    assert (a.face_semantic == green).sum() > (plain.face_semantic == green).sum()
    bare = place_street(3, _place(green=0.0, unlabeled=0.0), (0.0, 0.0))
    assert not any(o.label.startswith(("clutter", "place hedge")) for o in bare.obstacles)


def test_a_place_with_edges_narrows_the_road_and_lets_cars_onto_the_roadside():
    place = _place(edges=(3.5, 5.5))
    street = place_street(3, place, (0.0, 0.0))
    assert road_half_width(place) == street.road_half_width == 4.5
    assert float(street.terrain.kerb(np.array([10.0]))[0]) == 4.5     # no wider test site
    assert not street.kerbs_stop_cars and place_street(3, _place(), (0.0, 0.0)).kerbs_stop_cars
    assert road_half_width(_place(edges=(0.5, 0.9))) == ROAD_HALF_M[0]
    # Nothing stands on the road at the test site; the roadside may stand right beside it.
    (x0, x1), _ = FREE_ZONE
    beside = 0
    for fp in street.obstacles:
        if fp.label.startswith("curb"):
            continue
        lo, hi = fp.polygon.min(axis=0), fp.polygon.max(axis=0)
        if hi[0] > x0 and lo[0] < x1:
            assert lo[1] >= 4.5 or hi[1] <= -4.5, fp.label
            beside += min(abs(lo[1]), abs(hi[1])) < 8.5
    assert beside > 0
    # A car beyond the kerb is a sample, as one inserted in a real scan is; as built, not.
    def sample(x: float) -> Sample:
        return Sample((("car_model", "sedan"), ("x", x), ("y", 12.0), ("yaw", 0.0),
                       ("count", 1), ("background", 0)))

    def sim_of(p: Place) -> Simulator:
        profile = _profile((p,))
        return Simulator(load_sensor("kitti-hdl64e-front"),
                         background_source=lambda b: profile.street(3))
    verge = [x for x in np.arange(4.0, 8.0, 0.5) if _valid(sim_of(place), sample(x))]
    assert verge, "no place across the right kerb (4.5 m) for a car"
    with pytest.raises(InvalidSample, match="curb"):
        sim_of(_place()).placed_cars(sample(-11.5))


def _valid(sim: Simulator, sample: Sample) -> bool:
    try:
        sim.placed_cars(sample)
    except InvalidSample:
        return False
    return True


def test_the_simulator_stands_the_ego_as_the_place_saw_its_road():
    profile = _profile((_place(pitch=2.0),))
    sim = Simulator(load_sensor("kitti-hdl64e-front"),
                    background_source=profile.background_source())
    plain = Simulator(load_sensor("kitti-hdl64e-front"))
    got, ref = sim.ego_pose(4), plain.ego_pose(4)
    assert got.pitch_deg - ref.pitch_deg == pytest.approx(2.0)
    assert got.z - ref.z == pytest.approx(1.8 - 1.73)
    assert profile.draw_pose(np.random.default_rng(0)) == (0.0, 0.0)   # the street carries it


def test_profile_with_places_round_trips_and_version_1_still_loads(tmp_path):
    profile = _profile((_place("a"), _place("b", pitch=-1.0)))
    path = tmp_path / "w.json"
    path.write_text(json.dumps(profile.to_json()))
    assert json.loads(path.read_text())["version"] == PROFILE_VERSION
    assert load_profile(str(path)) == profile
    v1 = {k: v for k, v in profile.to_json().items() if k != "places"} | {"version": 1}
    path1 = tmp_path / "v1.json"
    path1.write_text(json.dumps(v1))
    assert load_profile(str(path1)).places == ()


def _config(tmp_path: Path, background: str) -> Path:
    text = (ROOT / "configs" / "smoke.toml").read_text()
    head, _, _ = text.partition("[dims.background]")
    path = tmp_path / "c.toml"
    path.write_text(head + "[dims.background]\n" + background)
    return path


def test_space_world_key_builds_place_streets_and_names_bad_values(tmp_path):
    profile = _profile((_place("a"),))
    (tmp_path / "w.json").write_text(json.dumps(profile.to_json()))
    space = load_space(_config(tmp_path, 'values = [0, 1]\nworld = "w.json"\n'))
    assert space.world.endswith("w.json")
    assert space.background_source()(1).ego_pitch_deg == pytest.approx(1.5)
    plain = load_space(_config(tmp_path, "values = [0, 1]\n"))
    assert plain.world == "" and plain.background_source() is None
    (tmp_path / "w.json").write_text(json.dumps(replace(profile, name="other").to_json()))
    again = load_space(_config(tmp_path, 'values = [0, 1]\nworld = "w.json"\n'))
    assert again.config_hash != space.config_hash        # another profile: another space
    with pytest.raises(ConfigError, match=r"dims\.background\.world.*nope\.json: no such file"):
        load_space(_config(tmp_path, 'values = [0]\nworld = "nope.json"\n'))
    with pytest.raises(ConfigError, match=r"dims\.background\.world: 3 is not"):
        load_space(_config(tmp_path, "values = [0]\nworld = 3\n"))
    with pytest.raises(ConfigError, match=r"dims\.background\.world: builds our streets"):
        load_space(_config(tmp_path, 'real = ["x"]\nworld = "w.json"\n'))


def test_streets_are_named_for_their_places():
    space = load_space(ROOT / "configs" / "paper.toml")
    profile = load_profile(space.world)
    names = [space.background_name(b) for b in range(len(profile.places))]
    assert names[0] == f"street 0 ({profile.places[0].name})"
    assert sorted(n.split("(")[1].rstrip(")") for n in names) == sorted(
        p.name for p in profile.places)
    assert load_space(ROOT / "configs" / "smoke.toml").background_name(3) == "street 3"


def test_the_ego_stands_across_its_road_where_the_place_sensor_did():
    assert road_offset(_place(edges=(4.0, 4.0))) == 0.0 and road_offset(_place()) == 0.0
    assert road_offset(_place(edges=(2.5, 7.0))) == pytest.approx(2.25)   # kerbs 2.5 and 7.0
    assert road_offset(_place(edges=(0.5, 0.9))) == pytest.approx(0.2)    # widened evenly
    assert road_offset(_place(edges=(0.0, 30.0))) == pytest.approx(15.0 - 1.5)   # kept inside
    place = _place(edges=(2.5, 7.0))
    street = place_street(1, place, (0.0, 0.0))    # kept around the crown, a sign stood 2.9 m
    assert street.ego_dy == pytest.approx(2.25)    # from the ego
    for fp in street.obstacles:    # the sensor's clearance is around the ego, not the crown
        if not fp.label.startswith("curb"):
            lo, hi = fp.polygon.min(axis=0), fp.polygon.max(axis=0)
            gap = np.maximum(np.maximum(lo - [0.0, 2.25], [0.0, 2.25] - hi), 0.0)
            assert np.hypot(*gap) >= SENSOR_CLEARANCE, fp.label
    profile = _profile((place,))
    sim = Simulator(load_sensor("kitti-hdl64e-front"),
                    background_source=lambda b: profile.street(3))
    assert sim.ego_pose(0).y == pytest.approx(2.25)
    # The sample's positions are the sensor's: the car 12 m ahead on its line stands 2.25 m
    # left of the crown, and its points lie on the sensor's line.
    sample = Sample((("car_model", "sedan"), ("x", 0.0), ("y", 12.0), ("yaw", 0.0),
                     ("count", 1), ("background", 0)))
    (car,) = sim.placed_cars(sample)
    assert (car.x, car.y) == (12.0, pytest.approx(2.25))
    scan = sim.scan(sample)
    pts = scan.image[sim.placed_pixels(scan)]
    assert len(pts) > 100 and abs(float(np.median(pts[:, 1]))) < 0.3
