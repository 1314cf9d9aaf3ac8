"""`falsify scan` and `falsify dataset`: outputs, determinism, exit code 2 with nothing written."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from falsify.cli import main
from tests.conftest import CONFIGS


def test_scan_writes_npy_and_png(tmp_path, capsys):
    out = tmp_path / "s"
    assert main(["scan", str(CONFIGS / "smoke.toml"), "--out", str(out), "--set", "x=2",
                 "--set", "background=1", "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["sample"]["x"] == 2.0 and summary["sample"]["background"] == 1
    img = np.load(out / "scan.npy")
    assert img.shape == (64, 512, 6) and img.dtype == np.float32
    assert (out / "scan.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    valid = img[..., 4] > 0
    assert summary["car_points"] == int((valid & (img[..., 5] == 1)).sum()) > 0


def test_scan_counts_the_placed_objects_points_by_their_instance(tmp_path, capsys):
    """Besides every car's points, the summary counts the placed object's own: in an actor run
    the pedestrian's, which the car count leaves out."""
    config = tmp_path / "ped.toml"
    config.write_text('[dims.actor]\nvalues = ["pedestrian"]\n[dims.x]\nvalues = [0.0]\n'
                      "[dims.y]\nvalues = [10.0]\n[dims.background]\nvalues = [0]\n")
    out = tmp_path / "s"
    assert main(["scan", str(config), "--out", str(out)]) == 0
    assert "on the placed pedestrian" in capsys.readouterr().out
    assert main(["scan", str(config), "--out", str(out), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    labels = np.fromfile(out / "scan.label", dtype=np.uint32)
    mine = (labels >> 16) == 1
    assert summary["placed_points"] == int(mine.sum()) > 30
    assert set(np.unique(labels[mine] & 0xFFFF)) == {30}   # SemanticKITTI's person


def test_scan_is_deterministic(tmp_path):
    for name in ("a", "b"):
        assert main(["scan", str(CONFIGS / "smoke.toml"), "--out", str(tmp_path / name)]) == 0
    assert (tmp_path / "a" / "scan.npy").read_bytes() == (tmp_path / "b" / "scan.npy").read_bytes()
    assert (tmp_path / "a" / "scan.png").read_bytes() == (tmp_path / "b" / "scan.png").read_bytes()


def test_scan_replaces_only_the_files_it_wrote(tmp_path, capsys):
    """Before: `scan --out DIR` deleted DIR's image.png, depth.npy and scan.* whoever wrote
    them. Now a file of those names that no scan wrote there is refused, before any cast, and
    stays; the scan's own files (listed in scan-files.json with their SHA-256) are replaced."""
    smoke = str(CONFIGS / "smoke.toml")
    out = tmp_path / "pictures"
    out.mkdir()
    (out / "image.png").write_bytes(b"a user's photo")
    (out / "notes.txt").write_bytes(b"mine")
    assert main(["scan", smoke, "--out", str(out)]) == 0      # no --camera: image.png is not ours
    assert (out / "image.png").read_bytes() == b"a user's photo"
    assert main(["scan", smoke, "--out", str(out), "--camera"]) == 2
    err = capsys.readouterr().err
    assert "image.png is there and is not a file `falsify scan` wrote" in err
    assert (out / "image.png").read_bytes() == b"a user's photo"
    listed = json.loads((out / "scan-files.json").read_text())["files"]
    assert sorted(listed) == ["scan.bin", "scan.label", "scan.npy", "scan.png"]
    # its own files, rewritten for another sample; a file the user has since edited is refused
    assert main(["scan", smoke, "--out", str(out), "--set", "x=2"]) == 0
    assert sorted(p.name for p in out.iterdir()) == [
        "image.png", "notes.txt", "scan-files.json", "scan.bin", "scan.label", "scan.npy",
        "scan.png"]
    (out / "scan.bin").write_bytes(b"edited by hand")
    assert main(["scan", smoke, "--out", str(out)]) == 2
    assert "scan.bin is there and is not a file `falsify scan` wrote" in capsys.readouterr().err
    assert (out / "scan.bin").read_bytes() == b"edited by hand"


@pytest.mark.parametrize("text", ["{not json", '{"files": ["scan.npy"]}'])
def test_scan_refuses_a_broken_file_list_and_writes_nothing(tmp_path, capsys, text):
    out = tmp_path / "o"
    out.mkdir()
    (out / "scan-files.json").write_text(text)
    assert main(["scan", str(CONFIGS / "smoke.toml"), "--out", str(out)]) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and f"--out {out / 'scan-files.json'}:" in lines[0]
    assert [p.name for p in out.iterdir()] == ["scan-files.json"]


TWO_CARS = """
[dims.x_2]
min = -6.0
max = 6.0
step = 12.0
[dims.y_2]
min = 16.0
max = 20.0
step = 4.0
"""



def two_cars(smoke: str) -> str:
    """smoke.toml with one or two cars, the second car's position its own dims."""
    return smoke.replace("[dims.count]\nvalues = [1]", "[dims.count]\nvalues = [1, 2]") + TWO_CARS


def test_scan_sets_a_second_cars_dim_with_its_count(tmp_path, capsys):
    config = tmp_path / "c.toml"
    config.write_text(two_cars((CONFIGS / "smoke.toml").read_text()))
    assert main(["scan", str(config), "--out", str(tmp_path / "o"), "--set", "count=2",
                 "--set", "x_2=6", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["sample"]["x_2"] == 6.0


@pytest.mark.parametrize(("toml", "sets", "message"), [
    ("", ["x=9"], "x: '9' is outside [-2, 2]"),
    ("", ["car_model=tank"], "car_model: 'tank' is not one of sedan"),
    ("", ["colour=red"], "unknown dim 'colour'"),
    ("", ["x"], "expected KEY=VALUE"),
    ("", ["x=-2", "x=2"], "--set x: given twice (-2 and 2); give it once"),
    ("two", ["x_2=6"], "--set x_2: a dim of a car beyond the sample's count (1)"),
    ("", ["y=1.0"], "outside"),
    ("BROKEN", [], "not valid TOML"),
    ("step0", [], "dims.x.step: 0 must be > 0"),
    ("fov", [], "unknown preset 'wide'"),
])
def test_bad_input_exits_2_and_writes_nothing(tmp_path, capsys, toml, sets, message):
    config = CONFIGS / "smoke.toml"
    if toml:
        text = config.read_text()
        text = {"BROKEN": "name = [", "step0": text.replace("step = 4.0", "step = 0.0"),
                "fov": text.replace('sensor = "kitti-hdl64e-front"', 'sensor = "wide"'),
                "two": two_cars(text)}[toml]
        config = tmp_path / "c.toml"
        config.write_text(text)
    out = tmp_path / "out"
    args = ["scan", str(config), "--out", str(out)]
    for s in sets:
        args += ["--set", s]
    assert main(args) == 2
    assert message in capsys.readouterr().err
    assert not out.exists()


def test_sensor_with_180_degree_vertical_fov_is_rejected(tmp_path, capsys):
    sensor = tmp_path / "wide.toml"
    sensor.write_text('elevations_deg = [90.0, 0.0, -30.0]\nh_fov_deg = [45.0, -45.0]\n'
                      'columns = 512\n')
    config = tmp_path / "c.toml"
    config.write_text((CONFIGS / "smoke.toml").read_text().replace(
        'sensor = "kitti-hdl64e-front"', f'sensor = "{sensor}"'))
    assert main(["scan", str(config), "--out", str(tmp_path / "o")]) == 2
    assert "FOV < 180" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_invalid_sample_is_a_clear_error(tmp_path, capsys):
    config = tmp_path / "c.toml"
    config.write_text((CONFIGS / "smoke.toml").read_text().replace("min = 8.0", "min = 2.0"))
    assert main(["scan", str(config), "--out", str(tmp_path / "o"), "--set", "y=2",
                 "--set", "x=0"]) == 2
    assert "intersects the ego vehicle" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_console_script_exit_code(tmp_path):
    r = subprocess.run([sys.executable, "-m", "falsify", "scan", "nope.toml", "--out",
                        str(tmp_path / "o")], capture_output=True, text=True)
    assert r.returncode == 2 and "nope.toml: no such config" in r.stderr
    r = subprocess.run([sys.executable, "-m", "falsify", "scan"], capture_output=True,
                       text=True)
    assert r.returncode == 2


def test_dataset_writes_resumable_scans(tmp_path, capsys):
    out = tmp_path / "ds"
    args = ["dataset", str(CONFIGS / "smoke.toml"), "--scans", "3", "--out", str(out), "--json"]
    assert main(args) == 0
    first = {p.name: p.read_bytes() for p in out.glob("*.npy")}
    assert len(first) == 3
    (out / "000001.npy").unlink()
    assert main(args) == 0
    assert json.loads(capsys.readouterr().out.split("\n}\n")[-1] or "{}") is not None
    assert {p.name: p.read_bytes() for p in out.glob("*.npy")} == first
    assert main(["dataset", str(CONFIGS / "smoke.toml"), "--scans", "3", "--out",
                 str(tmp_path / "x"), "--first-background", "0"]) == 2
    assert not (tmp_path / "x").exists()


@pytest.mark.parametrize(("option", "message"), [
    (["--max-cars", "-1"], "--max-cars: -1"), (["--backgrounds", "0"], "--backgrounds: 0"),
    (["--ray-drop", "1.5"], "--ray-drop"), (["--scans", "0"], "--scans: 0"),
])
def test_dataset_bad_options_exit_2(tmp_path, capsys, option, message):
    args = ["dataset", str(CONFIGS / "smoke.toml"), "--scans", "2", "--out", str(tmp_path / "d")]
    assert main(args + option) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "d").exists()
