"""`falsify dataset --out` into a folder already used: a resume or extension with the same
options, else exit 2 naming what differs, with nothing written."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from falsify.cli import main

SMOKE = str(Path(__file__).resolve().parents[2] / "configs" / "smoke.toml")


def dataset(out: Path, *argv: str) -> int:
    return main(["dataset", SMOKE, "--out", str(out), "--json", *argv])


def snapshot(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in root.rglob("*") if p.is_file()}


@pytest.fixture(scope="module")
def made(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("ds") / "set"
    assert dataset(out, "--scans", "2") == 0
    return out


def test_index_is_written_and_an_extension_keeps_the_scans(made, tmp_path, capsys):
    index = json.loads((made / "index.json").read_text())
    assert (index["scans"], index["seed"]) == (2, 0)
    out = tmp_path / "set"
    out.mkdir()
    for name, data in snapshot(made).items():
        (out / name).write_bytes(data)
    old = snapshot(out)
    assert dataset(out, "--scans", "2") == 0          # a resume with nothing left to do
    summary = json.loads(capsys.readouterr().out)
    assert summary["written"] == 0 and (summary["out"], summary["format"]) == (str(out), "npy")
    assert dataset(out, "--scans", "3") == 0          # an extension
    now = snapshot(out)
    assert all(now[k] == v for k, v in old.items() if k != "index.json")
    assert "000002.npy" in now and json.loads(now["index.json"])["scans"] == 3


@pytest.mark.parametrize("argv, names", [
    (["--scans", "1"], "--scans 1"),
    (["--scans", "3", "--seed", "7"], "--seed"),
    (["--scans", "3", "--max-cars", "3"], "--max-cars"),
    (["--scans", "3", "--labels", "semantickitti"], "--labels"),
    (["--scans", "3", "--format", "semantickitti"], "--format"),
    (["--scans", "3", "--format", "kitti-object"], "--format"),
])
def test_other_options_into_a_set_exit_2_and_write_nothing(made, capsys, argv, names):
    before = snapshot(made)
    assert dataset(made, *argv) == 2
    err = capsys.readouterr().err
    assert f"--out {made}" in err and names in err, err
    assert snapshot(made) == before


def test_a_folder_holding_something_else_is_refused(tmp_path, capsys):
    out = tmp_path / "busy"
    out.mkdir()
    (out / "notes.txt").write_text("mine\n")
    assert dataset(out, "--scans", "1") == 2
    assert f"--out {out}: not empty" in capsys.readouterr().err
    assert snapshot(out) == {"notes.txt": b"mine\n"}


def test_camera_is_refused_where_no_camera_renders(tmp_path, capsys):
    """--camera with npy or semantickitti did nothing, unsaid; kitti-object still takes it."""
    for fmt in ("npy", "semantickitti"):
        assert dataset(tmp_path / fmt, "--scans", "1", "--format", fmt, "--camera",
                       "kitti-rig") == 2
        assert "only --format kitti-object renders the camera" in capsys.readouterr().err
        assert not (tmp_path / fmt).exists()
    assert dataset(tmp_path / "ko", "--scans", "1", "--format", "kitti-object") == 0
    assert json.loads((tmp_path / "ko" / "index.json").read_text())["camera"] == "kitti-centre"
