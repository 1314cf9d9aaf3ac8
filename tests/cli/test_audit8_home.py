"""A `~` the shell leaves alone: `--opt=~/x` and a config's data and mesh paths name the home
folder, not a folder called `~` in the working folder."""

from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import pytest

from falsify.cli import expand_home, main
from falsify.paths import expand_data_path
from falsify.world.space import parse_space
from tests.conftest import CONFIGS


@pytest.fixture
def home(tmp_path: Path, monkeypatch) -> Path:
    home, work = tmp_path / "home", tmp_path / "work"
    home.mkdir()
    work.mkdir()
    monkeypatch.setenv("HOME", str(home))
    monkeypatch.chdir(work)
    return home


def test_expand_home_only_touches_an_option_value(home: Path) -> None:
    assert expand_home("--out=~/runs/a") == f"--out={home}/runs/a"
    for kept in ("~/x", "--note=a~b", "--out=./~", "-o=~/x", "--out"):
        assert expand_home(kept) == kept


def test_out_with_equals_tilde_writes_under_home(home: Path) -> None:
    scan = home / "a.bin"
    np.zeros((10, 4), np.float32).tofile(scan)
    assert main(["holdout", str(scan), "--out=~/splits.toml"]) == 0
    assert (home / "splits.toml").is_file()
    assert not (Path.cwd() / "~").exists()


def test_run_folder_with_equals_tilde(home: Path) -> None:
    assert main(["search", str(CONFIGS / "smoke.toml"), "--out=~/run", "--algorithm", "random",
                 "--budget", "1", "--no-report"]) == 0
    assert (home / "run" / "results.sqlite").is_file()
    assert not (Path.cwd() / "~").exists()


def test_config_paths_expand_home(home: Path) -> None:
    assert expand_data_path("~/kitti", "real") == str(home / "kitti")
    raw = {"name": "t", "car_models": {"mine": {"file": "~/meshes/car.obj"}},
           "dims": {"car_model": {"values": ["mine"]}, "x": {"values": [0.0]},
                    "y": {"values": [8.0]}, "background": {"values": [0]}}}
    space = parse_space(copy.deepcopy(raw))
    assert space.user_cars["mine"].file == home / "meshes" / "car.obj"
