"""What a run scores is what a user inspects and resumes: `falsify scan` casts with the sample's
own seed (ray drop and the return model's dropout as a run applies them), and a user's sensor
file, with the return model it names, is part of the run's identity."""

from __future__ import annotations

import hashlib
import shutil
from pathlib import Path

import numpy as np
import pytest

from falsify.cli import main
from falsify.data.real_backgrounds import scanner_for
from falsify.results.samples import sample_seed
from falsify.world.space import load_space
from tests.conftest import CONFIGS

SENSORS = CONFIGS / "sensors"


def test_scan_command_writes_the_scan_a_run_scores(tmp_path: Path) -> None:
    assert main(["scan", str(CONFIGS / "smoke.toml"), "--out", str(tmp_path / "s"),
                 "--set", "x=2", "--set", "y=8", "--set", "background=1"]) == 0
    written = np.load(tmp_path / "s" / "scan.npy")
    space = load_space(CONFIGS / "smoke.toml")
    sample = space.make({"x": 2.0, "y": 8.0, "background": 1})
    sim = scanner_for(space)
    scored = sim.scan(sample, rng=np.random.default_rng(sample_seed(space, sample)))
    unseeded = sim.scan(sample)   # no dropout: more returns than the sensor gives
    assert np.array_equal(written, scored.image)
    assert int(scored.valid.sum()) < int(unseeded.valid.sum())


def _config(folder: Path, sensor_text: str) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "mine.toml").write_text(sensor_text)
    config = folder / "c.toml"
    config.write_text((CONFIGS / "smoke.toml").read_text().replace(
        'sensor = "kitti-hdl64e-front"', 'sensor = "mine.toml"'))
    return config


def test_a_user_sensor_file_and_its_return_model_are_in_the_config_hash(tmp_path: Path) -> None:
    preset = (SENSORS / "kitti-hdl64e-front.toml").read_text()
    shutil.copy(CONFIGS / "returns" / "semantickitti-fit.json", tmp_path / "returns.json")
    config = _config(tmp_path, preset.replace('returns = "semantickitti-fit"',
                                              'returns = "returns.json"'))
    first = load_space(config).config_hash
    assert first != hashlib.sha256(config.read_bytes()).hexdigest()
    (tmp_path / "mine.toml").write_text((tmp_path / "mine.toml").read_text().replace(
        "mount_height = 1.73", "mount_height = 1.5"))
    second = load_space(config).config_hash
    assert second != first
    ret = tmp_path / "returns.json"
    ret.write_text(ret.read_text().replace("{", '{"note": "refitted", ', 1))
    assert load_space(config).config_hash != second
    # a preset keeps the hash of the config's bytes alone: existing runs stay resumable
    smoke = CONFIGS / "smoke.toml"
    assert load_space(smoke).config_hash == hashlib.sha256(smoke.read_bytes()).hexdigest()


def test_resume_refuses_a_changed_sensor_file(tmp_path: Path, capsys) -> None:
    config = _config(tmp_path / "cfg", (SENSORS / "kitti-hdl64e-front.toml").read_text())
    out = tmp_path / "run"
    args = ["search", str(config), "--out", str(out), "--algorithm", "random", "--budget", "1",
            "--no-report"]
    assert main(args) == 0
    sensor = tmp_path / "cfg" / "mine.toml"
    sensor.write_text(sensor.read_text().replace("mount_height = 1.73", "mount_height = 1.5"))
    capsys.readouterr()
    assert main([*args, "--resume"]) == 2
    assert "differs" in capsys.readouterr().err


@pytest.mark.parametrize("broken", ["missing", "unreadable"])
def test_a_missing_sensor_file_is_named(tmp_path: Path, broken: str, capsys) -> None:
    config = _config(tmp_path, "")
    (tmp_path / "mine.toml").unlink()
    if broken == "unreadable":
        (tmp_path / "mine.toml").mkdir()
    assert main(["grid", str(config), "--out", str(tmp_path / "run")]) == 2
    assert "mine.toml" in capsys.readouterr().err
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("fmt", ["npy", "kitti-object"])
def test_dataset_extension_refuses_a_changed_sensor_file(tmp_path: Path, fmt: str,
                                                         capsys) -> None:
    config = _config(tmp_path / "cfg", (SENSORS / "kitti-hdl64e-front.toml").read_text())
    out = tmp_path / "set"
    args = ["dataset", str(config), "--scans", "1", "--out", str(out), "--format", fmt]
    assert main(args) == 0
    sensor = tmp_path / "cfg" / "mine.toml"
    sensor.write_text(sensor.read_text().replace("mount_height = 1.73", "mount_height = 1.5"))
    capsys.readouterr()
    assert main([*args[:3], "2", *args[4:]]) == 2
    assert "sensor_file (the content of the config's sensor file)" in capsys.readouterr().err


def test_a_preset_sensors_dataset_index_is_unchanged(tmp_path: Path) -> None:
    assert main(["dataset", str(CONFIGS / "smoke.toml"), "--scans", "1", "--out",
                 str(tmp_path / "set")]) == 0
    assert "sensor_file" not in (tmp_path / "set" / "index.json").read_text()


def test_the_report_names_the_sensor_file_and_grid(tmp_path: Path) -> None:
    config = _config(tmp_path / "cfg", (SENSORS / "kitti-hdl64e-front.toml").read_text().replace(
        'name = "kitti-hdl64e-front"', 'name = "<mine>"'))
    out = tmp_path / "run"
    assert main(["search", str(config), "--out", str(out), "--algorithm", "random",
                 "--budget", "1"]) == 0
    page = (out / "report.html").read_text()
    card = page[page.index("<dt>Sensor</dt>"):]
    card = card[:card.index("</dd>")]
    assert "&lt;mine&gt;" in card and "64 x 512" in card
    assert str((tmp_path / "cfg" / "mine.toml").resolve()) in card


def test_the_report_calls_a_preset_a_preset(tmp_path: Path) -> None:
    out = tmp_path / "run"
    assert main(["search", str(CONFIGS / "smoke.toml"), "--out", str(out), "--algorithm",
                 "random", "--budget", "1", "--workers", "1"]) == 0
    page = (out / "report.html").read_text()
    card = page[page.index("<dt>Sensor</dt>"):]
    assert "64 x 512 · a bundled preset" in card[:card.index("</dd>")]
    assert "on 1 worker<" in page or "on 1 worker " in page


def _mesh_config(folder: Path, size: float) -> Path:
    """A config placing the user's own car mesh (a box of `size` metres) on the smoke street."""
    import trimesh

    folder.mkdir(parents=True, exist_ok=True)
    trimesh.creation.box(extents=(4.0, 1.8, size)).export(folder / "mine.obj")
    config = folder / "c.toml"
    config.write_text('[car_models.mine]\nfile = "mine.obj"\n[dims.car_model]\n'
                      'values = ["mine"]\n[dims.x]\nvalues = [2.0]\n[dims.y]\nvalues = [8.0]\n'
                      "[dims.background]\nvalues = [0]\n")
    return config


def test_resume_refuses_a_changed_user_mesh(tmp_path: Path, capsys) -> None:
    """A user's mesh is part of the run's identity: --resume after the file changed (another
    car) is refused, as for a sensor file; the same mesh keeps the hash."""
    config = _mesh_config(tmp_path / "cfg", 1.5)
    first = load_space(config).config_hash
    assert first != hashlib.sha256(config.read_bytes()).hexdigest()
    out = tmp_path / "run"
    args = ["grid", str(config), "--out", str(out), "--no-report", "--quiet"]
    assert main(args) == 0
    _mesh_config(tmp_path / "cfg", 1.5)
    assert load_space(config).config_hash == first
    _mesh_config(tmp_path / "cfg", 1.2)
    assert load_space(config).config_hash != first
    capsys.readouterr()
    assert main([*args, "--resume"]) == 2
    assert "a file it names (a sensor, a mesh" in capsys.readouterr().err
