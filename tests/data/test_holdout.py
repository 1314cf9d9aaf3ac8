"""Data where the user keeps it: `${VAR}` paths in configs, `per_sequence`, and held-out scans
as a user's split manifest, matched by content."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from falsify.cli import main
from falsify.data.holdout import Holdout, holdout_for, load_manifest
from falsify.errors import FalsifyError
from falsify.paths import expand_data_path
from falsify.world.space import load_space
from tests.conftest import HOLDOUT, MINI, one_car_config


def _sequence(root: Path, sid: str, scans: int, points: int = 20) -> list[Path]:
    """A labelled SemanticKITTI sequence of `scans` scans, each of its own size and bytes."""
    out = []
    for i in range(scans):
        n = points + i + 5 * int(sid)
        pts = np.random.default_rng(100 * int(sid) + i).normal(size=(n, 4)).astype(np.float32)
        pts[:, :2] += [8.0, 0.0]
        for sub in ("velodyne", "labels"):
            (root / "sequences" / sid / sub).mkdir(parents=True, exist_ok=True)
        f = root / "sequences" / sid / "velodyne" / f"{i:06d}.bin"
        pts.tofile(f)
        np.full(n, 40, np.uint32).tofile(f.parent.parent / "labels" / f"{i:06d}.label")
        out.append(f)
    return out



def test_a_variable_in_a_path_reads_the_environment(tmp_path, monkeypatch):
    _sequence(tmp_path / "sk", "00", 2)
    monkeypatch.setenv("MY_SCANS", str(tmp_path / "sk"))
    space = load_space(one_car_config(tmp_path, 'real = ["${MY_SCANS}"]\n'))
    assert [r.name for r in space.real_backgrounds] == ["00/000000", "00/000001"]
    monkeypatch.delenv("MY_SCANS")
    with pytest.raises(FalsifyError, match=r"dims\.background\.real: \$\{MY_SCANS\} is not set; "
                                           r"it must name the folder it names: `export MY_SCANS"):
        load_space(one_car_config(tmp_path, 'real = ["${MY_SCANS}"]\n'))
    monkeypatch.setenv("EMPTY", "")
    with pytest.raises(FalsifyError, match=r"\$\{EMPTY\} is not set"):
        expand_data_path("${EMPTY}/x", "k")
    assert expand_data_path("plain/$HOME/path", "k") == "plain/$HOME/path"   # only ${NAME}


def test_per_sequence_takes_evenly_spaced_scans_of_each_sequence(tmp_path):
    _sequence(tmp_path / "sk", "00", 7)
    _sequence(tmp_path / "sk", "01", 3)
    background = f'real = ["{tmp_path / "sk"}"]\nper_sequence = 3\n'
    space = load_space(one_car_config(tmp_path, background))
    assert [r.name for r in space.real_backgrounds] == [
        "00/000000", "00/000003", "00/000006", "01/000000", "01/000001", "01/000002"]
    one = load_space(one_car_config(tmp_path, f'real = ["{tmp_path / "sk"}"]\nper_sequence = 1\n'))
    assert [r.name for r in one.real_backgrounds] == ["00/000000", "01/000000"]


@pytest.mark.parametrize("value", ["0", "true", '"3"', "2.5"])
def test_a_bad_per_sequence_exits_2_naming_it(tmp_path, capsys, value):
    _sequence(tmp_path / "sk", "00", 2)
    cfg = one_car_config(tmp_path, f'real = ["{tmp_path / "sk"}"]\nper_sequence = {value}\n')
    assert main(["grid", str(cfg), "--out", str(tmp_path / "run")]) == 2
    err = capsys.readouterr().err
    assert "dims.background.per_sequence: expected an integer >= 1" in err
    assert not (tmp_path / "run").exists()


def test_content_not_path_decides(tmp_path):
    """A copy and a symlink of a held-out scan are held out; a scan of the same size but other
    bytes is not."""
    (held,) = _sequence(tmp_path / "a", "05", 1)
    manifest = tmp_path / "m.toml"
    assert main(["holdout", str(held), "--out", str(manifest)]) == 0
    h = load_manifest(manifest)
    assert [s.name for s in h.scans] == ["000000.bin"] and h.scans[0].size == held.stat().st_size
    copy = tmp_path / "copy.bin"
    shutil.copyfile(held, copy)
    link = tmp_path / "link.bin"
    link.symlink_to(held)
    other = tmp_path / "other.bin"
    other.write_bytes(bytes(reversed(held.read_bytes())))
    assert h.held_out([held, copy, link, other]) == [held, copy, link]
    with pytest.raises(FalsifyError, match=r"copy\.bin: a held-out scan \(.*m\.toml, the same "
                                           r"bytes as 000000\.bin\)"):
        h.check([other, copy], "train's --data")


@pytest.mark.parametrize("text, message", [
    ("[split]\n", "unknown key 'split'"),
    ("x = 1\n", "unknown key 'x'"),
    ("[holdout]\nfolders = []\n", r"holdout\.folders: unknown key; allowed: sequences, paths"),
    ("[holdout]\nsequences = [8]\n", r"holdout\.sequences: expected a list of strings"),
    ("[holdout]\nsequences = [\"42\"]\n", r"holdout\.sequences: '42' is not a sequence"),
    ("[holdout]\npaths = [\"nowhere\"]\n", r"holdout\.paths: 'nowhere': no such file"),
    ("[[holdout.scan]]\nsha256 = \"abc\"\nbytes = 3\n", r"holdout\.scan\[0\]\.sha256: expected "
                                                        "64 lowercase hex digits"),
    ("[[holdout.scan]]\nsha256 = \"" + "a" * 64 + "\"\n", r"holdout\.scan\[0\]\.bytes"),
    ("[holdout\n", "not valid TOML split manifest"),
])
def test_a_bad_manifest_exits_2_naming_the_key(tmp_path, capsys, text, message):
    _sequence(tmp_path / "sk", "05", 1)
    manifest = tmp_path / "sk" / "splits.toml"
    manifest.write_text(text)
    out = tmp_path / "profile.json"
    assert main(["fit-world", str(tmp_path / "sk"), "--out", str(out), "--base-scans", "1"]) == 2
    err = capsys.readouterr().err
    assert str(manifest) in err
    assert __import__("re").search(message, err), err
    assert not out.exists()


def test_manifests_are_found_beside_the_data_and_named_in_the_environment(tmp_path,
                                                                          monkeypatch):
    monkeypatch.delenv("FALSIFY_HOLDOUT", raising=False)
    files = _sequence(tmp_path / "sk", "05", 2) + _sequence(tmp_path / "sk", "08", 1)
    assert holdout_for(files).held_out(files) == files[2:]        # the official split: 08
    (tmp_path / "sk" / "splits.toml").write_text('[holdout]\npaths = ["sequences/05"]\n')
    assert holdout_for(files).held_out(files) == files[:2]        # the manifest replaces it
    elsewhere = tmp_path / "m.toml"
    assert main(["holdout", str(files[2]), "--out", str(elsewhere)]) == 0
    monkeypatch.setenv("FALSIFY_HOLDOUT", str(elsewhere))
    assert holdout_for(files).held_out(files) == files             # both
    assert not Holdout()


@pytest.mark.skipif(not (MINI / "sequences" / "00").is_dir(), reason=f"{MINI} not present")
def test_the_projects_manifest_holds_its_evaluation_split_and_no_fit_scan():
    h = load_manifest(HOLDOUT)
    evaluation = [f for q in ("00", "03", "06", "08")
                  for f in sorted((MINI / "sequences" / q / "velodyne").glob("*.bin"))]
    fit = [f for q in ("01", "02", "04", "05", "07", "09", "10")
           for f in sorted((MINI / "sequences" / q / "velodyne").glob("*.bin"))]
    assert len(evaluation) == 12 and h.held_out(evaluation) == evaluation
    assert len(fit) == 21 and h.held_out(fit) == []


def test_train_refuses_held_out_scans(tmp_path, capsys):
    """`falsify train` checks --data and --val-data before it trains."""
    pytest.importorskip("torch")
    data = tmp_path / "data"
    data.mkdir()
    np.save(data / "000000.npy", np.zeros((64, 512, 6), np.float32))
    manifest = tmp_path / "m.toml"
    assert main(["holdout", str(data), "--out", str(manifest)]) == 0
    out = tmp_path / "out"
    rc = main(["train", "--data", str(data), "--out", str(out), "--holdout", str(manifest),
               "--max-steps", "1"])
    assert rc == 2
    assert "000000.npy: a held-out scan" in capsys.readouterr().err
    assert not (out / "checkpoint.pt").exists()


def test_a_missing_manifest_and_an_empty_holdout_exit_2_writing_nothing(tmp_path, capsys):
    _sequence(tmp_path / "sk", "05", 1)
    out = tmp_path / "profile.json"
    assert main(["fit-world", str(tmp_path / "sk"), "--holdout", str(tmp_path / "no.toml"),
                 "--out", str(out)]) == 2
    assert f"{tmp_path / 'no.toml'}: no such split manifest" in capsys.readouterr().err
    assert not out.exists()
    empty = tmp_path / "empty"
    empty.mkdir()
    manifest = tmp_path / "m.toml"
    assert main(["holdout", str(empty), "--out", str(manifest)]) == 2
    assert f"{empty}: no .bin scans here" in capsys.readouterr().err
    assert not manifest.exists()


def test_a_manifest_of_linked_data_names_the_scans_as_given(tmp_path):
    """A root of symlinked sequences and a folder of symlinked scans (links into another tree)
    are named as the user laid them out, not where the links point."""
    real = _sequence(tmp_path / "store", "05", 2)
    root = tmp_path / "sk" / "sequences"
    root.mkdir(parents=True)
    (root / "05").symlink_to(real[0].parent.parent)
    linked = tmp_path / "links"
    linked.mkdir()
    (linked / "a.bin").symlink_to(real[1])
    manifest = tmp_path / "m.toml"
    assert main(["holdout", str(tmp_path / "sk"), str(linked), "--out", str(manifest)]) == 0
    assert [s.name for s in load_manifest(manifest).scans] == [
        "sk/sequences/05/velodyne/000000.bin", "sk/sequences/05/velodyne/000001.bin",
        "links/a.bin"]


def test_a_note_of_several_lines_stays_a_comment(tmp_path):
    (scan,) = _sequence(tmp_path / "a", "05", 1)
    manifest = tmp_path / "m.toml"
    assert main(["holdout", str(scan), "--out", str(manifest), "--note", "one\nsplit = 2"]) == 0
    assert "# one\n# split = 2\n" in manifest.read_text()
    assert len(load_manifest(manifest).scans) == 1
