"""Weather and sensor faults on the LiDAR (falsify.sensor.weather): the physics against its
formulas, severity against loss, zero severity against today's bytes, seeding, bad values, and
the effect dims in every sampler."""

from __future__ import annotations

import copy
import math

import numpy as np
import pandas as pd
import pytest
from scipy import integrate, optimize

from falsify.cli import main
from falsify.results.samples import sample_seed
from falsify.sensor import weather
from falsify.sensor.lidar import load_sensor
from falsify.sensor.simulator import Simulator
from falsify.sensor.weather import Effects, effects_of
from falsify.world.space import EFFECT_DIMS, Sample, parse_space

BASE = {"name": "w", "dims": {"car_model": {"values": ["sedan"]},
                              "x": {"values": [-2.0, 2.0]}, "y": {"values": [9.0, 13.0]},
                              "background": {"values": [1]}}}
C = weather.LIGHT_SPEED
TAU = weather.PULSE_HALF_POWER_S


@pytest.fixture(scope="module")
def sim() -> Simulator:
    # The material model, whose stored intensity is the power detection is decided on, so the
    # formulas read straight off the clear scan.
    return Simulator(load_sensor("kitti-hdl64e-front", returns="kitti-hdl64e"))


def space_with(**dims):
    raw = copy.deepcopy(BASE)
    raw["dims"].update(dims)
    return parse_space(raw)


def scan_of(sim: Simulator, sample: Sample, seed: int | None = 3):
    return sim.scan(sample, rng=None if seed is None else np.random.default_rng(seed))


def clear_and(sim: Simulator, fx: Effects, seed: int | None = None):
    """A clear scan and one with `fx` of the same scene, with the same generator seed."""
    space = space_with()
    s = space.grid()[0]
    placed, pose = sim.placed_cars(s), sim.ego_pose(s.background)
    rng = (lambda: None) if seed is None else (lambda: np.random.default_rng(seed))
    return (sim.render(s.background, placed, pose, rng()),
            sim.render(s.background, placed, pose, rng(), fx, 11))


# -- fog: the formulas ------------------------------------------------------------------------
def reference_integral(r: float, alpha: float, r0: float = math.inf) -> float:
    """Hahner et al. 2021's soft-target integral in the time variable, by adaptive quadrature."""
    def f(t: float) -> float:
        s = r - C * t / 2
        if s <= weather.OVERLAP_START_M or s > r0:
            return 0.0
        xi = min(1.0, (s - weather.OVERLAP_START_M)
                 / (weather.OVERLAP_FULL_M - weather.OVERLAP_START_M))
        return math.sin(math.pi * t / (2 * TAU)) ** 2 * xi * math.exp(-2 * alpha * s) / s ** 2
    stop = min(2 * TAU, 2 * (r - weather.OVERLAP_START_M) / C)
    if stop <= 0:
        return 0.0
    kinks = [x for x in (2 * (r - weather.OVERLAP_FULL_M) / C, 2 * (r - r0) / C) if 0 < x < stop]
    return integrate.quad(f, 0.0, stop, points=kinks or None, limit=400, epsabs=0.0,
                          epsrel=1e-12)[0]


def reference_peak(alpha: float, r0: float = math.inf) -> tuple[float, float]:
    """(reported range, integral) at the soft echo's maximum, found by a bounded minimiser."""
    grid = np.linspace(weather.OVERLAP_START_M, 12.0, 500)
    vals = [reference_integral(r, alpha, r0) for r in grid]
    k = int(np.argmax(vals))
    res = optimize.minimize_scalar(lambda r: -reference_integral(r, alpha, r0),
                                   bounds=(grid[max(k - 1, 0)], grid[k + 1]), method="bounded",
                                   options={"xatol": 1e-9})
    return res.x - C * TAU / 2, -res.fun


@pytest.mark.parametrize("visibility", [10.0, 50.0, 200.0, 1000.0])
def test_soft_return_range_matches_the_integral(visibility):
    alpha, _ = weather.fog_coefficients(visibility)
    assert alpha == pytest.approx(math.log(20) / visibility)
    r_fog, value = weather.fog_peak(alpha)
    want_r, want_v = reference_peak(alpha)
    assert r_fog == pytest.approx(want_r, rel=1e-3)
    assert value == pytest.approx(want_v, rel=1e-6)
    # The integral itself, anywhere on the pulse, with and without a target cutting the fog.
    for r in (1.0, 2.0, 4.6, 6.95, 9.0):
        for r0 in (math.inf, 3.0):
            got = weather.soft_integral(np.array([r]), alpha, r0)[0]
            assert got == pytest.approx(reference_integral(r, alpha, r0), rel=1e-9, abs=1e-22)


def test_soft_return_in_front_of_a_near_target():
    alpha, beta = weather.fog_coefficients(3.0)   # fog dense enough to beat a target at 2.5 m
    ranges, power = weather.soft_echo(alpha, beta, np.array([2.5, 3.5, np.inf]), np.zeros(3))
    for r0, got_r, got_p in zip((2.5, 3.5, math.inf), ranges, power, strict=True):
        want_r, want_v = reference_peak(alpha, r0)
        assert got_r == pytest.approx(want_r, rel=1e-3)
        assert got_p == pytest.approx(math.pi * beta * want_v / weather.FOG_GAMMA, rel=1e-5)


@pytest.mark.parametrize("visibility", [50.0, 200.0])
def test_fog_in_a_scan_follows_the_formulas_ray_by_ray(sim, visibility):
    """Every hard return keeps its range and has intensity I exp(-2 alpha R); it is kept exactly
    where its power I exp(-2 alpha R) / R^2 beats the fog's and reaches the floor; every other
    ray holds the soft return at R_fog (label 0) or nothing."""
    clear, fog = clear_and(sim, Effects(fog=visibility))
    alpha, beta = weather.fog_coefficients(visibility)
    want_r, want_v = reference_peak(alpha)
    soft_p = math.pi * beta * want_v / weather.FOG_GAMMA
    r, i = clear.image[..., 4].astype(np.float64), clear.image[..., 3].astype(np.float64)
    hard_p = np.where(clear.valid, i * np.exp(-2 * alpha * r) / np.maximum(r, 1e-9) ** 2, 0.0)
    kept = clear.valid & fog.valid & (np.abs(fog.image[..., 4] - clear.image[..., 4]) < 1e-4)
    assert kept.sum() > 5000
    np.testing.assert_allclose(fog.image[..., 3][kept], (i * np.exp(-2 * alpha * r))[kept],
                               rtol=0.01)
    # Which hard returns survive: decided by the formulas (a few at the float32 edge may differ).
    want_kept = clear.valid & (hard_p >= soft_p) & (hard_p >= sim.weather.floor)
    assert (kept == want_kept).mean() > 0.999
    assert (clear.valid & ~kept).sum() > 100          # fog removed some far returns
    soft = fog.valid & ~kept
    if soft_p >= sim.weather.floor:                   # dense fog: the soft echoes are seen
        assert soft.sum() > 1000
        np.testing.assert_allclose(fog.image[..., 4][soft], want_r, rtol=0.01)
        assert (fog.label[soft] == 0).all() and (fog.instance[soft] == 0).all()
        assert fog.image[..., 3][soft].max() < 1e-3   # faint
    else:
        assert soft.sum() == 0


# -- severity, zero severity, seeds -----------------------------------------------------------
SEVERITIES = {
    "fog": [0.0, 1000.0, 200.0, 100.0, 50.0, 20.0],   # visibility: smaller is worse
    "rain": [0.0, 5.0, 25.0, 100.0, 400.0],
    "snow": [0.0, 0.5, 2.0, 8.0, 30.0],
    "wet_road": [0.0, 0.3, 0.8, 2.0, 10.0],
    "beam_loss": [0, 1, 4, 16, 64],
    "beams": [0, 48, 32, 16, 8],     # lasers kept: fewer is worse
    "crosstalk": [0, 100, 1000, 5000, 20000],
    "ego_speed": [0.0, 20.0, 60.0, 150.0, 300.0],
}


def lost_share(clear, other) -> float:
    """The share of clear returns the other scan does not hold as they were."""
    same = (other.valid & (np.abs(other.image[..., 4] - clear.image[..., 4]) < 1e-3)
            & (other.label == clear.label))
    return float((clear.valid & ~same).sum() / clear.valid.sum())


@pytest.mark.parametrize("name", sorted(SEVERITIES))
def test_lost_share_grows_with_severity(sim, name):
    shares = []
    for value in SEVERITIES[name]:
        clear, other = clear_and(sim, Effects(**{name: value}), seed=5)
        shares.append(lost_share(clear, other))
    assert shares[0] == 0.0
    assert all(b >= a for a, b in zip(shares, shares[1:], strict=False)), shares
    assert shares[-1] > shares[1] and shares[-1] > 0.005, shares


def test_ego_motion_moves_points_by_the_sweep(sim):
    """At speed v each column's range changes by about v t_col along the ego's axis: a wall ahead
    nearer on the right (fired later), farther on the left, the ground unchanged."""
    clear, moving = clear_and(sim, Effects(ego_speed=100.0))
    both = clear.valid & moving.valid
    dr = (moving.image[..., 4] - clear.image[..., 4]).astype(np.float64)
    step = 100 / 3.6 * sim.weather.column_time                 # metres, per column
    ahead = both & (np.abs(clear.image[..., 1]) < 0.5 * clear.image[..., 0])
    ground = ahead & (clear.image[..., 2] < -1.5)               # flat road: no change
    assert np.abs(dr[ground]).mean() < 0.05
    assert np.abs(dr[both]).max() <= 5 * np.abs(step).max() + 1e-3
    assert np.abs(dr[both]).max() > 0.1


def test_zero_severity_is_todays_scan(sim):
    plain = space_with()
    zero = space_with(**{name: {"values": [0.0]} for name in EFFECT_DIMS})
    for a, b in zip(plain.grid(), zero.grid(), strict=True):
        assert effects_of(b).clear
        for seed in (None, 7):
            sa, sb = scan_of(sim, a, seed), scan_of(sim, b, seed)
            assert sa.image.tobytes() == sb.image.tobytes()
            assert sa.instance.tobytes() == sb.instance.tobytes()
    clear, same = clear_and(sim, Effects(), seed=4)
    assert clear.image.tobytes() == same.image.tobytes()


ONE_EACH = {"fog": 40.0, "rain": 30.0, "snow": 3.0, "wet_road": 2.0, "beam_loss": 6, "beams": 32,
            "crosstalk": 300, "ego_speed": 80.0}


@pytest.mark.parametrize("name", sorted(ONE_EACH))
def test_each_effect_is_seeded_by_its_sample(sim, name):
    space = space_with(**{name: {"values": [ONE_EACH[name]]}})
    a, b = space.grid()[:2]
    first = scan_of(sim, a, sample_seed(space, a))
    again = scan_of(sim, a, sample_seed(space, a))
    assert first.image.tobytes() == again.image.tobytes()
    assert first.instance.tobytes() == again.instance.tobytes()
    clear = scan_of(sim, Sample(tuple(v for v in a.values if v[0] != name)),
                    sample_seed(space, a))
    assert first.image.tobytes() != clear.image.tobytes()
    # Another sample: another scene and, for the drawn effects, other draws.
    other = scan_of(sim, b, sample_seed(space, b))
    assert other.image.tobytes() != first.image.tobytes()
    if name in ("rain", "snow", "crosstalk", "beam_loss"):
        fx = effects_of(a)
        _, x = clear_and(sim, fx, seed=sample_seed(space, a))
        _, y = clear_and(sim, fx, seed=sample_seed(space, b))   # same scene, other seed
        assert x.image.tobytes() != y.image.tobytes()


@pytest.mark.parametrize("beams, kept", [(32, np.arange(0, 64, 2)), (16, np.arange(0, 64, 4)),
                                         (48, np.setdiff1d(np.arange(64), np.arange(3, 64, 4)))])
def test_fewer_beams_keep_evenly_spaced_rows_of_the_same_scan(sim, beams, kept):
    """Robo3D's cross-sensor corruption: a 64-laser scan seen as a sensor of `beams` lasers keeps
    those rows as they were, and nothing of the others; as many lasers as rows change nothing."""
    clear, fewer = clear_and(sim, Effects(beams=beams), seed=6)
    assert np.array_equal(weather.kept_rows(64, beams), kept)
    assert fewer.image[kept].tobytes() == clear.image[kept].tobytes()
    gone = np.setdiff1d(np.arange(64), kept)
    assert not fewer.valid[gone].any() and (fewer.image[gone] == 0).all()
    _, all_rows = clear_and(sim, Effects(beams=64), seed=6)
    assert all_rows.image.tobytes() == clear.image.tobytes()


def test_effects_leave_the_scans_own_draws_alone(sim):
    """The effects read their seed from the generator without drawing from it: a clear scan's
    drop decisions are the same whether the generator was first seen by an effect or not."""
    rng = np.random.default_rng(9)
    before = rng.bit_generator.state
    weather.effect_seed(rng, 0)
    assert rng.bit_generator.state == before


# -- bad values and the samplers --------------------------------------------------------------
def write_config(path, extra: str, ys: str = "9.0, 13.0") -> str:
    path.write_text('name = "w"\nsensor = "kitti-hdl64e-front"\n'
                    '[dims.car_model]\nvalues = ["sedan"]\n[dims.x]\nvalues = [0.0]\n'
                    f'[dims.y]\nvalues = [{ys}]\n[dims.background]\nvalues = [1]\n' + extra)
    return str(path)


@pytest.mark.parametrize(("extra", "named"), [
    ("[dims.fog]\nvalues = [-5.0]\n", "dims.fog"),
    ("[dims.rain]\nvalues = [nan]\n", "dims.rain"),
    ("[dims.snow]\nmin = 0.0\nmax = 1000.0\nstep = 10.0\n", "dims.snow"),
    ("[dims.wet_road]\nvalues = [inf]\n", "dims.wet_road"),
    ("[dims.beam_loss]\nvalues = [2.5]\n", "dims.beam_loss"),
    ("[dims.beams]\nvalues = [200]\n", "dims.beams"),
    ("[dims.beams]\nvalues = [0, 48]\n", "dims.beams: 48 lasers do not divide"),
    ("[dims.beams]\nvalues = [48]\n", "dims.beams: 48 lasers do not divide"),
    ("[dims.beams]\nmin = 16\nmax = 64\nstep = 16\n", "dims.beams: give values"),
    ("[dims.crosstalk]\nvalues = [\"many\"]\n", "dims.crosstalk"),
    ("[dims.ego_speed]\nvalues = [-30.0]\n", "dims.ego_speed"),
    ("[dims.fogg]\nvalues = [50.0]\n", "dims.fogg"),
])
def test_bad_effect_values_exit_2_naming_the_dim(tmp_path, capsys, extra, named):
    cfg = write_config(tmp_path / "bad.toml", extra)
    assert main(["grid", cfg, "--out", str(tmp_path / "run"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert named in err, err
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("beams", [0, 32])
def test_one_beams_value_is_a_sensor_not_a_range(tmp_path, beams):
    """`values = [32]` reads as a fixed value (min = max): it runs every sample with 32 lasers."""
    cfg = write_config(tmp_path / "one.toml", f"[dims.beams]\nvalues = [{beams}]\n")
    assert main(["grid", cfg, "--out", str(tmp_path / "run"), "--quiet"]) == 0
    frame = pd.read_csv(tmp_path / "run" / "results.csv")
    assert list(frame["beams"]) == [beams, beams]


SEARCH_DIMS = (
    "[dims.fog]\nmin = 20.0\nmax = 1000.0\nstep = 10.0\n"
    "[dims.rain]\nmin = 0.0\nmax = 50.0\nstep = 5.0\n"
    "[dims.snow]\nmin = 0.0\nmax = 5.0\nstep = 1.0\n"
    "[dims.wet_road]\nmin = 0.0\nmax = 3.0\nstep = 1.0\n"
    "[dims.beam_loss]\nmin = 0\nmax = 16\nstep = 4\n"
    "[dims.beams]\nvalues = [16, 32, 64]\n"
    "[dims.crosstalk]\nmin = 0\nmax = 2000\nstep = 500\n"
    "[dims.ego_speed]\nmin = 0.0\nmax = 120.0\nstep = 30.0\n")


@pytest.mark.parametrize(("args", "rows"), [
    (["grid", "--max-samples", "8"], None),
    (["search", "--algorithm", "random", "--budget", "4"], 4),
    (["search", "--algorithm", "sobol", "--budget", "4"], 4),
    (["search", "--algorithm", "LN_COBYLA", "--budget", "27"], 27),   # 9 per beams value
])
def test_samplers_search_the_effect_dims(tmp_path, args, rows):
    if args[0] == "grid":   # a grid of 2 positions x 2 x 2 over two effect dims
        cfg = write_config(tmp_path / "w.toml", "[dims.fog]\nvalues = [0.0, 50.0]\n"
                           "[dims.beam_loss]\nmin = 0\nmax = 8\nstep = 8\n")
        cmd = ["grid", cfg, *args[1:]]
    else:
        # One position: NLopt's run per beams value walks the seven continuous effect dims
        # from the box's centre.
        cfg = write_config(tmp_path / "w.toml", SEARCH_DIMS, ys="9.0")
        cmd = ["search", cfg, *args[1:]]
    run = tmp_path / "run"
    assert main([*cmd, "--out", str(run), "--quiet", "--no-report"]) == 0
    frame = pd.read_csv(run / "results.csv")
    if rows is None:
        assert len(frame) == 8
        assert sorted(set(frame["fog"])) == [0.0, 50.0]
        assert sorted(set(frame["beam_loss"])) == [0.0, 8.0]
        return
    assert len(frame) == rows
    for name in EFFECT_DIMS:
        lo, hi = (0.0, 1000.0) if name == "fog" else (0.0, None)
        col = frame[name].astype(float)
        assert col.min() >= (20.0 if name == "fog" else lo) - 1e-9
        if hi is not None:
            assert col.max() <= hi + 1e-9
        assert col.nunique() > 1, name   # the sampler moved along every effect dim
    assert set(frame["beams"]) <= {16, 32, 64}   # lasers that divide the sensor's 64
    assert frame["status"].isin(["ok", "undefined"]).all()


def test_effect_dims_in_the_space():
    space = space_with(fog={"values": [0.0, 50.0]}, beam_loss={"min": 0, "max": 8, "step": 4},
                       colour={"values": ["red", "white"]})
    clear, foggy = space.make({"fog": "0"}), space.make({"fog": "50", "beam_loss": 3.6})
    assert foggy["fog"] == 50.0 and effects_of(foggy) == Effects(fog=50.0, beam_loss=4)
    assert clear.scene_key() != foggy.scene_key()      # the scan depends on the effects
    assert clear.scene_key() == space.make({"fog": 0.0, "colour": "white"}).scene_key()
    drawn = {weather.draw_effects(space, np.random.default_rng(k)) for k in range(20)}
    assert {d.fog for d in drawn} == {0.0, 50.0}
    assert all(0 <= d.beam_loss <= 8 for d in drawn) and len({d.beam_loss for d in drawn}) > 2


def test_dataset_draws_the_spaces_weather_and_clear_sets_keep_their_bytes(tmp_path):
    """Training scans of a space with effect dims are in that weather (seeded, recorded in
    index.json); a space without them writes the same bytes as no space at all."""
    import json

    from falsify.cli import main
    from falsify.data.training import TrafficOptions, write_dataset
    from falsify.sensor.lidar import load_sensor
    from falsify.world.space import parse_space

    dims = {"car_model": {"values": ["sedan"]}, "x": {"values": [0.0]},
            "y": {"values": [10.0]}, "background": {"values": [0]}}
    clear = parse_space({"dims": dims})
    foggy = parse_space({"dims": {**dims, "fog": {"values": [30.0]}}})
    sensor = load_sensor("kitti-hdl64e-front")
    opts = TrafficOptions(first_background=1000)
    outs = {name: tmp_path / name for name in ("none", "clear", "foggy", "foggy2")}
    for name, space in (("none", None), ("clear", clear), ("foggy", foggy), ("foggy2", foggy)):
        write_dataset(sensor, outs[name], 3, seed=0, opts=opts, weather=space)
    for i in range(3):
        f = f"{i:06d}.npy"
        assert (outs["none"] / f).read_bytes() == (outs["clear"] / f).read_bytes()
        assert (outs["foggy"] / f).read_bytes() == (outs["foggy2"] / f).read_bytes()
        c, g = np.load(outs["clear"] / f), np.load(outs["foggy"] / f)
        # Dense fog: far returns gone, near soft returns added.
        assert g[..., 4].max() < c[..., 4].max() and (g[..., 4] > 0).sum() != (c[..., 4] > 0).sum()
    drawn = json.loads((outs["foggy"] / "index.json").read_text())["effects"]["fog"]
    assert drawn in ({"values": [30.0]}, {"min": 30.0, "max": 30.0})
    assert (outs["none"] / "index.json").read_bytes() == (outs["clear"] / "index.json").read_bytes()
    cfg = tmp_path / "foggy.toml"
    cfg.write_text('[dims.car_model]\nvalues = ["sedan"]\n[dims.x]\nvalues = [0.0]\n'
                   '[dims.y]\nvalues = [10.0]\n[dims.background]\nvalues = [0]\n'
                   '[dims.fog]\nvalues = [30.0]\n')
    assert main(["dataset", str(cfg), "--out", str(tmp_path / "cli"), "--scans", "1",
                 "--first-background", "1000", "--json"]) == 0
    assert json.loads((tmp_path / "cli" / "index.json").read_text())["effects"]["fog"]
