"""The per-class return model: its copula keeps each class's fitted distribution, its fit
recovers what it is built from, and `fit-returns --labelled` fits only labelled fit scans."""

from __future__ import annotations

import json

import numpy as np
import pytest

from falsify.cli import main
from falsify.errors import ConfigError
from falsify.jobs.fit_returns import _instance_share, within_class_slopes
from falsify.paths import RETURN_MODELS
from falsify.semantic import RAW_ID, TRAIN_CLASSES, TRAIN_ID
from falsify.sensor.lidar import load_sensor
from falsify.sensor.returns import ClassReturns, load_return_model, side_generator
from falsify.sensor.scanner import PlacedCar
from falsify.sensor.simulator import Simulator
from tests.conftest import CONFIGS, HOLDOUT, MINI

Z = tuple(float(z) for z in np.linspace(-3.0, 3.0, 25))


def linear_classes(share: float) -> ClassReturns:
    """Every class's reflectivity 0.5 + 0.1 z: its median 0.5, its quartiles 0.5 -+ 0.0674."""
    n = len(TRAIN_CLASSES)
    row = tuple(0.5 + 0.1 * z for z in Z)
    return ClassReturns(z=Z, reflectivity=(row,) * n, instance_share=(share,) * n,
                        p_return=(0.9,) * n)


def test_the_table_is_read_linearly_and_held_at_its_ends():
    c = linear_classes(0.0)
    train = np.full(5, TRAIN_ID["car"])
    z = np.array([-9.0, -3.0, 0.1, 3.0, 1e30], np.float32)
    np.testing.assert_allclose(c.reflectivity_at(train, z), [0.2, 0.2, 0.51, 0.8, 0.8], atol=1e-5)
    no_draws = c.shades(train, np.arange(5), None)            # no draws: each class's median
    np.testing.assert_allclose(no_draws, 0.5, atol=1e-6)


def test_without_draws_each_hit_gets_the_fitted_class_table_at_score_zero():
    """The no-draw shade is a per-class lookup; it must be the table read at z = 0, bit for bit,
    for every class of the shipped model (the bench and unseeded scans take this path)."""
    c = load_return_model("semantickitti-fit").classes
    n = len(TRAIN_CLASSES)
    train = np.repeat(np.arange(n, dtype=np.int32), 3)
    want = c.reflectivity_at(train, np.zeros(len(train), np.float32))
    got = c.shades(train, np.arange(len(train)), None)
    assert got.dtype == np.float32 and got.tobytes() == want.tobytes()
    assert len(np.unique(got)) > 5   # classes differ: the lookup is indexed by class


@pytest.mark.parametrize("share", [0.0, 0.5, 0.9])
def test_the_copula_keeps_each_class_marginal_whatever_the_share(share):
    c = linear_classes(share)
    n = 200_000
    train = np.full(n, TRAIN_ID["car"])
    inst = np.arange(n) // 20 + 1                              # 10,000 cars of 20 points
    refl = c.shades(train, inst, np.random.default_rng(0))
    q25, q50, q75 = np.quantile(refl, [0.25, 0.5, 0.75])
    assert q50 == pytest.approx(0.5, abs=0.003)
    assert q75 - q25 == pytest.approx(2 * 0.1 * 0.6745, abs=0.004)
    per_car = refl.reshape(-1, 20)                             # and the share lies between cars
    between = per_car.mean(axis=1).var() / refl.var()
    assert between == pytest.approx(share + (1 - share) / 20, abs=0.03)


def test_stuff_without_an_instance_draws_per_point_only():
    c = linear_classes(0.9)
    train = np.full(100_000, TRAIN_ID["road"])
    refl = c.shades(train, np.zeros(100_000, np.int64), np.random.default_rng(1))
    assert np.std(refl) == pytest.approx(0.1, rel=0.03)        # the full spread, not sqrt(0.1)


@pytest.mark.parametrize("share", [0.0, 0.3, 0.7])
def test_the_instance_share_is_recovered_from_known_draws(share):
    rng = np.random.default_rng(2)
    sizes = rng.integers(20, 400, 300)
    key = np.repeat(np.arange(300), sizes)
    z = np.sqrt(share) * rng.standard_normal(300)[key] + np.sqrt(1 - share) * \
        rng.standard_normal(len(key))
    assert _instance_share(z, key) == pytest.approx(share, abs=0.07)
    assert _instance_share(z, np.full(len(key), -1)) == 0.0    # no instance: nothing between


def test_within_class_slopes_are_those_of_the_whole_design_matrix():
    """Frisch-Waugh-Lovell: the gain fit's slopes from class-centred columns equal least
    squares on one dummy column a class plus the columns, with a class of one point and class
    ids that skip some (absent classes), and scales as far apart as log cos and range."""
    rng = np.random.default_rng(3)
    cls = np.concatenate([rng.choice([0, 2, 5, 9], 4000), [7]]).astype(np.uint8)
    x = (np.log(rng.uniform(0.05, 1.0, len(cls))), -rng.uniform(1.0, 60.0, len(cls)))
    y = (np.array([0.3, 0, -1.2, 0, 0, 0.8, 0, 2.0, 0, -0.4])[cls] + 0.7 * x[0] + 0.013 * x[1]
         + rng.normal(0, 0.2, len(cls)))
    present = np.unique(cls)
    design = np.column_stack([(cls[:, None] == present).astype(np.float64), *x])
    want = np.linalg.lstsq(design, y, rcond=None)[0][-2:]
    got = within_class_slopes(cls, tuple(v.copy() for v in x), y.copy())
    np.testing.assert_allclose(got, want, rtol=1e-10)
    assert got[0] == pytest.approx(0.7, abs=0.02) and got[1] == pytest.approx(0.013, abs=1e-3)
    # at the extremes: no point, or a column constant within every class, gives finite slopes
    empty = np.zeros(0)
    assert within_class_slopes(np.zeros(0, np.uint8), (empty.copy(), empty.copy()),
                               empty.copy()).tolist() == [0.0, 0.0]
    flat = within_class_slopes(cls, (x[0].copy(), np.full(len(cls), -30.0)), y.copy())
    assert np.isfinite(flat).all() and flat[1] == pytest.approx(0.0, abs=1e-12)


def test_the_shipped_model_loads_with_a_table_per_class():
    m = load_return_model("semantickitti-fit")
    doc = json.loads((RETURN_MODELS / "semantickitti-fit.json").read_text())
    assert "--labelled" in doc["command"] and "--holdout" in doc["command"]
    assert m.classes is not None and len(m.classes.reflectivity) == len(TRAIN_CLASSES)
    for row in m.classes.reflectivity:                          # quantile functions rise
        assert np.all(np.diff(row) >= 0)
    assert all(0.5 < p <= 1.0 for p in m.classes.p_return)
    # What the real fit scans show: cars return far darker than the road they stand on.
    med = len(m.classes.z) // 2
    assert m.classes.reflectivity[TRAIN_ID["car"]][med] < 0.5 * \
        m.classes.reflectivity[TRAIN_ID["road"]][med]


def test_streets_render_each_class_with_its_fitted_spread_and_the_same_bytes_again():
    sensor = load_sensor("kitti-hdl64e-front", returns="semantickitti-fit")
    sim = Simulator(sensor)
    car = sim.settle(2, PlacedCar("sedan", 10.0, 0.0, 0.0, 1))
    a = sim.render(2, [car], sim.ego_pose(2), np.random.default_rng(3))
    b = Simulator(sensor).render(2, [car], sim.ego_pose(2), np.random.default_rng(3))
    assert a.image.tobytes() == b.image.tobytes()
    inten, sem = a.image[..., 3][a.valid], a.semantic[a.valid]
    assert inten.min() >= 0.0 and inten.max() <= 1.0
    road, cars = inten[sem == RAW_ID["road"]], inten[sem == RAW_ID["car"]]
    assert np.median(cars) < np.median(road)
    q10, q90 = np.quantile(road, [0.1, 0.9])
    assert q90 - q10 > 0.1                 # a spread, not the material level's thin band
    old = Simulator(load_sensor("kitti-hdl64e-front", returns="kitti-hdl64e"))
    c = old.render(2, [car], old.ego_pose(2), np.random.default_rng(3))
    r_old = c.image[..., 3][c.valid & (c.semantic == RAW_ID["road"])]
    assert np.subtract(*np.quantile(r_old, [0.9, 0.1])) < q90 - q10


@pytest.fixture
def mini():
    if not (MINI / "sequences").is_dir():
        pytest.skip(f"semantickitti-mini not found at {MINI}")
    return MINI


@pytest.mark.slow
def test_the_shipped_model_is_what_its_command_fits(mini, tmp_path, capsys):
    doc = json.loads((RETURN_MODELS / "semantickitti-fit.json").read_text())
    argv = doc["command"].replace("$SEMANTICKITTI", str(mini)).split()[1:]
    out = tmp_path / "semantickitti-fit.json"
    argv[argv.index("--out") + 1] = str(out)
    argv[argv.index("--holdout") + 1] = str(HOLDOUT)
    assert main(argv) == 0
    capsys.readouterr()
    # To 1e-9: the fit's least squares round differently across numpy/scipy builds (seen: the
    # 14th digit of atten_m), and nothing downstream reads that far.
    fitted, shipped = _leaves(json.loads(out.read_text())["params"]), _leaves(doc["params"])
    assert fitted.keys() == shipped.keys()
    assert {k: (fitted[k], v) for k, v in shipped.items()
            if fitted[k] != (pytest.approx(v, rel=1e-9, abs=1e-12) if isinstance(v, float)
                             else v)} == {}


def _leaves(doc, path: str = "") -> dict:
    """Every leaf of a JSON document by its path."""
    if isinstance(doc, dict):
        return {k: v for key, val in doc.items() for k, v in _leaves(val, f"{path}/{key}").items()}
    if isinstance(doc, list):
        return {k: v for i, val in enumerate(doc) for k, v in _leaves(val, f"{path}/{i}").items()}
    return {path: doc}


def test_labelled_fit_refuses_held_out_and_unlabelled_scans(mini, tmp_path, capsys):
    out = tmp_path / "r.json"
    assert main(["fit-returns", "--labelled", str(mini), "--sequences", "00", "--holdout",
                 str(HOLDOUT), "--out", str(out)]) == 2
    assert "held-out scan" in capsys.readouterr().err and not out.exists()
    bare = tmp_path / "scans" / "000000.bin"
    bare.parent.mkdir()
    bare.write_bytes((mini / "sequences" / "01" / "velodyne").glob("*.bin").__next__()
                     .read_bytes())
    assert main(["fit-returns", "--labelled", str(bare), "--out", str(out)]) == 2
    assert "000000.bin: no SemanticKITTI .label" in capsys.readouterr().err and not out.exists()
    assert main(["fit-returns", str(bare), "--sequences", "01", "--out", str(out)]) == 2
    assert "--sequences: only with --labelled" in capsys.readouterr().err
    # a copy of a fit scan under another name would weigh it twice in the fit
    seq = mini / "sequences" / "01"
    copy = tmp_path / "copy" / "01"
    for sub, suffix in (("velodyne", ".bin"), ("labels", ".label")):
        (copy / sub).mkdir(parents=True)
        first = sorted((seq / sub).glob(f"*{suffix}"))[0]
        (copy / sub / f"999999{suffix}").write_bytes(first.read_bytes())
    assert main(["fit-returns", "--labelled", str(seq), str(copy), "--out", str(out)]) == 2
    assert "999999.bin: the same bytes as" in capsys.readouterr().err and not out.exists()


def test_labelled_fit_writes_a_model_the_sensor_reads(mini, tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("SEMANTICKITTI", str(mini))
    out = tmp_path / "mine.json"
    assert main(["fit-returns", "--labelled", str(mini), "--sequences", "01", "--out", str(out),
                 "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["classes"]["road"]["points"] > 10_000
    assert json.loads(out.read_text())["name"] == "mine"
    # the command as run, the data root written as its variable
    want = f"falsify fit-returns --labelled $SEMANTICKITTI --sequences 01 --out {out}"
    assert json.loads(out.read_text())["command"] == want
    # A sensor names the file beside its TOML; the scans then carry its classes' shades.
    toml = (CONFIGS / "sensors" / "kitti-hdl64e-front.toml").read_text()
    mine = tmp_path / "mine.toml"
    mine.write_text(toml.replace('returns = "semantickitti-fit"', 'returns = "mine.json"'))
    sensor = load_sensor(mine)
    assert sensor.returns == str(out.resolve())
    sim = Simulator(sensor)
    assert sim.returns.classes is not None and sim.returns.name == "mine"
    broken = tmp_path / "broken.json"
    broken.write_text('{"params": {"classes": {}}}')
    mine.write_text(toml.replace('returns = "semantickitti-fit"', 'returns = "broken.json"'))
    with pytest.raises(ConfigError, match=r"returns: .*broken.json is not a return model"):
        load_sensor(mine)
    mine.write_text(toml.replace('returns = "semantickitti-fit"', 'returns = "gone.json"'))
    with pytest.raises(ConfigError, match=r"returns: cannot read .*gone.json"):
        load_sensor(mine)


def test_shades_leave_the_scans_own_draws_alone():
    a, b = np.random.default_rng(5), np.random.default_rng(5)
    side = side_generator(a).random(4)
    assert (a.random(8) == b.random(8)).all()                  # not one draw taken
    assert (side_generator(np.random.default_rng(5)).random(4) == side).all()
    assert not (side_generator(np.random.default_rng(6)).random(4) == side).any()


def test_a_labelled_fit_can_drop_as_another_model_does(mini, tmp_path, capsys):
    out = tmp_path / "shades.json"
    assert main(["fit-returns", "--labelled", str(mini), "--sequences", "02", "--dropout-from",
                 "kitti-hdl64e", "--out", str(out)]) == 0
    capsys.readouterr()
    doc, r0 = json.loads(out.read_text()), load_return_model("kitti-hdl64e")
    assert doc["params"]["classes"]["dropout"] == "intensity"
    assert "--dropout-from kitti-hdl64e" in doc["command"]
    mine = load_return_model(str(out))
    assert mine.row_keep == r0.row_keep and mine.blocked == r0.blocked
    i = np.linspace(0.0, 1.0, 11, dtype=np.float32)
    sem = np.full(11, RAW_ID["car"])
    np.testing.assert_array_equal(mine.return_probability(i, sem), r0.p_return(i))
    assert main(["fit-returns", "--labelled", str(mini), "--sequences", "02", "--dropout-from",
                 "nope", "--out", str(tmp_path / "x.json")]) == 2
    err = capsys.readouterr().err
    assert "--dropout-from: returns: 'nope' is not a fitted return model" in err
    assert "kitti-hdl64e" in err and not (tmp_path / "x.json").exists()


def test_thin_fog_keeps_every_near_return_however_dark_its_class_shade():
    """Detection is decided on the material's power: a dark class shade is a stored remission,
    and its echo reached the floor in clear air (as a real scan's recorded return did)."""
    from falsify.sensor.weather import Effects
    from tests.sensor.test_weather import clear_and

    sim = Simulator(load_sensor("kitti-hdl64e-front"))      # the presets shade by class
    assert sim.returns.classes is not None
    clear, fog = clear_and(sim, Effects(fog=2000.0), seed=4)
    near = clear.valid & (clear.image[..., 4] < 40.0)
    assert (clear.image[..., 3][near] < 0.02).sum() > 50      # dark shades are drawn
    assert fog.valid[near].all()


def test_class_intensity_stays_finite_and_in_range_at_the_extremes():
    m = load_return_model("semantickitti-fit")
    cos = np.array([0.0, 1e-12, 1.0, 1.0, 1.0], np.float32)
    rng = np.array([1.0, 1.0, 0.0, 1e6, 1e-9], np.float32)
    sem = np.full(5, RAW_ID["traffic-sign"])
    out = m.intensity(np.zeros(5, np.int64), cos, rng, sem, np.zeros(5, np.int64),
                      np.random.default_rng(0))
    assert np.isfinite(out).all() and out.min() >= 0.0 and out.max() <= 1.0
    assert out[0] == 0.0 and out[3] == 0.0          # grazing and far: nothing comes back
