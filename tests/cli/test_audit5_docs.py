"""What the README and docs promise of objects other than a car, and of config errors, held to.

- `gate --baseline` compares blind spots of one objective only: a baseline of another class's
  IoU (a run, or a `gate --json` file that says its objective) exits 2; the verdict names it.
- A dim's mistyped key beside `values` is named, with the allowed keys (not "not both").
- `train` and `export` take `--json`, as "every command that prints a summary" does.
- The report's distance plot names the placed object as the map does (actor 1, not car 1).
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from falsify.cli import build_parser, main
from falsify.reports.run.plots import distance_section, search_section
from falsify.results.store import open_run
from tests.runfixture import SMOKE, write_run

ACTORS = SMOKE.read_text().replace("[dims.car_model]\nvalues = [\"sedan\"]",
                                   "[dims.actor]\nvalues = [\"pedestrian\"]")


def gate(args: list[str], capsys) -> tuple[int, str, str]:
    code = main(["gate", *args])
    out, err = capsys.readouterr()
    return code, out, err


def test_gate_refuses_a_baseline_of_another_objective(tmp_path: Path, capsys) -> None:
    cars = write_run(tmp_path / "cars")
    people = write_run(tmp_path / "people", meta={"objective": "pedestrian",
                                                  "score_column": "pedestrian_iou"})
    code, _, err = gate([str(cars), "--baseline", str(people)], capsys)
    assert code == 2 and "pedestrian IoU" in err and "car IoU" in err and "--baseline" in err

    code, out, _ = gate([str(cars), "--json"], capsys)
    doc = json.loads(out)
    assert doc["objective"] == "car"
    other = tmp_path / "people.json"
    other.write_text(json.dumps({**doc, "objective": "pedestrian"}))
    code, _, err = gate([str(cars), "--baseline", str(other)], capsys)
    assert code == 2 and "pedestrian IoU" in err

    # the same objective, or a baseline written before gate --json said it: judged as before
    same = tmp_path / "same.json"
    same.write_text(out)
    assert gate([str(cars), "--baseline", str(same)], capsys)[0] == 0
    old = tmp_path / "old.json"
    old.write_text(json.dumps({k: v for k, v in doc.items() if k != "objective"}))
    assert gate([str(cars), "--baseline", str(old)], capsys)[0] == 0


def test_gate_takes_person_and_pedestrian_for_one_class(tmp_path: Path, capsys) -> None:
    """A four-class network's pedestrian is a SemanticKITTI network's person."""
    run = write_run(tmp_path / "run", meta={"objective": "pedestrian"})
    base = tmp_path / "base.json"
    base.write_text(json.dumps({"objective": "person", "blind_spots": []}))
    code, out, _ = gate([str(run), "--baseline", str(base)], capsys)
    assert code in (0, 1) and "pedestrian mIoU" in out


def test_a_mistyped_key_beside_values_is_named(tmp_path: Path, capsys) -> None:
    config = tmp_path / "space.toml"
    config.write_text(SMOKE.read_text().replace("[dims.yaw]\nvalues = [0.0]",
                                                "[dims.yaw]\nvalues = [0.0]\nstp = 1.0"))
    out = tmp_path / "run"
    assert main(["grid", str(config), "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "dims.yaw: unknown key 'stp'; allowed: min, max, step, values" in err
    assert not out.exists()


@pytest.mark.parametrize("argv", [["train", "--data", "d", "--out", "o", "--json"],
                                  ["export", "w.pt", "--out", "m.onnx", "--json"]])
def test_train_and_export_take_json(argv: list[str]) -> None:
    assert build_parser().parse_args(argv).json is True


def test_the_distance_plot_names_the_placed_actor(tmp_path: Path) -> None:
    data = open_run(write_run(tmp_path / "run", ACTORS))
    html = distance_section(data, 0.65)
    assert "distance of actor 1 from the sensor" in html and "of actor 1)" in html
    assert "car 1" not in html
    search = open_run(write_run(tmp_path / "search", ACTORS, command="search"))
    assert "put actor 1," in search_section(search, search.cell_map(), 0.65)
    cars = open_run(write_run(tmp_path / "cars"))
    assert "distance of car 1 from the sensor" in distance_section(cars, 0.65)


def test_a_sensor_toml_beside_the_config_is_found_from_any_folder(tmp_path: Path, monkeypatch,
                                                                  capsys) -> None:
    """`sensor = "mine.toml"` reads the file beside the config, as its meshes, real scans and
    world profile are read, wherever the command runs."""
    folder = tmp_path / "space"
    folder.mkdir()
    preset = SMOKE.parent / "sensors" / "kitti-hdl64e-front.toml"
    (folder / "mine.toml").write_text(preset.read_text())
    config = folder / "space.toml"
    config.write_text(SMOKE.read_text().replace('sensor = "kitti-hdl64e-front"',
                                                'sensor = "mine.toml"'))
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    assert main(["scan", str(config), "--out", "scan", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["sensor"] == "kitti-hdl64e-front"
    # a path that is not beside the config is still read from the working folder
    (elsewhere / "cwd.toml").write_text(preset.read_text())
    config.write_text(SMOKE.read_text().replace('sensor = "kitti-hdl64e-front"',
                                                'sensor = "cwd.toml"'))
    assert main(["scan", str(config), "--out", "scan2", "--json"]) == 0
