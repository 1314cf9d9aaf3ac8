"""Modification-space configs: the bundled ones, the grid, and a clear error for every bad key."""

from __future__ import annotations

import copy

import pytest

from falsify.errors import ConfigError
from falsify.world.space import Continuous, load_space, parse_space
from tests.conftest import CONFIGS

BASE = {"name": "t", "dims": {"car_model": {"values": ["sedan"]},
                              "x": {"min": -1.0, "max": 1.0, "step": 1.0},
                              "y": {"min": 5.0, "max": 6.0, "step": 1.0},
                              "background": {"values": [0, 1]}}}


def test_paper_config_is_the_papers_space():
    space = load_space(CONFIGS / "paper.toml")
    assert space.dims["x"].grid() == tuple(float(v) for v in range(-5, 5))
    assert space.dims["y"].grid() == tuple(float(v) for v in range(5, 20))
    assert space.dims["background"].grid() == tuple(range(15))
    assert len(space.grid()) == 2250
    assert space.threshold == 0.65 and space.sensor == "kitti-hdl64e-front"
    assert space.name == "paper"


def test_smoke_config_is_tiny():
    space = load_space(CONFIGS / "smoke.toml")
    assert len(space.grid()) == 8


def test_grid_enumerates_further_cars_only_when_present():
    raw = copy.deepcopy(BASE)
    raw["dims"]["count"] = {"values": [1, 2]}
    raw["dims"]["x_2"] = {"values": [3.0, 4.0]}
    space = parse_space(raw)
    grid = space.grid()
    assert len(grid) == len(set(grid))
    ones = [s for s in grid if s.count == 1]
    twos = [s for s in grid if s.count == 2]
    assert len(ones) == 3 * 2 * 2 and len(twos) == 3 * 2 * 2 * 2 * 2 * 1  # y_2 defaults to y
    assert len(twos) == 3 * 2 * 2 * 2 * 2
    assert len(twos[0].cars) == 2 and len(ones[0].cars) == 1


def test_make_pins_inactive_dims_and_coerces_strings():
    raw = copy.deepcopy(BASE)
    raw["dims"]["count"] = {"values": [1, 2]}
    space = parse_space(raw)
    a = space.make({"x": "1", "count": "1", "x_2": 0.0})
    b = space.make({"x": 1.0, "count": 1, "x_2": 1.0})
    assert a == b  # x_2 cannot change a one-car sample


@pytest.mark.parametrize(("mutate", "message"), [
    (lambda r: r["dims"].pop("x"), "dims.x is missing"),
    (lambda r: r.pop("dims"), "missing table [dims]"),
    (lambda r: r["dims"]["x"].update(step=0.0), "dims.x.step: 0 must be > 0"),
    (lambda r: r["dims"]["x"].update(step=-1.0), "dims.x.step"),
    (lambda r: r["dims"]["x"].update(step=1e-11), "dims.x.step: 1e-11 must be >= 1e-09"),
    (lambda r: r["dims"]["x"].update(min=3.0), "empty range"),
    (lambda r: r["dims"]["x"].update(min="a"), "dims.x.min: expected a finite number"),
    (lambda r: r["dims"]["x"].pop("step"), "missing 'step'"),
    (lambda r: r["dims"]["car_model"].update(values=["tank"]), "unknown car model 'tank'"),
    (lambda r: r["dims"]["car_model"].update(values=[]), "non-empty list"),
    (lambda r: r["dims"]["background"].update(values=[-1]), "unknown background -1"),
    (lambda r: r["dims"]["background"].update(values=["street"]), "is not int"),
    (lambda r: r["dims"].update(colour_2={"values": ["red"]}), "unknown dim dims.colour_2"),
    (lambda r: r.update(sensr="x"), "unknown key 'sensr'"),
    (lambda r: r.update(seed="1"), "seed: expected int"),
    (lambda r: r.update(threshold=1.5), "threshold"),
    (lambda r: r["dims"].update(count={"values": [0]}), "dims.count"),
    (lambda r: r.update(car_models={"mine": {"scale": 2}}), "car_models.mine: needs file"),
    (lambda r: r.update(car_models={"mine": {"file": "a.obj", "forward": "north"}}),
     "forward: 'north'; allowed"),
])
def test_bad_configs_name_the_key(mutate, message):
    raw = copy.deepcopy(BASE)
    mutate(raw)
    with pytest.raises(ConfigError) as err:
        parse_space(raw)
    assert message in str(err.value)


def test_unknown_car_model_lists_the_allowed_ones():
    raw = copy.deepcopy(BASE)
    raw["dims"]["car_model"]["values"] = ["tank"]
    with pytest.raises(ConfigError, match="allowed: sedan, hatchback"):
        parse_space(raw)


def test_out_of_range_value_is_an_error():
    space = parse_space(copy.deepcopy(BASE))
    with pytest.raises(ConfigError, match=r"x: '7' is outside \[-1, 1\]"):
        space.make({"x": "7"})
    with pytest.raises(ConfigError, match="unknown dim 'z'"):
        space.make({"z": 1})
    with pytest.raises(ConfigError, match="background: '5' is not one of 0, 1"):
        space.make({"background": "5"})


def test_not_toml_and_missing_file(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text("name = [")
    with pytest.raises(ConfigError, match="bad.toml: not valid TOML"):
        load_space(bad)
    with pytest.raises(ConfigError, match="none.toml: no such config; give a TOML file or a "
                                          "bundled config: bench, ci, paper"):
        load_space(tmp_path / "none.toml")


def test_continuous_grid_includes_max_and_fixed_values():
    assert Continuous("x", -5.0, 4.0, 1.0).grid()[-1] == 4.0
    assert Continuous("y", 0.0, 1.0, 0.3).grid() == (0.0, 0.3, 0.6, 0.9)
    space = parse_space({"dims": {**BASE["dims"], "yaw": {"values": [0.0, 90.0]}}})
    assert space.dims["yaw"].grid() == (0.0, 90.0)


def test_a_single_tiny_value_is_kept_as_given():
    """`fog = {values = [1e-11]}` was rounded to 1e-10 decimals: fog 0, no fog at all, the
    opposite of the densest fog the config asked for."""
    from falsify.world.space_dims import read_continuous_or_values
    dim = read_continuous_or_values("fog", {"values": [1e-11]}, "")
    assert dim.grid() == (1e-11,)
    assert read_continuous_or_values("x", {"values": [2.5]}, "").grid() == (2.5,)
