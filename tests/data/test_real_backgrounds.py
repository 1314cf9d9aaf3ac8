"""Synthetic cars inserted into real scans: constructed scans whose geometry is known (a ground
plane and a wall, cast analytically with a 360-degree HDL-64E's rays), and the real
SemanticKITTI scans where the test data folder holds them (tests/conftest.py)."""

from __future__ import annotations

import dataclasses
import math
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from falsify.data.real_backgrounds import (
    COLLISION_POINTS,
    INSERTED_INSTANCE,
    PointIndex,
    RealScanner,
    fit_ground,
    pixel_directions,
)
from falsify.data.real_backgrounds.rays import meets_box as _meets_box
from falsify.data.velodyne import read_kitti
from falsify.errors import ConfigError, FalsifyError
from falsify.results.metrics import Scoring
from falsify.semantic import RAW_ID
from falsify.sensor.lidar import load_sensor
from falsify.sensor.simulator import InvalidSample
from falsify.world.space import RealScan, load_space, parse_space
from tests.conftest import MINI

MOUNT = 1.73
WALL_X = 25.0          # a wall across the road, 25 m ahead


def street_cloud(slope: float = 0.0, extra: np.ndarray | None = None
                 ) -> tuple[np.ndarray, np.ndarray]:
    """(N, 4) points and raw ids: a 360-degree HDL-64E's rays meeting the ground
    z = -MOUNT + slope * x (road) or the wall x = WALL_X (building), whichever is nearer."""
    d = load_sensor("kitti-hdl64e-360").directions.reshape(-1, 3)
    with np.errstate(divide="ignore", invalid="ignore"):
        t_ground = -MOUNT / (d[:, 2] - slope * d[:, 0])
        t_wall = WALL_X / d[:, 0]
    t_ground = np.where(t_ground > 0, t_ground, np.inf)
    t_wall = np.where(t_wall > 0, t_wall, np.inf)
    t = np.minimum(t_ground, t_wall)
    keep = np.isfinite(t) & (t < 100.0)
    xyz = d[keep] * t[keep, None]
    sem = np.where(t_wall[keep] < t_ground[keep], RAW_ID["building"], RAW_ID["road"])
    if extra is not None:
        xyz = np.concatenate([xyz, extra[:, :3]])
        sem = np.concatenate([sem, extra[:, 3]])
    pts = np.column_stack([xyz, np.full(len(xyz), 0.25)]).astype(np.float32)
    return pts, sem.astype(np.uint32)


def write_scan(folder: Path, pts: np.ndarray, sem: np.ndarray | None, name: str = "000000"
               ) -> RealScan:
    """A SemanticKITTI-style .bin (+ .label when `sem` is given) in `folder`."""
    folder.mkdir(parents=True, exist_ok=True)
    pts.tofile(folder / f"{name}.bin")
    label = None
    if sem is not None:
        label = folder / f"{name}.label"
        sem.astype(np.uint32).tofile(label)
    return RealScan(f"t/{name}", folder / f"{name}.bin", label,
                    "semantickitti" if sem is not None else "none")


def space_toml(path: Path, real: str, extra: str = "") -> Path:
    path.write_text(f"""name = "inserted"
[dims.car_model]
values = ["sedan"]
[dims.x]
values = [0.0, 2.0]
[dims.y]
values = [8.0, 12.0]
[dims.background]
real = ['{real}']
{extra}""")
    return path


@pytest.fixture(scope="module")
def street(tmp_path_factory) -> RealScan:
    pts, sem = street_cloud()
    return write_scan(tmp_path_factory.mktemp("street"), pts, sem)


@pytest.fixture(scope="module")
def scanner(street) -> RealScanner:
    return RealScanner(load_sensor("kitti-hdl64e-front"), (street,))


def sample(x: float, y: float, yaw: float = 0.0):
    raw = {"dims": {"car_model": {"values": ["sedan"]}, "x": {"values": [x]},
                    "y": {"values": [y]}, "yaw": {"values": [yaw]},
                    "background": {"values": [0]}}}
    return parse_space(raw).grid()[0]


def same(a, b) -> bool:
    return (a.image.tobytes() == b.image.tobytes() and a.instance.tobytes() == b.instance.tobytes()
            and (a.semantic is None) == (b.semantic is None)
            and (a.semantic is None or a.semantic.tobytes() == b.semantic.tobytes()))


def test_a_car_beyond_the_range_or_out_of_view_leaves_the_real_scan_byte_for_byte(
        scanner, street):
    real = read_kitti(street.bin, street.label, scanner.sensor)
    for x, y in ((0.0, 150.0), (0.0, -10.0), (12.0, 0.0), (-12.0, 2.0)):
        scan = scanner.scan(sample(x, y), rng=np.random.default_rng(1))
        assert same(scan, real), (x, y)


def test_the_car_occludes_the_wall_behind_it_and_only_its_columns_change(scanner, street):
    real = read_kitti(street.bin, street.label, scanner.sensor)
    scan = scanner.scan(sample(0.0, 12.0), rng=np.random.default_rng(1))
    car = scan.instance >= INSERTED_INSTANCE
    assert car.sum() > 300
    assert (scan.label[car] == 1).all()
    assert (scan.semantic[car] == RAW_ID["car"]).all()
    # Its points stand where the car is: 10-16 m ahead, on the ground, below its roof.
    pts = scan.image[car]
    assert pts[:, 0].min() > 9.0 and pts[:, 0].max() < 16.0
    assert pts[:, 2].min() > -MOUNT - 0.05 and pts[:, 2].max() < -MOUNT + 1.7
    # Wall pixels the car covers lost their wall point: the ray now ends at the car.
    wall = real.semantic == RAW_ID["building"]
    hidden = wall & car
    assert hidden.sum() > 50
    assert (scan.image[hidden, 4] < real.image[hidden, 4] - 5.0).all()
    # Every pixel the car did not take (and did not empty) keeps the real bytes.
    changed = (scan.image != real.image).any(axis=-1)
    assert not (changed & ~car & scan.valid).any()
    cols = np.flatnonzero(changed.any(axis=0))
    assert set(cols) <= set(scanner.columns(scanner.placed_cars(sample(0.0, 12.0))[0]))


def test_casting_only_the_cars_columns_equals_casting_every_column(scanner, monkeypatch):
    s = sample(-2.0, 9.0, 30.0)
    windowed = scanner.scan(s, rng=np.random.default_rng(3))
    monkeypatch.setattr(scanner, "columns", lambda car: np.arange(scanner.sensor.columns))
    assert same(scanner.scan(s, rng=np.random.default_rng(3)), windowed)


def test_the_same_sample_and_seed_give_the_same_bytes(street):
    a = RealScanner(load_sensor("kitti-hdl64e-front"), (street,))
    b = RealScanner(load_sensor("kitti-hdl64e-front"), (street,))
    s = sample(1.0, 10.0, 15.0)
    assert same(a.scan(s, rng=np.random.default_rng(5)), b.scan(s, rng=np.random.default_rng(5)))
    assert not same(a.scan(s, rng=np.random.default_rng(5)),
                    a.scan(s, rng=np.random.default_rng(6)))


def test_an_inserted_car_is_shaded_by_its_class_as_the_streets_cars_are(street):
    """With a per-class return model an inserted car takes the car class's shades (dark, as real
    cars return), one shade per car, not its materials' levels; the same seed, the same bytes."""
    s = sample(1.0, 10.0)

    def car_points(returns: str, seed: int) -> tuple:
        sc = RealScanner(load_sensor("kitti-hdl64e-front", returns=returns), (street,))
        scan = sc.scan(s, rng=np.random.default_rng(seed))
        car = sc.placed_pixels(scan)
        return scan, scan.image[..., 3][car], scan.semantic[car]

    a, _, sem = car_points("semantickitti-fit", 4)
    assert same(a, car_points("semantickitti-fit", 4)[0])
    assert len(sem) > 100 and set(np.unique(sem)) == {RAW_ID["car"]}
    by_class = [np.median(car_points("semantickitti-fit", k)[1]) for k in range(6)]
    by_material = [np.median(car_points("kitti-hdl64e", k)[1]) for k in range(6)]
    assert np.mean(by_class) < 0.6 * np.mean(by_material)
    assert np.ptp(by_class) > 3 * np.ptp(by_material)      # each car its own shade


def test_a_car_in_a_wall_is_invalid_and_named(scanner):
    with pytest.raises(InvalidSample, match=r"intersects the real scan's building"):
        scanner.scan(sample(0.0, WALL_X))


def test_a_real_car_in_the_way_is_invalid_and_few_stray_points_are_removed(tmp_path):
    sensor = load_sensor("kitti-hdl64e-front")
    # A block of "car" points 10 m ahead, 0.5-1.2 m above the ground.
    g = np.mgrid[9.0:11.0:0.1, -0.8:0.8:0.1, 0.5:1.2:0.1].reshape(3, -1).T
    block = np.column_stack([g[:, 0], g[:, 1], g[:, 2] - MOUNT, np.full(len(g), 10)])
    pts, sem = street_cloud(extra=block)
    scanner = RealScanner(sensor, (write_scan(tmp_path / "car", pts, sem),))
    with pytest.raises(InvalidSample, match=r"intersects the real scan's car \(\d+ points"):
        scanner.scan(sample(0.0, 10.0))
    # Fewer than COLLISION_POINTS: not a collision; the points in the car's body go.
    few = block[:COLLISION_POINTS - 1]
    pts, sem = street_cloud(extra=few)
    scanner = RealScanner(sensor, (write_scan(tmp_path / "few", pts, sem),))
    scan = scanner.scan(sample(0.0, 10.0), rng=np.random.default_rng(0))
    left = scan.image[scan.valid & (scan.semantic == RAW_ID["car"])
                      & (scan.instance < INSERTED_INSTANCE)]
    assert len(left) == 0
    # Unlabelled, any point above the clearance counts, and is named as points.
    pts, _ = street_cloud(extra=block)
    scanner = RealScanner(sensor, (write_scan(tmp_path / "unlabelled", pts, None),))
    with pytest.raises(InvalidSample, match=r"intersects the real scan's points"):
        scanner.scan(sample(0.0, 10.0))


def test_the_car_stands_on_the_fitted_slope(tmp_path):
    slope = 0.05
    pts, sem = street_cloud(slope=slope)
    scanner = RealScanner(load_sensor("kitti-hdl64e-front"),
                          (write_scan(tmp_path / "slope", pts, sem),))
    car = scanner.placed_cars(sample(0.0, 10.0))[0]
    assert car.z == pytest.approx(-MOUNT + slope * 10.0, abs=0.02)
    assert car.pitch_deg == pytest.approx(math.degrees(math.atan(-slope)), abs=0.2)
    assert car.roll_deg == pytest.approx(0.0, abs=0.2)
    # Turned 90 degrees, the slope is across the car: roll, not pitch.
    car = scanner.placed_cars(sample(0.0, 10.0, 90.0))[0]
    assert car.pitch_deg == pytest.approx(0.0, abs=0.2)
    assert abs(car.roll_deg) == pytest.approx(math.degrees(math.atan(slope)), abs=0.2)


def test_fit_ground_is_exact_on_a_plane_and_flat_where_nothing_is_near():
    rng = np.random.default_rng(0)
    xy = rng.uniform(-5, 5, (400, 2))
    plane = np.column_stack([xy, -1.7 + 0.02 * xy[:, 0] - 0.03 * xy[:, 1]])
    z, gx, gy = fit_ground(PointIndex.of(plane), 1.0, 2.0, 2.5, -9.0)
    assert (z, gx, gy) == pytest.approx((-1.7 + 0.02 - 0.06, 0.02, -0.03), abs=1e-9)
    assert fit_ground(PointIndex.of(plane), 500.0, 0.0, 2.5, -9.0) == (-9.0, 0.0, 0.0)
    assert fit_ground(PointIndex.of(np.empty((0, 3))), 0.0, 0.0, 2.5, -1.73) == (-1.73, 0.0,
                                                                                 0.0)


def test_the_point_index_finds_every_point_near_a_place():
    rng = np.random.default_rng(1)
    pts = rng.uniform(-60, 60, (20000, 3))
    index = PointIndex.of(pts, np.arange(20000))
    for x, y, r in ((0.0, 0.0, 3.0), (-59.0, 10.5, 2.0), (13.3, -7.9, 7.5), (200.0, 0.0, 1.0)):
        found = set(index.semantic[index.near(x, y, r)].tolist())
        inside = np.flatnonzero((np.abs(pts[:, 0] - x) <= r) & (np.abs(pts[:, 1] - y) <= r))
        assert set(inside.tolist()) <= found
    kept = index.subset(index.points[:, 2] > 0)
    assert (kept.points[:, 2] > 0).all() and (np.diff(kept.keys) >= 0).all()


def test_the_slab_test_never_misses_a_ray_that_meets_the_box():
    rng = np.random.default_rng(2)
    o = rng.normal(0, 6, (4000, 3))
    d = rng.normal(size=(4000, 3))
    d[:500, 1:] = 0.0     # axis-parallel rays: directions with exact zeros
    d[500:900, 2] = 0.0
    d /= np.linalg.norm(d, axis=1)[:, None]
    lo, hi = np.array([-2.0, -1.0, 0.0]), np.array([2.0, 1.0, 1.5])
    hits = _meets_box(o, d, np.full(4000, 30.0), lo, hi)
    t = np.linspace(0.0, 30.0, 6001)
    walk = o[:, None, :] + d[:, None, :] * t[None, :, None]
    met = ((walk >= lo) & (walk <= hi)).all(axis=-1).any(axis=1)
    assert (hits >= met).all() and met.sum() > 50
    assert (hits & ~met).sum() <= 0.01 * len(o)   # grazing rays the walk steps over


def test_spherical_pixel_directions_land_in_their_own_pixels():
    sensor = load_sensor("semantickitti-hdl64e")
    d = pixel_directions(sensor)
    rows, cols, inside = sensor.pixel_of(d.reshape(-1, 3) * 10.0)
    h, w = sensor.shape
    assert inside.all()
    assert (rows == np.repeat(np.arange(h), w)).all()
    assert (cols == np.tile(np.arange(w), h)).all()


def test_parts_score_the_inserted_and_the_real_cars_apart():
    scoring = Scoring(parts=True)
    truth = np.array([1, 1, 1, 1, 0, 0])
    inserted = np.array([True, True, False, False, False, False])
    pred = np.array([1, 0, 1, 1, 1, 0])
    m, _ = scoring.score(pred, truth, inserted)
    # Inserted: real car pixels (2, 3) left out; TP 1, FN 1, FP 1 (pixel 4).
    assert m["inserted_iou"] == pytest.approx(1 / 3)
    assert m["inserted_recall"] == pytest.approx(1 / 2)
    # Real: inserted pixels left out; TP 2, FP 1.
    assert m["real_iou"] == pytest.approx(2 / 3)
    assert m["real_recall"] == 1.0
    assert m["car_iou"] == pytest.approx(3 / 5)
    assert "inserted_iou" in scoring.columns and "inserted_iou" not in Scoring().columns


def test_config_names_the_missing_scan_and_refuses_weather(tmp_path):
    with pytest.raises(ConfigError, match=r"dims.background.real: .*nowhere.bin: no such file"):
        load_space(space_toml(tmp_path / "a.toml", str(tmp_path / "nowhere.bin")))
    missing = space_toml(tmp_path / "m.toml", str(tmp_path / "no-root"), 'sequences = ["08"]\n')
    with pytest.raises(ConfigError, match=r"no-root: no such file or folder"):
        load_space(missing)
    (tmp_path / "x.bin").write_bytes(b"\0" * 17)
    with pytest.raises(ConfigError, match=r"x.bin: 17 bytes is not a KITTI scan"):
        load_space(space_toml(tmp_path / "b.toml", str(tmp_path / "x.bin")))
    (tmp_path / "x.bin").write_bytes(b"\0" * 32)
    (tmp_path / "x.label").write_bytes(b"\0" * 4)
    with pytest.raises(ConfigError, match=r"x.label: 1 labels for 2 points in x.bin"):
        load_space(space_toml(tmp_path / "b.toml", str(tmp_path / "x.bin")))
    (tmp_path / "x.label").unlink()
    ok = space_toml(tmp_path / "c.toml", str(tmp_path / "x.bin"))
    (tmp_path / "d.toml").write_text(ok.read_text().replace("real = [", "values = [0]\nreal = ["))
    with pytest.raises(ConfigError, match=r"unknown key 'values' beside real"):
        load_space(tmp_path / "d.toml")


def test_config_relative_paths_and_the_data_itself_are_part_of_the_space(tmp_path, street):
    import shutil
    shutil.copy(street.bin, tmp_path / "s.bin")
    shutil.copy(street.label, tmp_path / "s.label")
    space = load_space(space_toml(tmp_path / "a.toml", "s.bin"))
    assert space.real_backgrounds[0].kind == "semantickitti"
    assert space.background_name(0).endswith("/s")
    before = space.config_hash
    pts, sem = street_cloud(slope=0.01)
    pts.tofile(tmp_path / "s.bin")
    sem.tofile(tmp_path / "s.label")
    assert load_space(tmp_path / "a.toml").config_hash != before


def test_grid_on_a_real_background_exits_2_on_a_bad_path_and_writes_nothing(tmp_path):
    cfg = space_toml(tmp_path / "bad.toml", str(tmp_path / "missing.bin"))
    out = tmp_path / "run"
    proc = subprocess.run([sys.executable, "-m", "falsify", "grid", str(cfg), "--out", str(out)],
                          capture_output=True, text=True)
    assert proc.returncode == 2
    assert "missing.bin" in proc.stderr
    assert not out.exists()


def test_grid_and_gate_run_on_a_constructed_real_background(tmp_path, street):
    cfg = space_toml(tmp_path / "ok.toml", str(street.bin))
    out = tmp_path / "run"
    proc = subprocess.run([sys.executable, "-m", "falsify", "grid", str(cfg), "--out", str(out),
                           "--json", "--no-report"], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    import sqlite3
    with sqlite3.connect(out / "results.sqlite") as con:
        rows = con.execute("SELECT status, car_iou, inserted_iou, real_recall "
                           "FROM samples").fetchall()
    assert len(rows) == 4 and all(r[0] == "ok" for r in rows)
    assert all(r[2] is not None for r in rows)   # the inserted car is scored apart
    assert all(r[3] is None for r in rows)       # no real car here: its recall is undefined
    gate = subprocess.run([sys.executable, "-m", "falsify", "gate", str(out),
                           "--max-blind-spots", "4", "--json"], capture_output=True, text=True)
    assert gate.returncode == 0, gate.stderr


@pytest.mark.skipif(not MINI.is_dir(), reason=f"SemanticKITTI mini scans not found at {MINI} "
                    "(see shared/data/README.md)")
def test_real_semantickitti_scans_keep_their_bytes_out_of_the_cars_reach(tmp_path):
    seq = MINI / "sequences" / "08"
    space = load_space(space_toml(tmp_path / "r.toml", str(seq)))
    assert [r.name for r in space.real_backgrounds] == ["08/000000", "08/000005", "08/000009"]
    scanner = RealScanner(load_sensor(space.sensor), space.real_backgrounds)
    for bg, real in enumerate(space.real_backgrounds):
        behind = space.make({"x": 0.0, "y": 8.0, "background": bg})
        car = scanner.placed_cars(behind)[0]
        # Behind the sensor, out of the front view: the scan is the real one.
        scan = scanner.insert(scanner.background(bg), [replace(car, x=-car.x)],
                              np.random.default_rng(0))
        assert same(scan, read_kitti(real.bin, real.label, scanner.sensor))


def test_retrain_runs_on_real_backgrounds_and_refuses_evaluation_scans(tmp_path):
    pytest.importorskip("torch")   # its fine-tuning trains
    from falsify.data.training import TrafficOptions, write_dataset
    from falsify.jobs.retrain import RetrainJob, RetrainRequest
    from falsify.models.runners import BUNDLED_ONNX

    v = write_scan(tmp_path / "v", *street_cloud())
    r = write_scan(tmp_path / "r", *street_cloud(slope=0.02))
    cfg = tmp_path / "two.toml"
    cfg.write_text("threshold = 0.99\n" + space_toml(tmp_path / "x.toml", str(v.bin)).read_text(
    ).replace(f"real = ['{v.bin}']", f"real = ['{v.bin}', '{r.bin}']"))
    write_dataset(load_sensor("kitti-hdl64e-front"), tmp_path / "train", 1, seed=1,
                  opts=TrafficOptions(backgrounds=1, traffic="drive"))
    req = RetrainRequest(config=cfg, model=BUNDLED_ONNX, train_data=tmp_path / "train",
                         out=tmp_path / "exp", validation=(0,), retraining=(1,), epochs=1,
                         batch=4, oversample=1, train_scans=1, held_out_scans=0, kitti=None,
                         workers=1)
    result = RetrainJob(req).run()
    assert result.retraining_scans > 0 and result.model_after is not None
    sub = load_space(tmp_path / "exp" / "config-retraining.toml")
    assert [s.bin for s in sub.real_backgrounds] == [r.bin.resolve()]
    if MINI.is_dir():   # a scan of the evaluation split may be tested on, never trained on
        seq08 = MINI / "sequences" / "08" / "velodyne" / "000000.bin"
        cfg.write_text(cfg.read_text().replace(str(r.bin), str(seq08)))
        with pytest.raises(FalsifyError, match="held-out scan"):
            RetrainJob(dataclasses.replace(req, out=tmp_path / "exp2")).prepare()


def test_the_report_of_a_real_run_names_its_scans_escaped_in_chromium(tmp_path, browser):
    from selenium.webdriver.common.by import By

    from tests.conftest import assert_offline

    odd = 'st<b>&"x'
    scan = write_scan(tmp_path / odd, *street_cloud())
    cfg = space_toml(tmp_path / "odd.toml", str(scan.bin))
    out = tmp_path / "run"
    proc = subprocess.run([sys.executable, "-m", "falsify", "grid", str(cfg), "--out", str(out),
                           "--quiet"], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    html = (out / "report.html").read_text()
    assert "st&lt;b&gt;&amp;&quot;x/000000" in html and odd not in html
    browser.get((out / "report.html").as_uri())
    section = browser.find_element(By.ID, "inserted")
    assert section.is_displayed()
    assert len(section.find_elements(By.CSS_SELECTOR, "figure svg")) == 2
    rows = section.find_elements(By.CSS_SELECTOR, "tbody tr")
    assert [r.find_elements(By.TAG_NAME, "td")[0].text for r in rows] == [f"{odd}/000000"]
    assert_offline(browser)


def test_the_fast_insertion_casts_what_the_naive_path_casts(tmp_path, street):
    from falsify.bench.scan import naive_insert

    space = load_space(space_toml(tmp_path / "n.toml", str(street.bin)))
    scanner = RealScanner(load_sensor(space.sensor), space.real_backgrounds)
    for s in space.grid():
        fast = scanner.scan(s)   # no rng: no dropouts, no range noise
        naive = naive_insert(space, s)
        car = fast.instance >= INSERTED_INSTANCE
        real = scanner.background(0).dist
        hit = naive < real - 1e-6
        assert car.sum() > 100 and not (car & ~hit).any()
        assert np.allclose(fast.image[car, 4], naive[car], atol=2e-3)
        # what the naive path hits and the fast scan does not show is glass (no return)
        assert (hit & ~car).sum() < 0.25 * hit.sum()


def test_bench_scan_on_real_scans_keeps_its_rounds_and_best_of_three(tmp_path, street):
    """`bench scan` on real backgrounds: N rounds of the N-process run (their median), and the
    1-process rate the best of its three passes alternating with our streets."""
    from falsify.bench.scan import bench_scan

    cfg = space_toml(tmp_path / "b.toml", str(street.bin))
    r = bench_scan(cfg, samples=4, naive_samples=1, workers=2, repeats=2).to_json()
    assert r["background"] == "real scans (insertion)" and r["rounds"] == 2
    two = r["fast_scans_per_s_2_processes_rounds"]
    one = r["fast_scans_per_s_1_process_rounds"]
    assert len(two) == 2 and len(one) == 3 and min(one + two) > 0
    assert r["fast_scans_per_s_2_processes"] == pytest.approx(np.median(two), abs=0.1)
    assert r["fast_scans_per_s_1_process"] == pytest.approx(max(one), abs=0.1)
    assert r["streets_scans_per_s_1_process"] > 0


def test_scan_inserts_into_a_real_background_and_refuses_what_needs_our_streets(tmp_path,
                                                                                 street):
    cfg = space_toml(tmp_path / "s.toml", str(street.bin))
    run = [sys.executable, "-m", "falsify"]
    proc = subprocess.run([*run, "scan", str(cfg), "--out", str(tmp_path / "scan"), "--set",
                           "x=0", "--set", "y=12", "--json"], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    labels = np.fromfile(tmp_path / "scan" / "scan.label", np.uint32)
    assert ((labels & 0xFFFF) == RAW_ID["car"]).sum() > 300       # the inserted car
    assert ((labels & 0xFFFF) == RAW_ID["building"]).sum() > 100  # the real wall behind it
    for args in (["scan", str(cfg), "--out", str(tmp_path / "cam"), "--camera"],
                 ["tradeoff", str(cfg), "--out", str(tmp_path / "t")]):
        bad = subprocess.run([*run, *args], capture_output=True, text=True)
        assert bad.returncode == 2 and "backgrounds are real scans" in bad.stderr, bad.stderr
        assert not (tmp_path / args[3]).exists()
