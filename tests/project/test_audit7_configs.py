"""A bundled config is named as a user would name it: `paper`, `paper.toml` or
`configs/paper.toml`, from any folder, even beside a folder of that name (a run's `--out
paper` made one and then read it as the config: 'paper: cannot read config (Is a
directory)'); a name that is nothing lists the bundled configs."""

from __future__ import annotations

import pytest

from falsify.cli import main
from falsify.errors import ConfigError
from falsify.paths import CONFIGS, bundled_configs, config_path
from falsify.world.space import load_space


@pytest.mark.parametrize("name", ["smoke", "smoke.toml", "configs/smoke.toml"])
def test_a_bundled_config_by_any_of_its_names(tmp_path, monkeypatch, name) -> None:
    monkeypatch.chdir(tmp_path)
    (tmp_path / "smoke").mkdir()   # a folder of that name does not hide it
    assert config_path(name) == CONFIGS / "smoke.toml"
    assert load_space(name).name == "smoke"


def test_a_run_named_for_its_config_runs(tmp_path, monkeypatch, capsys) -> None:
    monkeypatch.chdir(tmp_path)
    assert main(["grid", "smoke", "--out", "smoke", "--quiet", "--no-report"]) == 0
    assert (tmp_path / "smoke" / "results.sqlite").is_file()


def test_a_name_that_is_nothing_lists_the_bundled_configs(tmp_path, monkeypatch) -> None:
    monkeypatch.chdir(tmp_path)
    names = bundled_configs()
    assert {"paper", "smoke", "ci"} <= set(names) and "sensors" not in names
    with pytest.raises(ConfigError, match="nosuch: no such config; give a TOML file or a "
                                          "bundled config: bench, ci, paper"):
        load_space("nosuch")
