"""Weather and sensor faults on real backgrounds (RealScanner.weather): each recorded return,
real or inserted, through the same physics as a cast ray. Constructed KITTI scans whose ranges
and remissions are known: the fog against its formulas, zero severity against the scan's bytes,
each effect dim on a real background, seeding, and a grid run."""

from __future__ import annotations

import json
import math

import numpy as np
import pandas as pd
import pytest

from falsify.cli import main
from falsify.data.real_backgrounds import INSERTED_INSTANCE, RealScanner, scanner_for
from falsify.errors import ConfigError
from falsify.paths import config_path
from falsify.semantic import RAW_ID
from falsify.sensor import weather
from falsify.sensor.lidar import load_sensor
from falsify.world.space import load_space, parse_space
from tests.data.test_real_backgrounds import space_toml, write_scan
from tests.sensor.test_weather import reference_peak

MOUNT = 1.73
SECTORS = ((15.0, 10.0), (-15.0, 40.0), (-90.0, 80.0))   # azimuth above which: wall range (m)
REMISSION = 0.5
SENSOR = "kitti-hdl64e-front"


def walls_cloud() -> tuple[np.ndarray, np.ndarray]:
    """(N, 4) points and raw ids: each of the front sensor's rays ends on a wall at exactly 10 m
    (left third), 40 m (middle) or 80 m (right third), or on the road z = -MOUNT where that is
    nearer. Walls have remission 0.5 but every 7th wall point 0 (stored below KITTI's first
    step); the road 0.3."""
    s = load_sensor(SENSOR)
    d = s.directions.reshape(-1, 3)
    az = np.broadcast_to(s.azimuths_deg, s.shape).reshape(-1)
    wall = np.select([az > a for a, _ in SECTORS], [r for _, r in SECTORS])
    with np.errstate(divide="ignore"):
        road = np.where(d[:, 2] < 0, -MOUNT / d[:, 2], np.inf)
    on_road = road < wall
    t = np.where(on_road, road, wall)
    remission = np.where(on_road, 0.3, REMISSION)
    remission[np.flatnonzero(~on_road)[::7]] = 0.0
    pts = np.column_stack([d * t[:, None], remission]).astype(np.float32)
    sem = np.where(on_road, RAW_ID["road"], RAW_ID["building"]).astype(np.uint32)
    return pts, sem


@pytest.fixture(scope="module")
def walls(tmp_path_factory):
    return write_scan(tmp_path_factory.mktemp("walls"), *walls_cloud())


@pytest.fixture(scope="module")
def scanner(walls) -> RealScanner:
    return RealScanner(load_sensor(SENSOR), (walls,))


def sample(walls, y: float = -12.0, **effects):
    """A sedan at x = 0, `y` m ahead (behind the sensor by default: out of view) on the walls
    scan, with the given effect dims."""
    dims = {"car_model": {"values": ["sedan"]}, "x": {"values": [0.0]}, "y": {"values": [y]},
            "yaw": {"values": [0.0]}, "background": {"real": [str(walls.bin)]}}
    dims.update({k: {"values": [v]} for k, v in effects.items()})
    return parse_space({"sensor": SENSOR, "dims": dims}, real_backgrounds=(walls,)).grid()[0]


def same(a, b) -> bool:
    return (a.image.tobytes() == b.image.tobytes() and a.instance.tobytes() == b.instance.tobytes()
            and a.semantic.tobytes() == b.semantic.tobytes())


def floor_of_the_return_model() -> float:
    """The detection floor from the fitted model's numbers: the darkest reflectivity at the
    sensor's 120 m, 88 deg from the normal, over 120^2."""
    p = json.loads(config_path("configs/returns/kitti-hdl64e.json").read_text())["params"]
    dark = min(p["reflectivity"].values())
    return (dark * math.cos(math.radians(88.0)) ** p["cos_exp"] * math.exp(-120.0 / p["atten_m"])
            / 120.0 ** 2)


# -- fog against its formulas -----------------------------------------------------------------
@pytest.mark.parametrize("visibility", [50.0, 300.0])
def test_fog_attenuates_each_recorded_return_by_its_formula(scanner, walls, visibility):
    clear = scanner.scan(sample(walls))
    fog = scanner.scan(sample(walls, fog=visibility))
    alpha = math.log(20.0) / visibility
    beta = 0.046 / visibility
    soft_r, soft_v = reference_peak(alpha)
    soft_p = math.pi * beta * soft_v / 1e-6
    floor = floor_of_the_return_model()
    r = clear.image[..., 4].astype(np.float64)
    i = clear.image[..., 3].astype(np.float64)
    decided = np.where(i > 0, i, 0.005)   # a stored 0 taken as half of KITTI's 0.01 step
    power = decided * np.exp(-2 * alpha * r) / np.where(clear.valid, r, 1.0) ** 2
    kept = fog.valid & (fog.image[..., 0:3] == clear.image[..., 0:3]).all(axis=-1)
    want = clear.valid & (power >= floor) & (power >= soft_p)
    wall = clear.valid & (clear.semantic == RAW_ID["building"])
    assert (kept[wall] == want[wall]).all()          # walls: far from either threshold
    assert (kept == want).mean() > 0.999             # the road: a few at a float32 edge
    # A kept return's received power fell by exactly exp(-2 alpha R): its range is unchanged,
    # its intensity is the recorded one times the factor (a stored 0 stays 0).
    np.testing.assert_allclose(fog.image[..., 3][kept], (i * np.exp(-2 * alpha * r))[kept],
                               rtol=1e-6, atol=0)
    assert (fog.label[kept] == clear.label[kept]).all()
    # The lost ones are gone, or hold the fog's soft echo: near, faint, unlabelled.
    soft = fog.valid & ~kept
    if soft_p >= floor:
        assert soft.sum() > 1000
        np.testing.assert_allclose(fog.image[..., 4][soft], soft_r, rtol=2e-3)
        assert (fog.label[soft] == 0).all() and (fog.semantic[soft] == 0).all()
        assert (fog.instance[soft] == 0).all()
        np.testing.assert_allclose(fog.image[..., 3][soft], soft_p * soft_r ** 2, rtol=2e-3)
    else:
        assert soft.sum() == 0
    dark = clear.valid & (i == 0)
    if visibility == 50.0:   # dense: the walls at 40 and 80 m are gone, the one at 10 m stays
        assert kept[wall & (r > 30)].sum() == 0 and kept[wall & (r < 11) & ~dark].all()
    else:                    # light: every near return stays, the dark ones too
        assert kept[clear.valid & (r < 11)].all() and dark[kept].sum() > 100
        assert kept[wall & ~dark].all()


def test_the_inserted_cars_returns_are_attenuated_too(scanner, walls):
    clear = scanner.scan(sample(walls, y=12.0))
    fog = scanner.scan(sample(walls, y=12.0, fog=300.0))
    car = clear.instance >= INSERTED_INSTANCE
    assert car.sum() > 300 and (fog.instance[car] == clear.instance[car]).all()
    r = clear.image[..., 4][car].astype(np.float64)
    np.testing.assert_allclose(fog.image[..., 3][car], clear.image[..., 3][car]
                               * np.exp(-2 * math.log(20.0) / 300.0 * r), rtol=1e-6)


# -- zero severity, every dim, seeds ----------------------------------------------------------
SUPPORTED = {"fog": 40.0, "rain": 30.0, "snow": 3.0, "wet_road": 2.0, "beam_loss": 6,
             "beams": 32, "crosstalk": 300}


def generator(seed: int | None) -> np.random.Generator | None:
    return None if seed is None else np.random.default_rng(seed)


def test_zero_severity_keeps_the_scans_bytes(scanner, walls):
    for y in (-12.0, 12.0):
        for seed in (None, 4):
            def rng(s=seed):
                return generator(s)
            plain = scanner.scan(sample(walls, y=y), rng=rng())
            for name in SUPPORTED:
                assert same(scanner.scan(sample(walls, y=y, **{name: 0.0}), rng=rng()), plain)
            zero = sample(walls, y=y, **{name: 0.0 for name in SUPPORTED})
            assert same(scanner.scan(zero, rng=rng()), plain)


@pytest.mark.parametrize("name", sorted(SUPPORTED))
def test_each_effect_dim_acts_on_a_real_background(tmp_path, scanner, walls, name):
    cfg = space_toml(tmp_path / "e.toml", str(walls.bin),
                     f"[dims.{name}]\nvalues = [0.0, {SUPPORTED[name]}]\n")
    space = load_space(cfg)
    assert name in space.dims and isinstance(scanner_for(space), RealScanner)
    clear = scanner.scan(sample(walls, y=12.0), rng=np.random.default_rng(2))
    got = scanner.scan(sample(walls, y=12.0, **{name: SUPPORTED[name]}),
                       rng=np.random.default_rng(2))
    changed = (got.image != clear.image).any(axis=-1)
    if name == "beam_loss":   # six whole rows emptied, every other row as it was
        rows = np.flatnonzero(~got.valid.any(axis=1) & clear.valid.any(axis=1))
        assert len(rows) == SUPPORTED[name]
        assert not changed[np.setdiff1d(np.arange(got.image.shape[0]), rows)].any()
    elif name == "beams":   # a 32-laser sensor: every other row as recorded, the rest empty
        kept = np.arange(0, got.image.shape[0], 2)
        assert not changed[kept].any()
        assert not got.valid[np.setdiff1d(np.arange(got.image.shape[0]), kept)].any()
        assert clear.valid[1::2].any()
    elif name == "crosstalk":   # points at random pixels, unlabelled; nothing else moved
        assert 0 < changed.sum() <= SUPPORTED[name]
        assert (got.label[changed] == 0).all() and got.valid[changed].all()
    elif name == "wet_road":   # road returns darker by the film's factor; the rest as it was
        road = clear.valid & (clear.semantic == RAW_ID["road"])
        assert not changed[~road].any()
        d = scanner.background(0).direction[road]
        factor = weather.wet_factor(np.abs(d[:, 2]), SUPPORTED[name],
                                    scanner.sim.weather.road_albedo)   # flat road: cos = |d_z|
        kept = got.valid[road]
        assert kept.mean() > 0.95 and factor.max() < 1.0
        np.testing.assert_allclose(got.image[..., 3][road][kept],
                                   (clear.image[..., 3][road] * factor)[kept], rtol=1e-3)
    else:   # the medium: returns lost or replaced by near spurious echoes
        assert changed.sum() > 50
        lost = clear.valid & ~(got.valid & (got.image[..., 4] == clear.image[..., 4]))
        assert lost.sum() > 50


def test_ego_speed_moves_each_return_as_on_our_streets(scanner, walls):
    """Each column fired from where the ego then is: a return on a wall facing the sensor (the
    walls here are spheres about it) comes nearer by the ego's step along its ray, as
    Weather.moving_ranges has it on a cast scan; the flat road's returns keep their range."""
    speed = 60.0
    clear = scanner.scan(sample(walls))
    moving = scanner.scan(sample(walls, ego_speed=speed))
    w = scanner.sim.weather
    step = speed * weather.KMH * w.column_time                       # (W,) m along +x
    u = scanner.sensor.directions
    r0, r1 = clear.image[..., 4].astype(np.float64), moving.image[..., 4].astype(np.float64)
    wall = clear.valid & (clear.semantic == RAW_ID["building"]) & moving.valid
    expected = r0 - u[..., 0] * step[None, :]
    assert np.abs(r1[wall] - expected[wall]).max() < 2e-3
    assert np.abs(r1[wall] - r0[wall]).max() > 0.05            # it moved at all
    road = clear.valid & (clear.semantic == RAW_ID["road"]) & moving.valid
    interior = road & np.roll(road, 1, 0) & np.roll(road, -1, 0) & np.roll(road, 1, 1) & \
        np.roll(road, -1, 1)
    assert np.abs(r1[interior] - r0[interior]).max() < 2e-3
    assert same(scanner.scan(sample(walls, ego_speed=0.0)), clear)


def test_spherical_images_are_refused_naming_the_dim(tmp_path, walls):
    sph = tmp_path / "sph.toml"
    sph.write_text('sensor = "semantickitti-hdl64e"\n' + space_toml(
        tmp_path / "x.toml", str(walls.bin), "[dims.rain]\nvalues = [5.0]\n").read_text())
    with pytest.raises(ConfigError, match=r"dims.rain: .*spherical image"):
        scanner_for(load_space(sph))


@pytest.mark.parametrize("name", ["fog", "rain", "snow", "crosstalk", "beam_loss"])
def test_the_same_sample_gives_the_same_bytes(walls, name):
    s = sample(walls, y=12.0, **{name: SUPPORTED[name]})
    a = RealScanner(load_sensor(SENSOR), (walls,)).scan(s, rng=np.random.default_rng(8))
    b = RealScanner(load_sensor(SENSOR), (walls,)).scan(s, rng=np.random.default_rng(8))
    assert same(a, b)
    if name != "fog":   # drawn effects: another generator state, other draws
        c = RealScanner(load_sensor(SENSOR), (walls,)).scan(s, rng=np.random.default_rng(9))
        assert not same(a, c)


# -- a grid run ---------------------------------------------------------------------------------
def test_a_fog_grid_on_a_real_background_stores_rows_for_each_visibility(tmp_path, walls):
    cfg = space_toml(tmp_path / "fog.toml", str(walls.bin), "[dims.fog]\nvalues = [0.0, 50.0]\n")
    out = tmp_path / "run"
    assert main(["grid", str(cfg), "--out", str(out), "--quiet", "--no-report"]) == 0
    frame = pd.read_csv(out / "results.csv")
    assert len(frame) == 8 and sorted(set(frame["fog"])) == [0.0, 50.0]
    assert frame["status"].isin(["ok", "undefined"]).all()
    assert frame["inserted_iou"].notna().all()
    by_fog = frame.groupby("fog")["inserted_iou"].mean()
    assert by_fog[50.0] < by_fog[0.0]   # the fog reached the scored scans
