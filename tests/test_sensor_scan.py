"""Sensor presets against the real KITTI layout, and the scan file formats (ours and KITTI's)."""

from __future__ import annotations

import numpy as np
import pytest

from falsify.errors import ConfigError, FalsifyError
from falsify.kitti import load_scan_npy, read_kitti, write_kitti
from falsify.scene import PlacedCar, Simulator
from falsify.sensor import load_sensor, parse_sensor, preset_names


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
    ({"vertical": {"up_deg": 2, "down_deg": -2, "beams": 4}}, "exactly one of"),
])
def test_bad_sensor_values_name_the_key(change, message):
    with pytest.raises(ConfigError) as err:
        parse_sensor({**BASE, **change})
    assert message in str(err.value)


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
