"""Drive traffic (`falsify dataset --traffic drive`): deterministic, lane-aligned, at driving
distances; the scattered default unchanged byte for byte."""

from __future__ import annotations

import hashlib
import math

import numpy as np
import pytest

from falsify.cli import main
from falsify.data.traffic import SAME_LANE_GAP, lanes_of
from falsify.data.training import TRAFFIC_KINDS, TrafficOptions, scene_for, write_dataset
from falsify.sensor.lidar import load_sensor
from falsify.sensor.placement import ego_outline, first_overlap
from falsify.sensor.simulator import Simulator
from tests.conftest import CONFIGS

# sha256 of the scattered scenes 0, 3, ..., 21 (seed 0): the default must not move unless the
# world does. Last moved by narrowing streets and training egos over a longer stretch of road.
SCATTERED_SCENES = "874d7f040f6846f3e32f1a0eb21e18f879df3c0f0a85299530cc07c14b27d7cd"
DRIVE = TrafficOptions(backgrounds=3, traffic="drive")
SCENES = 240


@pytest.fixture(scope="module")
def sim() -> Simulator:
    return Simulator(load_sensor("kitti-hdl64e-front"), max_bvh=3, max_hits=8)


@pytest.fixture(scope="module")
def drive_scenes(sim) -> list:
    # scene i uses background 1000 + (i // 8) % 3: keep each background's scenes together
    return [scene_for(i, 5, sim, DRIVE) for i in range(SCENES)]


def _heading_off(h: float, lane_dir: float) -> float:
    return abs(math.remainder(h - lane_dir, 360.0))


def test_scattered_default_unchanged(sim) -> None:
    h = hashlib.sha256()
    for i in range(0, 24, 3):
        h.update(repr(scene_for(i, 0, sim, TrafficOptions())).encode())
    assert h.hexdigest() == SCATTERED_SCENES


def test_drive_is_deterministic(sim, tmp_path) -> None:
    assert scene_for(17, 3, sim, DRIVE) == scene_for(17, 3, sim, DRIVE)
    assert scene_for(17, 3, sim, DRIVE) != scene_for(17, 4, sim, DRIVE)
    sensor = load_sensor("kitti-hdl64e-front", ray_drop=0.05, range_noise=0.02)
    for d in ("a", "b"):
        write_dataset(sensor, tmp_path / d, 2, seed=3, opts=DRIVE)
    for name in ("000000.npy", "000001.npy", "index.json"):
        assert (tmp_path / "a" / name).read_bytes() == (tmp_path / "b" / name).read_bytes()
    assert b'"traffic": "drive"' in (tmp_path / "a" / "index.json").read_bytes()


def test_drive_distribution(sim, drive_scenes) -> None:
    """Headings near lane directions, cars near lane centres or kerbs, gaps at driving
    distances, few cars close beside the ego; the scattered placement is far less regular."""
    egos, cars, same_lane_gaps, close = [], [], [], 0
    for bg_id, pose, placed in drive_scenes:
        lanes = lanes_of(sim.background(bg_id)[1].road_half_width)
        centres = np.array(lanes.centres)
        k = int(np.argmin(np.abs(centres - pose.y)))
        egos.append((abs(pose.y - centres[k]),
                     _heading_off(pose.heading_deg, 0.0 if lanes.directions[k] > 0 else 180.0)))
        fwd = np.array([math.cos(math.radians(pose.heading_deg)),
                        math.sin(math.radians(pose.heading_deg))])
        for c in placed:
            rel = np.array([c.x - pose.x, c.y - pose.y])
            along, across = float(rel @ fwd), float(rel @ [-fwd[1], fwd[0]])
            if abs(along) < 6.0 and abs(across) < 2.5:
                close += 1
            lane = int(np.argmin(np.abs(centres - c.y)))
            lane_dir = 0.0 if lanes.directions[lane] > 0 else 180.0
            # parked cars line the kerbs, facing either way
            kerb = lanes.half_width - abs(c.y) < 2.0
            off = min(_heading_off(c.heading_deg, 0.0), _heading_off(c.heading_deg, 180.0)) \
                if kerb else _heading_off(c.heading_deg, lane_dir)
            cars.append((off, kerb, abs(c.y - centres[lane])))
            if lane == k and abs(c.y - centres[k]) < 0.5 and not kerb and along > 0:
                same_lane_gaps.append(along)
    egos_a, cars_a = np.array(egos), np.array(cars, dtype=float)
    assert len(cars_a) > 500
    assert (egos_a[:, 0] < 0.5).mean() > 0.95 and (egos_a[:, 1] < 4.0).mean() > 0.95
    assert (cars_a[:, 0] < 8.0).mean() > 0.93            # headings along the lanes
    in_lane = (cars_a[:, 1] == 1) | (cars_a[:, 2] < 0.75)
    assert in_lane.mean() > 0.9                          # in a lane or at a kerb
    assert 0.1 < cars_a[:, 1].mean() < 0.4               # some parked
    gaps = np.array(same_lane_gaps)
    assert len(gaps) > 30 and (gaps >= SAME_LANE_GAP[0] - 0.5).mean() > 0.9
    assert np.median(gaps) > 20.0                        # driving distances, not bumpers
    assert close / len(cars_a) < 0.03                    # rarely close beside the ego
    # the scattered placement of the same streets turns cars every which way
    scattered = TrafficOptions(backgrounds=3)
    offs = [min(_heading_off(c.heading_deg, 0.0), _heading_off(c.heading_deg, 180.0))
            for i in range(0, SCENES, 4) for c in scene_for(i, 5, sim, scattered)[2]]
    assert (np.array(offs) > 8.0).mean() > 0.15


def test_cli_traffic_choice(tmp_path, capsys) -> None:
    out = tmp_path / "d"
    with pytest.raises(SystemExit) as exc:
        main(["dataset", str(CONFIGS / "ci.toml"), "--scans", "1", "--out", str(out),
              "--traffic", "jam"])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "--traffic" in err and "drive" in err and "scattered" in err
    assert not out.exists()


@pytest.mark.slow
def test_ego_and_cars_stand_on_the_terrain(sim) -> None:
    """Every traffic kind stands the ego and its cars on the street's terrain: a drive ego once
    stayed at z = 0, a metre under the road on hills, and saw the road as a wall at its bumper.
    (Both kinds on each street in turn, so a street is built once.)"""
    raised = dict.fromkeys(TRAFFIC_KINDS, 0)
    for i in range(0, 24 * 8, 8):   # one scene on each of streets 1000-1023
        for traffic in TRAFFIC_KINDS:
            bg_id, pose, placed = scene_for(i, 0, sim, TrafficOptions(backgrounds=24,
                                                                      traffic=traffic))
            assert pose == sim.ego_pose(bg_id, pose), traffic
            assert all(c == sim.settle(bg_id, c) for c in placed), traffic
            raised[traffic] += abs(pose.z) > 0.3
    assert min(raised.values()) >= 2   # the streets have hills, so the check above can fail


@pytest.mark.slow
def test_the_ego_never_stands_in_a_background_obstacle(sim) -> None:
    """Drive scenes 1 and 67 (seed 0) once put the ego inside a parked bus of streets 1000 and
    1008; the ego pose is now drawn again until it is free (scenes that were free stay equal)."""
    for i in (1, 67, *range(0, 400, 23)):
        for traffic in TRAFFIC_KINDS:
            bg_id, pose, _ = scene_for(i, 0, sim, TrafficOptions(traffic=traffic))
            assert first_overlap(ego_outline(pose), sim.obstacles(bg_id)) is None, (i, traffic)
