"""A user's own LiDAR, written as a sensor TOML: its rays are the configured angles (a published
beam table, a uniform fan, a field of view off forward), a raised or pitched mount moves the
road's returns as geometry says, range limits drop points, bad files exit 2 before anything is
written, and grid, report and a network of its H x W run on it."""

from __future__ import annotations

import math
import sqlite3
import textwrap
from pathlib import Path

import numpy as np
import pytest

from falsify.cli import main
from falsify.errors import ConfigError
from falsify.rotations import rot_y
from falsify.sensor.lidar import MAX_RAYS, MAX_ROWS, load_sensor, parse_sensor
from falsify.sensor.simulator import Simulator
from falsify.world.streets import Background

ROOT = Path(__file__).resolve().parents[2]

# Velodyne VLP-32C vertical angles by laser id 0..31 (VLP-32C User Manual, Velodyne Lidar
# 63-9325 Rev. B, table "VLP-32C Laser Firing Order and Vertical Angles"; the same table as
# the vert_correction of Velodyne's ROS driver calibration VeloView-VLP-32C.yaml): firing
# order, not sorted, spaced unevenly (0.333 deg near the horizon, 8 deg at the bottom).
VLP32C_BY_LASER_ID = [
    -25.0, -1.0, -1.667, -15.639, -11.31, 0.0, -0.667, -8.843,
    -7.254, 0.333, -0.333, -6.148, -5.333, 1.333, 0.667, -4.0,
    -4.667, 1.667, 1.0, -3.667, -3.333, 3.333, 2.333, -2.667,
    -3.0, 7.0, 4.667, -2.333, -2.0, 15.0, 10.333, -1.333,
]
VLP32C_TOP_DOWN = sorted(VLP32C_BY_LASER_ID, reverse=True)


def write_sensor(tmp_path: Path, text: str, name: str = "mine.toml") -> Path:
    path = tmp_path / name
    path.write_text(textwrap.dedent(text))
    return path


def mesh_background(vertices: np.ndarray, faces: np.ndarray) -> Background:
    """A bare background of one mesh (class 0, no obstacles, no terrain)."""
    n = len(faces)
    return Background(0, np.asarray(vertices, np.float64), np.asarray(faces, np.int32),
                      np.zeros(n, np.uint8), np.zeros(n, np.int32), (), 3.5)


def sphere(radius: float, centre: tuple[float, float, float], n: int = 360) -> Background:
    """A UV sphere around the sensor: every ray meets it at about `radius`."""
    th, ph = np.meshgrid(np.linspace(0.0, np.pi, n // 2 + 1), np.linspace(0.0, 2 * np.pi, n + 1),
                         indexing="ij")
    v = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], -1)
    v = v.reshape(-1, 3) * radius + centre
    idx = np.arange(len(v)).reshape(th.shape)
    a, b, c, d = idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]
    f = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3),
                        np.stack([a, c, d], -1).reshape(-1, 3)])
    return mesh_background(v, f)


def flat_ground(size: float = 4000.0) -> Background:
    h = size / 2
    v = np.array([[-h, -h, 0.0], [h, -h, 0.0], [h, h, 0.0], [-h, h, 0.0]])
    return mesh_background(v, np.array([[0, 1, 2], [0, 2, 3]]))


def cast_on(sensor, background: Background) -> np.ndarray:
    return Simulator(sensor, background_source=lambda _id: background).render(0, []).image


def angles_of(image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each pixel's point's elevation and azimuth in the sensor frame, degrees."""
    x, y, z = image[..., 0], image[..., 1], image[..., 2]
    return np.degrees(np.arctan2(z, np.hypot(x, y))), np.degrees(np.arctan2(y, x))


def az_diff(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.abs((a - b + 180.0) % 360.0 - 180.0)


# -- the rays are the configured angles --------------------------------------------------------
@pytest.mark.parametrize(("text", "rows", "columns", "elevations", "az_edges"), [
    # Velodyne VLP-32C: its published table, sorted top down; 0.2 deg at 10 Hz
    (f"elevations_deg = {VLP32C_TOP_DOWN}\nh_fov_deg = [180.0, -180.0]\ncolumns = 1800\n"
     "mount_height = 1.9\n", 32, 1800, VLP32C_TOP_DOWN, (180.0, -180.0)),
    # Ouster OS1-128: 128 beams evenly over +-22.5 deg, 2048 columns
    ("vertical = { up_deg = 22.5, down_deg = -22.5, beams = 128 }\n"
     "h_fov_deg = [180.0, -180.0]\ncolumns = 2048\nmount_height = 2.0\n", 128, 2048,
     list(np.linspace(22.5, -22.5, 128)), (180.0, -180.0)),
    # a solid-state sensor looking left of forward: 120 x 25 deg, off-centre
    ("vertical = { up_deg = 12.5, down_deg = -12.5, beams = 40 }\n"
     "h_fov_deg = [150.0, 30.0]\ncolumns = 240\n", 40, 240, list(np.linspace(12.5, -12.5, 40)),
     (150.0, 30.0)),
], ids=["vlp32c-table", "os1-128x2048", "solid-state-left"])
def test_each_ray_returns_at_its_configured_elevation_and_azimuth(
        tmp_path, text, rows, columns, elevations, az_edges):
    """Cast onto a sphere around the sensor, every pixel holds a point whose elevation is its
    row's (row 0 the top beam) and whose azimuth is its column's centre, left edge first."""
    sensor = load_sensor(write_sensor(tmp_path, text))
    assert sensor.shape == (rows, columns)
    image = cast_on(sensor, sphere(60.0, (0.0, 0.0, sensor.mount_height)))
    assert image.shape == (rows, columns, 6)
    assert (image[..., 4] > 0).all()
    el, az = angles_of(image)
    np.testing.assert_allclose(el, np.repeat(np.array(elevations)[:, None], columns, 1),
                               atol=1e-4)
    left, right = az_edges
    step = (left - right) / columns
    want_az = left - (np.arange(columns) + 0.5) * step
    assert az_diff(az, want_az[None, :]).max() < 1e-4
    assert el[0, 0] == pytest.approx(max(elevations), abs=1e-4)   # top row first


def test_the_vlp32c_table_in_laser_id_order_is_refused_with_how_to_fix_it(tmp_path, capsys):
    """A datasheet lists lasers in firing order: the error names the first pair out of order
    and says to sort by elevation, rather than only that the list must decrease."""
    with pytest.raises(ConfigError, match=r"elevations_deg: row 1 \(-1\) is not below row 0 "
                                          r"\(-25\).*sort a datasheet's laser-id table"):
        parse_sensor({"elevations_deg": VLP32C_BY_LASER_ID, "h_fov_deg": [180.0, -180.0],
                      "columns": 1800})
    with pytest.raises(ConfigError, match=r"row 2 \(1\) is not below row 1 \(1\).*no repeats"):
        parse_sensor({"elevations_deg": [2.0, 1.0, 1.0, -3.0], "h_fov_deg": [45.0, -45.0],
                      "columns": 8})


# -- the mount: height and pitch move the road's returns --------------------------------------
@pytest.mark.parametrize(("height", "pitch"), [(1.73, 0.0), (2.0, 0.0), (2.0, 5.0), (1.2, -3.0)])
def test_a_raised_or_pitched_mount_meets_flat_ground_where_geometry_says(tmp_path, height, pitch):
    """A ray at sensor elevation e and azimuth a, pitched down by p, falls at world slope
    -sin(p) cos(e) cos(a) + cos(p) sin(e); it meets ground h below at range h / -slope (straight
    ahead: h / sin(p - e)), and its point, turned back to the world, lies at z = -h."""
    sensor = load_sensor(write_sensor(tmp_path, f"""\
        vertical = {{ up_deg = 12.5, down_deg = -12.5, beams = 50 }}
        h_fov_deg = [60.0, -60.0]
        columns = 240
        mount_height = {height}
        pitch_deg = {pitch}
        max_range = 150.0
        """))
    image = cast_on(sensor, flat_ground())
    el = np.radians(np.asarray(sensor.elevations_deg))[:, None]
    az = np.radians(sensor.azimuths_deg)[None, :]
    p = math.radians(pitch)
    slope = -math.sin(p) * np.cos(el) * np.cos(az) + math.cos(p) * np.sin(el)
    with np.errstate(divide="ignore"):
        want = np.where(slope < 0, height / -slope, 0.0)
    want[want > sensor.max_range] = 0.0
    far_edge = np.abs(want - sensor.max_range) < 1e-3   # float32 may fall either side
    r = image[..., 4]
    assert (r > 0).sum() > 1000
    np.testing.assert_allclose(r[~far_edge], want[~far_edge], rtol=1e-5, atol=1e-4)
    hit = r > 0
    world = image[..., :3][hit] @ rot_y(pitch).T
    np.testing.assert_allclose(world[:, 2], -height, atol=1e-3)
    # straight ahead (the column nearest azimuth 0), the lowest row lands at h / tan(p - e)
    c = int(np.argmin(np.abs(sensor.azimuths_deg)))
    e0 = math.radians(sensor.elevations_deg[-1])
    ahead = image[sensor.rows - 1, c, :3] @ rot_y(pitch).T
    assert math.hypot(ahead[0], ahead[1]) == pytest.approx(height / math.tan(p - e0), rel=1e-4)


# -- range limits ------------------------------------------------------------------------------
@pytest.mark.parametrize(("limits", "kept"), [
    ("min_range = 0.5\nmax_range = 29.0", False),     # the sphere beyond max_range
    ("min_range = 31.0\nmax_range = 120.0", False),   # the sphere within min_range
    ("min_range = 29.0\nmax_range = 31.0", True),
], ids=["beyond-max", "within-min", "between"])
def test_points_beyond_max_range_or_within_min_range_are_dropped(tmp_path, limits, kept):
    sensor = load_sensor(write_sensor(tmp_path, f"""\
        elevations_deg = [10.0, 0.0, -7.5, -20.0]
        h_fov_deg = [180.0, -180.0]
        columns = 90
        {limits}
        """.replace("        {limits}", limits)))
    image = cast_on(sensor, sphere(30.0, (0.0, 0.0, sensor.mount_height)))
    if kept:
        np.testing.assert_allclose(image[..., 4], 30.0, atol=0.05)
    else:
        assert not image.any()


# -- bad sensor files: exit 2, one line naming the key and what is allowed, nothing written ---
GOOD = {
    "elevations_deg": "elevations_deg = [2.0, 0.0, -2.0, -10.0]",
    "h_fov_deg": "h_fov_deg = [45.0, -45.0]",
    "columns": "columns = 64",
}


@pytest.mark.parametrize(("change", "message"), [
    ({"elevations_deg": "vertical = { up_deg = 2.0, down_deg = -24.0, beams = 0 }"},
     "vertical.beams: 0 must be an integer in 1..2048"),
    ({"elevations_deg": "elevations_deg = [-2.0, 0.0, 2.0]"}, "row 1 (0) is not below row 0"),
    ({"elevations_deg": "elevations_deg = [2.0, 0.0, 0.0]"}, "row 2 (0) is not below row 1"),
    ({"elevations_deg": "elevations_deg = [2.0, nan, -2.0]"},
     "elevations_deg: row 1 is nan; allowed: finite numbers"),
    ({"elevations_deg": "elevations_deg = []"}, "elevations_deg: expected a non-empty list"),
    ({"columns": "columns = 0"}, "columns: 0 must be an integer in 1..16384"),
    ({"h_fov_deg": "h_fov_deg = [10.0, 10.0]"}, "h_fov_deg: left 10 minus right 10 must be in"),
    ({"h_fov_deg": "h_fov_deg = [nan, -45.0]"}, "h_fov_deg: expected [left_deg, right_deg]"),
    ({"h_fov_deg": "h_fov_deg = [true, -45.0]"}, "h_fov_deg: expected [left_deg, right_deg]"),
    ({"elevations_deg": "vertical = { up_deg = 2.0, down_deg = 2.0, beams = 8 }"},
     "vertical: up_deg 2.0, down_deg 2.0; allowed: finite numbers of degrees, up_deg above"),
    ({"elevations_deg": "vertical = { up_deg = true, down_deg = -2.0, beams = 8 }"},
     "vertical: up_deg True, down_deg -2.0; allowed: finite numbers"),
    ({"mount": "mount_height = -0.5"}, "mount_height: -0.5 must be >= 0.0"),
    ({"mount": "mount_height = nan"}, "mount_height: expected a finite number, got nan"),
    ({"mount": "pitch_deg = 60.0"}, "pitch_deg: 60.0 must be <= 45.0"),
])
def test_a_bad_sensor_file_exits_2_naming_the_key_before_anything_is_written(
        tmp_path, capsys, change, message):
    sensor = write_sensor(tmp_path, "\n".join({**GOOD, **change}.values()) + "\n")
    config = tmp_path / "space.toml"
    config.write_text((ROOT / "configs" / "smoke.toml").read_text().replace(
        '"kitti-hdl64e-front"', f'"{sensor}"'))
    out = tmp_path / "out"
    assert main(["scan", str(config), "--out", str(out), "--set", "x=2", "--set", "y=8"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and str(sensor) in err and message in err, err
    assert not out.exists()


@pytest.mark.parametrize(("raw", "message"), [
    ({"vertical": {"up_deg": 2.0, "down_deg": -24.0, "beams": MAX_ROWS + 1}, "columns": 8},
     f"vertical.beams: {MAX_ROWS + 1} must be an integer in 1..{MAX_ROWS}"),
    ({"elevations_deg": list(np.linspace(10.0, -10.0, MAX_ROWS + 1)), "columns": 8},
     f"elevations_deg: {MAX_ROWS + 1} rows; allowed: 1..{MAX_ROWS}"),
    ({"vertical": {"up_deg": 2.0, "down_deg": -24.0, "beams": 2048}, "columns": 4096},
     f"2048 rows x 4096 columns = 8,388,608 rays a scan; allowed: at most {MAX_RAYS:,}"),
])
def test_a_grid_too_large_to_cast_is_refused_where_the_file_is_read(raw, message):
    """beams = 100000000 allocated hundreds of GB and died with a MemoryError traceback."""
    with pytest.raises(ConfigError, match=message.replace("(", r"\(").replace(")", r"\)")):
        parse_sensor({"h_fov_deg": [180.0, -180.0], **raw})
    assert parse_sensor({"h_fov_deg": [180.0, -180.0], "columns": 2048, "vertical": {
        "up_deg": 2.0, "down_deg": -24.0, "beams": 2048}}).shape == (2048, 2048)


# -- the commands on it ------------------------------------------------------------------------
PLUGIN = '''
import numpy as np


class Net:
    """Car where a return stands above the road within 20 m: a rule, not a network."""

    spec = {"name": "rule-32x360", "input_kind": "range", "height": 32, "width": 360,
            "output_kind": "logits", "num_classes": 2, "classes": {"unknown": 0, "car": 1}}

    def predict(self, batch):
        return [((b[..., 2] > -1.4) & (b[..., 4] > 0) & (b[..., 4] < 20)).astype(np.int64)
                for b in batch]


def make():
    return Net()
'''


def test_grid_scan_and_report_run_on_an_own_sensor_with_a_network_of_its_size(tmp_path,
                                                                               capsys):
    """A VLP-32C at 1 deg on a roof rack: the bundled 64 x 512 network is refused before the run
    folder exists; a range plug-in of 32 x 360 runs the grid, the report names the sensor, and
    a scan repeats byte for byte."""
    sensor = write_sensor(tmp_path, f"""\
        name = "vlp32c-roof"
        elevations_deg = {VLP32C_TOP_DOWN}
        h_fov_deg = [180.0, -180.0]
        columns = 360
        mount_height = 2.0
        """)
    config = tmp_path / "space.toml"
    config.write_text((ROOT / "configs" / "smoke.toml").read_text().replace(
        '"kitti-hdl64e-front"', f'"{sensor.name}"'))
    plugin = tmp_path / "rule.py"
    plugin.write_text(PLUGIN)

    refused = tmp_path / "refused"
    assert main(["grid", str(config), "--out", str(refused), "--quiet"]) == 2
    assert "takes 64×512 range images but sensor vlp32c-roof makes 32×360" in (
        capsys.readouterr().err)
    assert not refused.exists()

    run = tmp_path / "run"
    assert main(["grid", str(config), "--out", str(run), "--model", f"{plugin}:make",
                 "--quiet"]) == 0
    with sqlite3.connect(run / "results.sqlite") as db:
        assert db.execute("SELECT COUNT(*) FROM samples").fetchone()[0] == 8
    page = (run / "report.html").read_text()
    assert "Sensor</dt><dd>vlp32c-roof" in page

    scans = []
    for k in range(2):
        out = tmp_path / f"scan{k}"
        assert main(["scan", str(config), "--out", str(out), "--set", "x=2", "--set",
                     "y=8"]) == 0
        scans.append([(out / f"scan.{e}").read_bytes() for e in ("npy", "bin", "label")])
        assert np.load(out / "scan.npy").shape == (32, 360, 6)
    assert scans[0] == scans[1]
