"""The sensor and weather physics against hand computations of their published equations, and the
scan at the extremes of every effect and sensor value a config may hold: finite, inside the
sensor's ranges, the same bytes twice, and bad values a clear exit 2."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from scipy import integrate

from falsify.cli import main
from falsify.errors import ConfigError
from falsify.paths import RETURN_MODELS
from falsify.sensor.lidar import load_sensor, parse_sensor
from falsify.sensor.returns import load_return_model
from falsify.sensor.simulator import Simulator
from falsify.sensor.weather import Effects, fresnel, wet_factor
from falsify.sensor.weather.ego_motion import moving_ranges
from falsify.sensor.weather.rain import rain
from falsify.sensor.weather.snow import snow
from falsify.sensor.weather.wet_road import INTERNAL_REFLECTANCE
from falsify.world.space import parse_space

RING = {"name": "t", "vertical": {"up_deg": 2.0, "down_deg": -24.0, "beams": 8},
        "columns": 36}


# -- rain and snow: extinction from the size distribution ---------------------------------------
def extinction_by_quadrature(n0: float, lam: float, grow: float) -> float:
    """2 int pi (g D)^2 / 4 N0 exp(-lam D) dD over D in mm, in 1/m (geometric optics, extinction
    efficiency 2: van de Hulst 1957), integrated numerically rather than in closed form."""
    f = lambda d: 2.0 * math.pi * (grow * d) ** 2 / 4.0 * n0 * math.exp(-lam * d)  # noqa: E731
    return integrate.quad(f, 0.0, math.inf, epsrel=1e-12)[0] * 1e-6


@pytest.mark.parametrize("rate", [0.5, 1.0, 10.0, 100.0, 500.0])
def test_rain_extinction_is_marshall_palmers(rate):
    """Marshall and Palmer (1948): N0 = 8000 m^-3 mm^-1, Lambda = 4.1 R^-0.21 mm^-1; the
    extinction this gives is the familiar 0.365 R^0.63 per km."""
    want = extinction_by_quadrature(8000.0, 4.1 * rate ** -0.21, 1.0)
    assert rain(rate).extinction == pytest.approx(want, rel=1e-9)
    assert rain(rate).extinction == pytest.approx(0.365e-3 * rate ** 0.63, rel=2e-3)


@pytest.mark.parametrize("rate", [0.1, 1.0, 10.0, 100.0])
def test_snow_extinction_is_gunn_marshalls(rate):
    """Gunn and Marshall (1958): N0 = 3800 S^-0.87 m^-3 mm^-1, Lambda = 2.55 S^-0.48 mm^-1 over
    melted diameters; a flake of density 0.1 is 10^(1/3) times wider than its drop."""
    want = extinction_by_quadrature(3800.0 * rate ** -0.87, 2.55 * rate ** -0.48,
                                    10.0 ** (1.0 / 3.0))
    assert snow(rate).extinction == pytest.approx(want, rel=1e-9)


def test_a_subnormal_rate_with_flush_to_zero_on_gives_a_finite_extinction():
    """Where a library has switched on flush-to-zero (torch does on request, and a test worker
    inherits it), 5e-324 mm/h reads as 0 and 0 ** -0.21 raised ZeroDivisionError; it failed
    only in a run whose earlier tests had switched it on."""
    torch = pytest.importorskip("torch")
    if not torch.set_flush_denormal(True):
        pytest.skip("this CPU cannot flush denormals")
    try:
        for p in (rain(5e-324), snow(5e-324)):
            assert math.isfinite(p.extinction) and p.extinction >= 0.0
    finally:
        torch.set_flush_denormal(False)


@pytest.mark.parametrize("rate", [1e-300, 5e-324, 1e-12])
def test_vanishing_rain_and_snow_rates_give_a_finite_extinction(rate):
    """Lambda^3 overflowed a float for a snow rate below 1e-213 mm/h (OverflowError: a config's
    `values = [1e-300, 1.0]` passes validation and crashed the scan)."""
    for p in (rain(rate), snow(rate)):
        assert math.isfinite(p.extinction) and 0.0 <= p.extinction < 1e-6
        assert p.hits_per_m == p.extinction / 2


# -- wet road: Fresnel and Lekner and Dorf ------------------------------------------------------
def test_fresnel_at_normal_incidence_and_beyond_the_critical_angle():
    n = 1.33
    assert fresnel(np.array([1.0]), n)[0] == pytest.approx(((n - 1) / (n + 1)) ** 2, rel=1e-12)
    critical = math.asin(1.0 / n)   # from water into air: total internal reflection beyond it
    inside = np.cos(np.array([critical - 1e-3, critical + 1e-3, 1.4]))
    got = fresnel(inside, 1.0 / n)
    assert got[0] < 1.0 and got[1] == 1.0 and got[2] == 1.0
    # Snell and the s-polarised amplitude ratio written out at 45 deg from air into water.
    ti = math.radians(45.0)
    tt = math.asin(math.sin(ti) / n)
    rs = (math.cos(ti) - n * math.cos(tt)) / (math.cos(ti) + n * math.cos(tt))
    rp = (n * math.cos(ti) - math.cos(tt)) / (n * math.cos(ti) + math.cos(tt))
    assert fresnel(np.array([math.cos(ti)]), n)[0] == pytest.approx((rs ** 2 + rp ** 2) / 2,
                                                                    rel=1e-12)


def test_internal_diffuse_reflectance_obeys_the_reciprocity_relation():
    """Lekner and Dorf's r-bar for diffuse light inside water: by reciprocity (radiance / n^2
    is conserved) 1 - r_inside = (1 - r_outside) / n^2, r_outside being diffuse light from air."""
    n = 1.33
    r_out = integrate.quad(lambda t: fresnel(np.array([math.cos(t)]), n)[0] * math.sin(2 * t),
                           0.0, math.pi / 2, epsrel=1e-12)[0]
    assert INTERNAL_REFLECTANCE == pytest.approx(1.0 - (1.0 - r_out) / n ** 2, abs=1e-6)
    assert 0.45 < INTERNAL_REFLECTANCE < 0.5


def test_wet_factor_at_normal_incidence_by_hand():
    """A film over the whole texture, looked at straight down: transmitted in and out
    ((1 - R0)^2), radiance / n^2 on the way out, 1 / (1 - albedo r-bar) from the light trapped
    under the surface, and 6.7 / m absorption over twice the film."""
    n, film, albedo = 1.33, 2.0, 0.3
    r0 = ((n - 1) / (n + 1)) ** 2
    want = ((1 - r0) ** 2 / n ** 2 / (1 - albedo * INTERNAL_REFLECTANCE)
            * math.exp(-2 * 6.7 * film * 1e-3))
    assert wet_factor(np.array([1.0]), film, albedo)[0] == pytest.approx(want, rel=1e-9)
    assert wet_factor(np.array([1.0]), 0.0, albedo)[0] == 1.0   # no water: the dry road


# -- ego motion -----------------------------------------------------------------------------------
def test_moving_ranges_to_a_wall_and_a_tilted_plane_by_hand():
    """A wall 20 m ahead (normal turned to the sensor, -x): fired t s later at v m/s the range is
    20 - v t. A plane at 60 deg to the ray: the ray from the moved origin meets it at
    R - (n . d) / (n . u), written out with the plane's own equation."""
    v_kmh, t = 72.0, 0.05                 # 20 m/s, 1 m
    fwd = np.array([1.0, 0.0, 0.0])
    got = moving_ranges(np.array([[20.0]]), np.array([[[-1.0, 0.0, 0.0]]]), np.array([[1.0]]),
                        v_kmh, np.array([t]), fwd)
    assert got[0, 0] == pytest.approx(19.0, abs=1e-12)
    u = np.array([math.cos(0.3), math.sin(0.3), 0.0])    # the ray
    p = 15.0 * u                                          # its clear hit
    nrm = np.array([-math.cos(0.3 + math.radians(30)), -math.sin(0.3 + math.radians(30)), 0.0])
    cos = -nrm @ u
    d = 20.0 * t * fwd
    s = (p - d) @ nrm / (u @ nrm)                         # (d + s u - p) . n = 0
    got = moving_ranges(np.array([[15.0]]), nrm[None, None], np.array([[cos]]), v_kmh,
                        np.array([t]), fwd)
    assert got[0, 0] == pytest.approx(s, rel=1e-12)


# -- the ring layout across +-180 deg ---------------------------------------------------------
@pytest.mark.parametrize("fov", [[270.0, 90.0], [200.0, -100.0], [-90.0, -270.0], [45.0, -45.0],
                                 [180.0, -180.0]])
def test_each_ray_projects_to_its_own_pixel(fov):
    """A sensor's own rays land in their own pixels, also where its field of view crosses
    +-180 deg (looking back): atan2 reports those azimuths a turn away, and half the rays of a
    [270, 90] sensor used to fall outside the image."""
    s = parse_sensor({**RING, "h_fov_deg": fov})
    row, col, inside = s.pixel_of(s.directions.reshape(-1, 3) * 10.0)
    want_row, want_col = np.divmod(np.arange(s.rows * s.columns), s.columns)
    assert inside.all()
    assert np.array_equal(row, want_row) and np.array_equal(col, want_col)
    # Just beyond either edge is outside (a field of view short of the full circle).
    if not s.full_circle:
        for az in (s.az_left_deg + 1.0, s.az_right_deg - 1.0):
            a = math.radians(az)
            assert not s.pixel_of(np.array([[math.cos(a), math.sin(a), 0.0]]))[2][0]


# -- bad values: exit 2, naming the key and what is allowed ------------------------------------
@pytest.mark.parametrize("value", [1e300, 1e39, 10_000.5])
def test_max_range_beyond_its_limit_is_a_config_error(tmp_path, capsys, value):
    """1e300 overflowed the detection floor (OverflowError on every scan) and 1e39 wrote inf
    into the float32 scan: max_range is bounded like every other sensor value."""
    with pytest.raises(ConfigError, match=r"max_range: .* must be <= 10000"):
        parse_sensor({**RING, "h_fov_deg": [180.0, -180.0], "max_range": value})
    assert parse_sensor({**RING, "h_fov_deg": [180.0, -180.0],
                         "max_range": 10_000.0}).max_range == 10_000.0
    sensor = tmp_path / "far.toml"
    sensor.write_text('name = "far"\nvertical = { up_deg = 2.0, down_deg = -24.0, beams = 8 }\n'
                      f'h_fov_deg = [180.0, -180.0]\ncolumns = 36\nmax_range = {value!r}\n')
    cfg = tmp_path / "c.toml"
    cfg.write_text(f'name = "c"\nsensor = "{sensor}"\n[dims.car_model]\nvalues = ["sedan"]\n'
                   '[dims.x]\nvalues = [0.0]\n[dims.y]\nvalues = [9.0]\n'
                   '[dims.background]\nvalues = [1]\n')
    assert main(["scan", str(cfg), "--out", str(tmp_path / "out")]) == 2
    assert "max_range" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize(("value", "message"), [
    (1e-300, "rotation_hz: 1e-300 must be >= 0.1"), (0.0, "must be >= 0.1"),
    (5000.0, "rotation_hz: 5000.0 must be <= 1000.0"),
])
def test_rotation_rate_out_of_its_bounds_is_a_config_error(value, message):
    """1e-300 Hz was accepted; with ego motion the sweep never ended and the scan was empty."""
    with pytest.raises(ConfigError, match=message):
        parse_sensor({**RING, "h_fov_deg": [180.0, -180.0], "rotation_hz": value})
    assert parse_sensor({**RING, "h_fov_deg": [180.0, -180.0], "rotation_hz": 20.0}
                        ).rotation_hz == 20.0


@pytest.mark.parametrize(("key", "value", "allowed"), [
    ("atten_m", 0.0, "> 0"), ("atten_m", float("nan"), "> 0"), ("i0", 0.0, "> 0"),
    ("k", -1.0, "> 0"), ("cos_exp", -0.5, ">= 0"), ("p_max", 2.0, "in [0, 1]"),
    ("reflectivity.dark", float("inf"), ">= 0"),
])
def test_bad_return_model_params_name_the_key(tmp_path, capsys, key, value, allowed):
    """A return model divides by atten_m and i0: 0 gave a ZeroDivisionError traceback, NaN a
    silently empty scan. Each param is checked where the file is read."""
    raw = json.loads((RETURN_MODELS / "kitti-hdl64e.json").read_text())
    if "." in key:
        table, level = key.split(".")
        raw["params"][table][level] = value
    else:
        raw["params"][key] = value
    model = tmp_path / "bad.json"
    model.write_text(json.dumps(raw))
    with pytest.raises(ConfigError, match=rf"params\.{key}: .*allowed: a finite number "
                                          + allowed.replace("[", r"\[").replace("]", r"\]")):
        load_return_model(str(model))
    sensor = tmp_path / "s.toml"
    sensor.write_text('name = "s"\nvertical = { up_deg = 2.0, down_deg = -24.0, beams = 8 }\n'
                      'h_fov_deg = [180.0, -180.0]\ncolumns = 36\nreturns = "bad.json"\n')
    cfg = tmp_path / "c.toml"
    cfg.write_text(f'name = "c"\nsensor = "{sensor}"\n[dims.car_model]\nvalues = ["sedan"]\n'
                   '[dims.x]\nvalues = [0.0]\n[dims.y]\nvalues = [9.0]\n'
                   '[dims.background]\nvalues = [1]\n')
    assert main(["scan", str(cfg), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert f"params.{key}" in err and "bad.json" in err
    assert not (tmp_path / "out").exists()


def test_shipped_return_models_pass_the_checks():
    paths = sorted(RETURN_MODELS.glob("*.json"))
    assert paths, f"no return model in {RETURN_MODELS}"   # an empty loop passes nothing
    for path in paths:
        load_return_model(path.stem)


# -- scans at every effect's extreme ------------------------------------------------------------
@pytest.fixture(scope="module")
def vlp16() -> Simulator:
    """A small sensor (16 x 1800) with a min_range (0.5 m) for spurious echoes to respect."""
    return Simulator(load_sensor("vlp16"))


EXTREMES = [Effects(fog=0.5), Effects(fog=5.0), Effects(fog=100_000.0),
            Effects(rain=1e-300), Effects(rain=500.0), Effects(snow=1e-300), Effects(snow=100.0),
            Effects(wet_road=20.0), Effects(crosstalk=100_000), Effects(ego_speed=300.0),
            Effects(beam_loss=128), Effects(beams=1),
            Effects(fog=20.0, rain=500.0, snow=100.0, wet_road=20.0, beam_loss=3, beams=8,
                    crosstalk=5000, ego_speed=300.0)]


@pytest.mark.parametrize("fx", EXTREMES, ids=lambda fx: ",".join(
    f"{k}={v:g}" for k, v in vars(fx).items() if v))
def test_extreme_effects_give_finite_scans_inside_the_sensors_ranges(vlp16, fx):
    """Every valid point finite and between min_range and max_range, every empty pixel zero, no
    floating-point warning, and the same bytes twice. A snow flake filling the beam inside
    min_range used to be reported there (ranges down to 3 mm on a 0.5 m sensor)."""
    space = parse_space({"dims": {"car_model": {"values": ["sedan"]}, "x": {"values": [0.0]},
                                  "y": {"values": [9.0]}, "background": {"values": [1]}}})
    s = space.grid()[0]
    placed, pose = vlp16.placed_cars(s), vlp16.ego_pose(s.background)
    with np.errstate(divide="raise", over="raise", invalid="raise"):
        a = vlp16.render(s.background, placed, pose, np.random.default_rng(3), fx, 11)
    b = vlp16.render(s.background, placed, pose, np.random.default_rng(3), fx, 11)
    assert a.image.tobytes() == b.image.tobytes() and a.instance.tobytes() == b.instance.tobytes()
    assert np.isfinite(a.image).all()
    r = a.image[..., 4][a.valid]
    sensor = vlp16.sensor
    assert (r >= sensor.min_range - 1e-4).all() and (r <= sensor.max_range + 1e-3).all()
    assert (a.image[~a.valid] == 0).all()


@pytest.mark.parametrize("fx", [Effects(rain=5.0), Effects(snow=5.0, wet_road=1.0),
                                Effects(fog=50.0)], ids=["rain", "snow", "fog"])
def test_a_zero_detection_floor_reports_no_miss(tmp_path, fx):
    """A return model whose darkest level is 0 makes the detection floor 0: every ray's power,
    0 on a miss, reached it, and the misses were written at range inf (inf and NaN in the
    scan). An echo needs power above 0."""
    raw = json.loads((RETURN_MODELS / "kitti-hdl64e.json").read_text())
    raw["params"]["reflectivity"]["dark"] = 0.0
    (tmp_path / "dark.json").write_text(json.dumps(raw))
    (tmp_path / "s.toml").write_text(
        'name = "s"\nvertical = { up_deg = 2.0, down_deg = -24.0, beams = 8 }\n'
        'h_fov_deg = [180.0, -180.0]\ncolumns = 64\nreturns = "dark.json"\n')
    sim = Simulator(load_sensor(str(tmp_path / "s.toml")))
    assert sim.weather.floor == 0.0
    space = parse_space({"dims": {"car_model": {"values": ["sedan"]}, "x": {"values": [0.0]},
                                  "y": {"values": [9.0]}, "background": {"values": [1]}}})
    s = space.grid()[0]
    scan = sim.render(s.background, sim.placed_cars(s), sim.ego_pose(s.background),
                      np.random.default_rng(3), fx, 11)
    assert np.isfinite(scan.image).all()
    assert (scan.image[..., 4][scan.valid] <= sim.sensor.max_range + 1e-3).all()
