"""Training's inputs kept apart: validation scans that are training scans (by path or by
content) are refused, and a checkpoint of the other trainer is named as such on --resume."""

from __future__ import annotations

import shutil

import pytest

pytest.importorskip("torch")

from falsify.cli import main as falsify_main  # noqa: E402

ARGS = ["--batch", "2", "--seed", "3", "--precision", "fp32", "--crf-iterations", "1"]
PN_ARGS = ["--batch", "1", "--points", "64", "--seed", "3"]
TRAINERS = [("train", ARGS), ("train-pointnet", PN_ARGS)]


@pytest.fixture(autouse=True)
def _no_holdout_from_env(monkeypatch):
    monkeypatch.delenv("FALSIFY_HOLDOUT", raising=False)


@pytest.mark.parametrize("trainer, args", TRAINERS)
def test_validating_on_the_training_folder_exits_2(data, tmp_path, capsys, trainer, args):
    """--val-data DIR equal to --data DIR chose the checkpoint on its own training scans."""
    out = tmp_path / "o"
    assert falsify_main([trainer, "--data", str(data), "--val-data", str(data), "--out",
                         str(out), *args]) == 2
    err = capsys.readouterr().err
    assert "--val-data" in err and "also a --data scan" in err
    assert not out.exists()


@pytest.mark.parametrize("trainer, args", TRAINERS)
def test_a_copied_training_scan_among_validation_scans_is_named(data, val, tmp_path, capsys,
                                                                trainer, args):
    mixed = tmp_path / "mixed"
    shutil.copytree(val, mixed)
    shutil.copy(data / "scan_2.npy", mixed / "copy.npy")
    out = tmp_path / "o"
    assert falsify_main([trainer, "--data", str(data), "--val-data", str(mixed), "--out",
                         str(out), *args]) == 2
    err = capsys.readouterr().err
    assert f"--val-data {mixed / 'copy.npy'}: the same bytes as --data scan" in err
    assert "scan_2.npy" in err and not out.exists()


FIRST = {"train": ["--max-steps", "1", "--no-export", *ARGS], "train-pointnet": PN_ARGS}


@pytest.mark.parametrize("first, second", [("train", "train-pointnet"),
                                           ("train-pointnet", "train")])
def test_resuming_the_other_trainers_checkpoint_names_that_trainer(data, tmp_path, capsys,
                                                                   first, second):
    """It said '--resume: batch differs' (or another option), not whose checkpoint it was."""
    out = tmp_path / "o"
    assert falsify_main([first, "--data", str(data), "--out", str(out), "--epochs", "1",
                         *FIRST[first]]) == 0
    capsys.readouterr()
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    args = dict(TRAINERS)[second]
    assert falsify_main([second, "--data", str(data), "--out", str(out), "--epochs", "1",
                         "--resume", *args]) == 2
    err = capsys.readouterr().err
    assert f"a checkpoint of `falsify {first}`" in err and f"falsify {first} --resume" in err
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before


def test_a_failed_spec_write_leaves_the_old_spec_whole(tmp_path, monkeypatch):
    """save_spec wrote in place: a stop mid-write left half a JSON beside the model."""
    import os
    from dataclasses import replace
    from pathlib import Path

    import falsify.models
    from falsify.models.spec import load_spec, save_spec

    spec = load_spec(Path(falsify.models.__file__).parent / "weights" / "squeezeseg.json")
    path = save_spec(spec, tmp_path / "net.json")
    before = path.read_bytes()

    def broken(fd):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "fsync", broken)
    with pytest.raises(OSError):
        save_spec(replace(spec, name="other"), path)
    assert path.read_bytes() == before and [p.name for p in tmp_path.iterdir()] == ["net.json"]
