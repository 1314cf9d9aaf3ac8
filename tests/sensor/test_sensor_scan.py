"""Sensor presets against the real KITTI layout, and the scan file formats (ours and KITTI's)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from falsify.data.range_npy import load_scan_npy
from falsify.data.velodyne import KITTI_RINGS, kitti_rows, read_kitti, write_kitti
from falsify.errors import ConfigError, FalsifyError
from falsify.sensor.lidar import load_sensor, parse_sensor, preset_names
from falsify.sensor.scanner import PlacedCar
from falsify.sensor.simulator import Simulator


def test_presets_load():
    assert {"kitti-hdl64e-front", "kitti-hdl64e-360", "vlp16", "os1-64"} <= set(preset_names())
    assert load_sensor("kitti-hdl64e-front").shape == (64, 512)
    assert load_sensor("kitti-hdl64e-360").shape == (64, 2048)
    assert load_sensor("vlp16").shape == (16, 1800)
    assert load_sensor("os1-64").shape == (64, 1024)


def test_kitti_preset_reproduces_the_real_pixel_layout(kitti_dir):
    """Project the real scans' points with our preset: they land in their own pixels."""
    sensor = load_sensor("kitti-hdl64e-front")
    rows_ok = cols_ok = total = 0
    for path in sorted((kitti_dir / "squeezeseg").glob("*.npy")):
        img = load_scan_npy(path)
        valid = img[..., 4] > 0
        rr, cc = np.nonzero(valid)
        row, col, inside = sensor.pixel_of(img[valid][:, :3])
        total += len(rr)
        cols_ok += int((col == cc).sum())
        rows_ok += int((np.abs(row - rr) <= 1).sum())
    assert cols_ok / total > 0.999
    assert rows_ok / total > 0.97  # real rings wander by a fraction of a degree


def test_real_and_synthetic_scans_share_one_layout(kitti_dir):
    real = load_scan_npy(sorted((kitti_dir / "squeezeseg").glob("*.npy"))[0])
    sim = Simulator(load_sensor("kitti-hdl64e-front"))
    ours = sim.render(0, [PlacedCar("sedan", 10.0, 0.0, 0.0, 1)]).image
    for img in (real, ours):
        assert img.shape == (64, 512, 6) and img.dtype == np.float32
        valid = img[..., 4] > 0
        assert (img[~valid] == 0).all()  # empty pixels are zero in all channels
        np.testing.assert_allclose(np.linalg.norm(img[valid][:, :3], axis=1), img[valid][:, 4],
                                   rtol=1e-3, atol=2e-3)
        el = np.degrees(np.arcsin(img[..., 2][valid] / img[..., 4][valid]))
        rows = np.nonzero(valid)[0]
        # Row 0 looks up about 2 degrees, row 63 down about 24: same in both.
        assert np.median(el[rows == 63]) == pytest.approx(-23.6, abs=0.6)
        assert set(np.unique(img[..., 5][valid])) <= {0.0, 1.0, 2.0, 3.0}


def test_semantickitti_scans_project_into_our_layout(kitti_dir):
    sensor = load_sensor("kitti-hdl64e-front")
    for name in ("000000", "000001", "000002"):
        base = kitti_dir / "semantickitti" / name
        scan = read_kitti(base.with_suffix(".bin"), base.with_suffix(".label"), sensor)
        assert scan.image.shape == (64, 512, 6)
        assert scan.valid.mean() > 0.8
        assert scan.count(1) > 1000  # real cars ahead, labelled car
        assert scan.image[..., 3].max() > 0  # real remission kept as intensity


def _ring_ordered_cloud(sensor, parallax_deg: float, seed: int = 0, start_deg: float = 0.05
                        ) -> tuple[np.ndarray, np.ndarray]:
    """Points stored as KITTI stores them: ring by ring from the top laser, each sweeping
    azimuth up from 0 through +-180 back to 0, at the preset's elevations moved by up to
    `parallax_deg` (a laser off the origin, seen at short range), with azimuth jitter."""
    rng = np.random.default_rng(seed)
    pts, ring = [], []
    for k, el in enumerate(sensor.elevations_deg):
        # KITTI's rings start just past 0 degrees; jitter crosses +-180 back and forth
        az = start_deg + np.linspace(0.0, 360.0, 2000, endpoint=False) + rng.uniform(
            -0.03, 0.03, 2000)
        az = (az + 180.0) % 360.0 - 180.0
        e = np.radians(el + rng.uniform(-parallax_deg, parallax_deg, 2000))
        a = np.radians(az)
        r = rng.uniform(3.0, 60.0, 2000)
        pts.append(np.stack([r * np.cos(e) * np.cos(a), r * np.cos(e) * np.sin(a),
                             r * np.sin(e)], axis=1))
        ring.append(np.full(2000, k))
    return np.concatenate(pts), np.concatenate(ring)


def test_kitti_scans_are_read_by_laser_ring(tmp_path):
    """Rows come from KITTI's storage order, not the elevation: with elevations moved by up to
    0.6 degrees (more than the 0.33 between upper rings) every point keeps its ring's row, and
    the front view's rows stay full; binning by elevation loses many pixels."""
    sensor = load_sensor("kitti-hdl64e-front")
    pts, ring = _ring_ordered_cloud(sensor, 0.6)
    np.testing.assert_array_equal(kitti_rows(sensor, pts), ring)
    np.column_stack([pts, np.zeros(len(pts))]).astype(np.float32).tofile(tmp_path / "r.bin")
    scan = read_kitti(tmp_path / "r.bin", None, sensor)
    assert scan.valid.mean(axis=1).min() > 0.9  # 500 points a ring over 512 columns
    row_of = np.nonzero(scan.valid)[0]
    el = np.degrees(np.arcsin(scan.image[..., 2][scan.valid] / scan.image[..., 4][scan.valid]))
    assert np.abs(el - np.asarray(sensor.elevations_deg)[row_of]).max() <= 0.6 + 1e-3
    by_elevation = read_kitti(tmp_path / "r.bin", None, replace(sensor, kitti_rings=False))
    assert by_elevation.valid[:32].mean() < scan.valid[:32].mean() - 0.1
    back, ring_back = _ring_ordered_cloud(sensor, 0.6, start_deg=-179.9)  # cut at the back
    np.testing.assert_array_equal(kitti_rows(sensor, back), ring_back)
    assert kitti_rows(sensor, pts[::-1]) is None  # reversed order: not KITTI's
    assert kitti_rows(sensor, pts[: 2000 * 40]) is None  # 40 rings: not the sensor's 64
    rng = np.random.default_rng(1)
    assert kitti_rows(sensor, pts[rng.permutation(len(pts))]) is None
    assert kitti_rows(replace(sensor, kitti_rings=False), pts) is None
    assert kitti_rows(load_sensor("vlp16"), pts) is None


def test_real_kitti_files_hold_64_rings_top_down(kitti_dir):
    """KITTI's object frames and SemanticKITTI scans: 64 rings of about 2,000 points, and far
    points (parallax small) step down ring by ring from the preset's top row."""
    sensor = load_sensor("kitti-hdl64e-front")
    files = sorted((kitti_dir / "semantickitti").glob("*.bin")) + sorted(
        (kitti_dir / "object" / "velodyne").glob("*.bin"))
    assert files
    for path in files:
        pts = np.fromfile(path, np.float32).reshape(-1, 4)[:, :3].astype(np.float64)
        ring = kitti_rows(sensor, pts)
        assert ring is not None, path.name
        counts = np.bincount(ring, minlength=KITTI_RINGS)
        assert len(counts) == KITTI_RINGS and np.median(counts) > 1800
        r = np.linalg.norm(pts, axis=1)
        el = np.degrees(np.arcsin(pts[:, 2] / r))
        far = [np.median(el[(ring == k) & (r > 25.0)]) for k in range(8)]
        assert (np.diff(far) < 0).all(), path.name
        assert far[0] == pytest.approx(sensor.elevations_deg[0], abs=0.3)
        # the front view's upper rows: empty pixels under a return (measured: 4.5-12 % by
        # ring, 11-19 % by elevation; what is left is columns: the upper lasers' azimuths do not
        # keep to the 512-column grid)
        by_ring = _holes_under_a_return(read_kitti(path, None, sensor).image)
        by_elevation = _holes_under_a_return(
            read_kitti(path, None, replace(sensor, kitti_rings=False)).image)
        assert by_ring < 0.13 and by_ring < 0.7 * by_elevation, (path.name, by_ring)


def _holes_under_a_return(image: np.ndarray) -> float:
    """Share of rows 1-31's pixels with a return above them in their column but none of
    their own."""
    valid = image[..., 4] > 0
    seen = np.zeros_like(valid)
    seen[1:] = np.maximum.accumulate(valid, axis=0)[:-1]
    return float((seen & ~valid)[1:32].sum() / seen[1:32].sum())


def test_kitti_bin_label_round_trip(tmp_path):
    sensor = load_sensor("kitti-hdl64e-front")
    sim = Simulator(sensor)
    scan = sim.render(2, [PlacedCar("van", 12.0, 1.0, 20.0, 1)])
    write_kitti(scan, tmp_path / "s.bin", tmp_path / "s.label")
    back = read_kitti(tmp_path / "s.bin", tmp_path / "s.label", sensor)
    np.testing.assert_array_equal(back.valid, scan.valid)
    np.testing.assert_array_equal(back.image[..., 5], scan.image[..., 5])
    np.testing.assert_array_equal(back.instance, scan.instance & 0xFFFF)
    np.testing.assert_allclose(back.image[..., :5], scan.image[..., :5], atol=1e-4)


def test_bad_kitti_files(tmp_path):
    sensor = load_sensor("kitti-hdl64e-front")
    (tmp_path / "a.bin").write_bytes(b"\0" * 10)
    with pytest.raises(FalsifyError, match="a.bin: size is not a multiple"):
        read_kitti(tmp_path / "a.bin", None, sensor)
    np.zeros((3, 4), np.float32).tofile(tmp_path / "b.bin")
    np.zeros(2, np.uint32).tofile(tmp_path / "b.label")
    with pytest.raises(FalsifyError, match="2 labels for 3 points"):
        read_kitti(tmp_path / "b.bin", tmp_path / "b.label", sensor)
    np.save(tmp_path / "bad.npy", np.zeros((4, 4)))
    with pytest.raises(FalsifyError, match="expected \\(H, W, 6\\)"):
        load_scan_npy(tmp_path / "bad.npy")
    arr = np.zeros((2, 2, 6), np.float32)
    arr[0, 0, 0] = np.nan
    np.save(tmp_path / "nan.npy", arr)
    with pytest.raises(FalsifyError, match="NaN or inf"):
        load_scan_npy(tmp_path / "nan.npy")


BASE = {"elevations_deg": [2.0, 0.0, -2.0], "h_fov_deg": [45.0, -45.0], "columns": 8}


@pytest.mark.parametrize(("change", "message"), [
    ({"elevations_deg": [90.0, 0.0]}, "FOV < 180"),
    ({"elevations_deg": [0.0, -95.0]}, "FOV < 180"),
    ({"elevations_deg": [0.0, 1.0]}, "decrease strictly"),
    ({"h_fov_deg": [200.0, -200.0]}, "must be in (0, 360]"),
    ({"h_fov_deg": [-45.0, 45.0]}, "must be in (0, 360]"),
    ({"columns": 0}, "columns: 0 must be an integer"),
    ({"max_range": -1.0}, "max_range: -1.0 must be > 0"),
    ({"ray_drop": 1.5}, "ray_drop: 1.5 must be <= 1"),
    ({"pitch": 3}, "unknown key 'pitch'"),
    ({"kitti_rings": "yes"}, "kitti_rings: expected true or false"),
    ({"vertical": {"up_deg": 2, "down_deg": -2, "beams": 4}}, "exactly one of"),
    ({"ring_offsets_m": [0.1, 0.1]}, "ring_offsets_m: expected a list of 3 numbers"),
    ({"ring_offsets_m": [0.1, "x", 0.1]}, "ring_offsets_m: expected a list of 3 numbers"),
    ({"ring_offsets_m": [0.1, 0.1, 2.0]}, "each within ±1"),
])
def test_bad_sensor_values_name_the_key(change, message):
    with pytest.raises(ConfigError) as err:
        parse_sensor({**BASE, **change})
    assert message in str(err.value)


def test_ring_offsets_parse_and_follow_a_resampled_grid():
    sensor = parse_sensor({**BASE, "ring_offsets_m": [0.2, 0.2, 0.1]})
    assert sensor.ring_offsets_m == (0.2, 0.2, 0.1)
    assert sensor.ray_origins[:, 0, 2].tolist() == [0.2, 0.2, 0.1]
    finer = sensor.with_resolution(5, 16)
    assert finer.ring_offsets_m == pytest.approx((0.2, 0.2, 0.2, 0.15, 0.1))
    assert parse_sensor(BASE).ray_origins is None
    assert parse_sensor({**BASE, "ring_offsets_m": [0, 0, 0]}).ray_origins is None


def test_unknown_preset_lists_the_presets():
    with pytest.raises(ConfigError, match="allowed: .*kitti-hdl64e-front"):
        load_sensor("hdl-128")


def test_pixel_of_full_circle_wraps():
    sensor = load_sensor("kitti-hdl64e-360")
    pts = np.array([[-10.0, 1e-9, 0.0], [-10.0, -1e-9, 0.0], [10.0, 0.0, 0.0]])
    _, col, inside = sensor.pixel_of(pts)
    assert inside.all() and set(col.tolist()) <= set(range(2048))
    assert col[2] in (1023, 1024)


def test_sensor_noise_and_drop_are_seeded():
    # Without the fitted return model, so the drop measured is ray_drop's alone.
    sensor = load_sensor("kitti-hdl64e-front", ray_drop=0.1, range_noise=0.02, returns="")
    sim = Simulator(sensor)
    car = [PlacedCar("sedan", 10.0, 0.0, 0.0, 1)]
    a = sim.render(0, car, rng=np.random.default_rng(5))
    b = sim.render(0, car, rng=np.random.default_rng(5))
    c = sim.render(0, car, rng=np.random.default_rng(6))
    clean = sim.render(0, car)
    assert a.image.tobytes() == b.image.tobytes()
    assert a.image.tobytes() != c.image.tobytes()
    assert 0.05 < 1 - a.valid.sum() / clean.valid.sum() < 0.15


def test_placed_pixels_are_the_placed_cars_not_the_parked_ones():
    sim = Simulator(load_sensor("kitti-hdl64e-front"))
    scan = sim.render(0, [PlacedCar("sedan", 10.0, 0.0, 0.0, 1), PlacedCar("sedan", 16.0, -3.0,
                                                                          30.0, 2)])
    placed = sim.placed_pixels(scan)
    car = scan.valid & (scan.label == 1)
    assert placed.sum() > 200 and np.array_equal(placed, car & (scan.instance < 1000))
    assert set(np.unique(scan.instance[placed])) == {1, 2}
    parked = car & ~placed
    assert parked.sum() > 100 and (scan.instance[parked] >= 1000).all()
