"""The `semantickitti-hdl64e` preset: RangeNet++'s spherical range image (Milioto et al., IROS
2019) checked against the definition written out point by point, on random points, a real
SemanticKITTI scan (skipped without ../shared/data) and simulated scans."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from falsify.data.velodyne import read_bin, read_kitti
from falsify.errors import ConfigError
from falsify.semantic import RAW_NAMES, kitti4
from falsify.sensor.lidar import load_sensor, parse_sensor
from falsify.sensor.scan import image_from_points, project_scan
from falsify.sensor.simulator import Simulator
from falsify.world.space import load_space
from tests.conftest import CONFIGS, KITTI_DIR

H, W, FOV_UP, FOV_DOWN = 64, 2048, 3.0, -25.0
# a fit sequence: the evaluation split (00, 03, 06, 08) is only reported on
SEQ = KITTI_DIR / "semantickitti-mini" / "sequences" / "05"


def reference(points: np.ndarray, h: int = H, w: int = W, fov_up_deg: float = FOV_UP,
              fov_down_deg: float = FOV_DOWN) -> tuple[list, dict]:
    """RangeNet++'s projection, one point at a time: each point's clamped (row, col) and which
    point each pixel holds (written far to near, so the nearest wins)."""
    fov_up, fov_down = fov_up_deg / 180.0 * math.pi, fov_down_deg / 180.0 * math.pi
    fov = abs(fov_down) + abs(fov_up)
    pix, depths = [], []
    for x, y, z in points.tolist():
        depth = math.sqrt(x * x + y * y + z * z)
        yaw = -math.atan2(y, x)
        pitch = math.asin(z / depth)
        px = math.floor(0.5 * (yaw / math.pi + 1.0) * w)
        py = math.floor((1.0 - (pitch + abs(fov_down)) / fov) * h)
        pix.append((min(max(py, 0), h - 1), min(max(px, 0), w - 1)))
        depths.append(depth)
    holder = {}
    for i in sorted(range(len(points)), key=lambda i: -depths[i]):
        holder[pix[i]] = i
    return pix, holder


def assert_image_holds(image: np.ndarray, points: np.ndarray, remission: np.ndarray,
                       holder: dict) -> None:
    """The image holds exactly the reference's pixels, each with its winning point."""
    assert image.shape == (H, W, 6)
    filled = set(zip(*np.nonzero(image[..., 4] > 0), strict=True))
    assert filled == set(holder)
    rc = np.array(list(holder))
    idx = np.array(list(holder.values()))
    np.testing.assert_array_equal(image[rc[:, 0], rc[:, 1], 0:3], points[idx].astype(np.float32))
    np.testing.assert_array_equal(image[rc[:, 0], rc[:, 1], 3], remission[idx].astype(np.float32))


@pytest.fixture(scope="module")
def sensor():
    return load_sensor("semantickitti-hdl64e")


def test_preset_is_the_hdl64e_rays_in_rangenet_layout(sensor):
    rays = load_sensor("kitti-hdl64e-360")
    assert sensor.projection == "spherical" and rays.projection == "rings"
    assert sensor.shape == (H, W) and (sensor.fov_up_deg, sensor.fov_down_deg) == (3.0, -25.0)
    # the 360 preset's lasers, each cast from its own origin (fit_rings on the object frames)
    assert len(sensor.ring_offsets_m) == sensor.rows and sensor.mount_height == 1.68
    assert replace(sensor, name=rays.name, description=rays.description, kitti_rings=True,
                   projection="rings", elevations_deg=rays.elevations_deg,
                   ring_offsets_m=rays.ring_offsets_m, mount_height=rays.mount_height) == rays
    assert not sensor.kitti_rings


def test_pixel_of_matches_the_definition_on_random_points(sensor):
    rng = np.random.default_rng(7)
    n = 20000
    az = rng.uniform(-math.pi, math.pi, n)
    el = np.radians(rng.uniform(-40.0, 15.0, n))   # beyond the fov both ways: clamped
    d = rng.uniform(0.5, 100.0, n)
    pts = np.stack([d * np.cos(el) * np.cos(az), d * np.cos(el) * np.sin(az), d * np.sin(el)], 1)
    row, col, inside = sensor.pixel_of(pts, rows=np.zeros(n, np.int64))   # rows ignored
    pix, holder = reference(pts)
    assert inside.all()
    assert list(zip(row.tolist(), col.tolist(), strict=True)) == pix
    remission = rng.random(n)
    scan = image_from_points(sensor, pts, np.ones(n, np.uint8), np.arange(n, dtype=np.int32),
                             intensity=remission)
    assert_image_holds(scan.image, pts, remission, holder)
    assert len(holder) < n   # some points lost their pixel to nearer ones


def test_orientation_row_0_is_fov_up_and_column_w_half_is_straight_ahead(sensor):
    step = (FOV_UP - FOV_DOWN) / H
    pitches = [FOV_UP - (k + 0.5) * step for k in (0, 1, 31, 62, 63)] + [10.0, -40.0]
    pts = [[20 * math.cos(math.radians(p)), 0.0, 20 * math.sin(math.radians(p))] for p in pitches]
    pts += [[0.0, 10.0, 0.0], [0.0, -10.0, 0.0], [-10.0, 1e-6, 0.0], [-10.0, -1e-6, 0.0]]
    row, col, inside = sensor.pixel_of(np.array(pts))
    assert row[:7].tolist() == [0, 1, 31, 62, 63, 0, 63]   # above fov_up / below fov_down clamp
    assert col[:7].tolist() == [W // 2] * 7                # +x (straight ahead): column W/2
    assert col[7:].tolist() == [W // 4, 3 * W // 4, 0, W - 1]   # left, right, behind either side
    assert inside.all()
    assert not sensor.pixel_of(np.zeros((1, 3)))[2][0]     # the origin has no direction


def test_real_scan_is_rangenet_projection(sensor):
    bin_path = SEQ / "velodyne" / "000000.bin"
    if not bin_path.is_file():
        pytest.skip(f"SemanticKITTI mini scans not found in {SEQ / 'velodyne'}")
    pts = read_bin(bin_path).astype(np.float64)
    scan = read_kitti(bin_path, SEQ / "labels" / "000000.label", sensor)
    _, holder = reference(pts[:, :3])
    assert_image_holds(scan.image, pts[:, :3], pts[:, 3], holder)
    assert scan.valid.sum() > 0.6 * H * W
    label = np.fromfile(SEQ / "labels" / "000000.label", np.uint32)
    rc = np.array(list(holder))
    idx = np.array(list(holder.values()))
    np.testing.assert_array_equal(scan.instance[rc[:, 0], rc[:, 1]], label[idx] >> 16)


def spherical_space(tmp_path: Path):
    text = (CONFIGS / "smoke.toml").read_text()
    config = tmp_path / "space.toml"
    config.write_text(text.replace('sensor = "kitti-hdl64e-front"',
                                   'sensor = "semantickitti-hdl64e"'))
    return load_space(config), config


def test_simulated_scan_is_the_ray_grid_projected(tmp_path, sensor):
    space, _ = spherical_space(tmp_path)
    assert space.sensor == "semantickitti-hdl64e"
    sample = space.make({"x": 2.0, "y": 8.0, "background": 1})
    scan = Simulator(sensor).scan(sample, rng=np.random.default_rng(3))
    again = Simulator(sensor).scan(sample, rng=np.random.default_rng(3))
    assert scan.image.shape == (H, W, 6) and scan.image.dtype == np.float32
    assert scan.image.tobytes() == again.image.tobytes()
    assert scan.instance.tobytes() == again.instance.tobytes()
    # The same rays stored in the ring layout: the points before projection.
    grid = Simulator(replace(sensor, projection="rings")).scan(sample,
                                                               rng=np.random.default_rng(3))
    assert project_scan(sensor, grid).image.tobytes() == scan.image.tobytes()
    assert scan.count(1) > 0
    before = grid.points   # x, y, z, intensity, range, class, instance
    after = scan.points
    key = [0, 1, 2, 3, 5, 6]
    kept = {tuple(p) for p in after[:, key].tolist()}
    assert kept <= {tuple(p) for p in before[:, key].tolist()}
    # Every ray point missing from the image lost its pixel to a point no farther away.
    row, col, _ = sensor.pixel_of(before[:, :3].astype(np.float64))
    lost = np.array([tuple(p) not in kept for p in before[:, key].tolist()])
    assert len(after) == len(set(zip(row.tolist(), col.tolist(), strict=True)))
    assert lost.sum() == len(before) - len(after) > 0
    holder_range = scan.image[row[lost], col[lost], 4]
    assert (holder_range > 0).all()
    assert (holder_range <= np.linalg.norm(before[lost, :3].astype(np.float64), axis=1)
            + 1e-4).all()


def test_ring_presets_keep_their_scans(tmp_path):
    sensor = load_sensor("kitti-hdl64e-front")
    scan = Simulator(sensor).render(0, [], rng=np.random.default_rng(0))
    assert project_scan(sensor, scan) is scan


def test_falsify_scan_runs_on_the_preset(tmp_path, capsys):
    import json

    from falsify.cli import main

    _, config = spherical_space(tmp_path)
    out = tmp_path / "s"
    assert main(["scan", str(config), "--out", str(out), "--set", "x=2", "--set",
                 "background=1", "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    img = np.load(out / "scan.npy")
    assert summary["sensor"] == "semantickitti-hdl64e" and summary["shape"] == [H, W, 6]
    assert img.shape == (H, W, 6) and summary["points"] == int((img[..., 4] > 0).sum())
    assert (out / "scan.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # SemanticKITTI's own per-point files, read as its tools read them (np.fromfile)
    pts = np.fromfile(out / "scan.bin", np.float32).reshape(-1, 4)
    lab = np.fromfile(out / "scan.label", np.uint32)
    assert len(pts) == len(lab) == summary["points"]
    valid = img[..., 4] > 0
    np.testing.assert_array_equal(pts[:, :3], img[valid][:, :3])
    sem = lab & 0xFFFF
    assert set(np.unique(sem).tolist()) <= set(RAW_NAMES)
    np.testing.assert_array_equal(kitti4(sem), img[valid][:, 5].astype(np.uint8))
    assert (sem == 10).sum() == summary["car_points"] > 0


BASE = {"elevations_deg": [2.0, 0.0, -2.0], "h_fov_deg": [180.0, -180.0], "columns": 8}
SPH = {**BASE, "projection": "spherical", "fov_up_deg": 3.0, "fov_down_deg": -25.0}


@pytest.mark.parametrize(("raw", "message"), [
    ({**BASE, "projection": "cylindrical"}, "projection: 'cylindrical' is not allowed; "
                                            "allowed: 'rings', 'spherical'"),
    ({**BASE, "fov_up_deg": 3.0}, "fov_up_deg: only for projection = \"spherical\""),
    ({**SPH, "fov_up_deg": -1.0}, "fov_up_deg: -1.0 is not allowed"),
    ({**SPH, "fov_up_deg": 90}, "allowed: a number of degrees in [0, 90)"),
    ({**SPH, "fov_down_deg": 5.0}, "fov_down_deg: 5.0 is not allowed"),
    ({**SPH, "fov_down_deg": "low"}, "allowed: a number of degrees in (-90, 0]"),
    ({**SPH, "fov_up_deg": 0, "fov_down_deg": 0}, "fov_up_deg above fov_down_deg"),
    ({k: v for k, v in SPH.items() if k != "fov_down_deg"}, "missing key 'fov_down_deg'"),
    ({**SPH, "h_fov_deg": [45.0, -45.0]}, "h_fov_deg: projection = \"spherical\" spans 360"),
    ({**SPH, "kitti_rings": True}, "kitti_rings: must be false"),
])
def test_bad_projection_values_name_the_key(raw, message):
    with pytest.raises(ConfigError) as err:
        parse_sensor(raw)
    assert message in str(err.value)


def test_projection_parses_and_defaults_to_rings():
    assert parse_sensor(BASE).projection == "rings"
    assert parse_sensor({**BASE, "projection": "rings"}) == parse_sensor(BASE)
    s = parse_sensor({**SPH, "fov_up_deg": 2, "fov_down_deg": -24.5})
    assert (s.projection, s.fov_up_deg, s.fov_down_deg) == ("spherical", 2.0, -24.5)
