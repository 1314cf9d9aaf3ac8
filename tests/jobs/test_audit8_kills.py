"""A kill mid-run loses no finished work and leaves nothing half-written: each test stops a
command's writes at a chosen point (a writer that raises, as a kill there would stop it) and
checks that no partial file stands under a final name and that a rerun or --resume finishes."""

from __future__ import annotations

import errno
import json
import os
import shutil
import tomllib
from pathlib import Path

import pytest

from falsify.data.training import TrafficOptions, write_dataset
from falsify.errors import FalsifyError
from falsify.jobs.retrain import RetrainJob, RetrainRequest
from falsify.models.runners import BUNDLED_ONNX
from falsify.sensor.lidar import load_sensor
from tests.bench.test_tradeoff import CONFIG as TRADEOFF_CONFIG
from tests.jobs.test_retrain import TINY


class Killed(BaseException):
    """Stands for the process being killed where it is raised (no handler of the job runs)."""


@pytest.fixture(scope="module")
def retrain_inputs(tmp_path_factory) -> dict:
    root = tmp_path_factory.mktemp("kills-retrain")
    (root / "tiny.toml").write_text(TINY)
    sensor = load_sensor("kitti-hdl64e-front", ray_drop=0.05, range_noise=0.02)
    write_dataset(sensor, root / "train", 1, seed=1,
                  opts=TrafficOptions(backgrounds=1, traffic="drive"))
    return {"config": root / "tiny.toml", "train": root / "train"}


def _retrain(inputs: dict, out: Path, **kw) -> RetrainRequest:
    args = dict(config=inputs["config"], model=BUNDLED_ONNX, train_data=inputs["train"],
                out=out, validation=(0,), retraining=(5,), epochs=1, batch=8, oversample=1,
                train_scans=1, held_out_scans=0, kitti=None, workers=1)
    return RetrainRequest(**{**args, **kw})


def _stop_at(stage: str) -> None:
    raise Killed(stage)


@pytest.mark.parametrize("kill_at", [1, 2])
def test_retrain_killed_while_writing_its_configs_resumes(retrain_inputs, tmp_path,
                                                          monkeypatch, kill_at) -> None:
    """`falsify retrain` killed while it writes config-validation.toml / config-retraining.toml
    (before: they came before stages.json, so OUT held a config and no run: both a rerun, "not
    empty", and --resume, "holds no retraining run", were refused) continues with --resume."""
    import falsify.jobs.retrain as retrain

    real, calls = retrain.subset_config, []

    def subset_then_kill(*a, **k):
        calls.append(a)
        if len(calls) == kill_at:
            raise Killed("while writing a config")
        return real(*a, **k)

    out = tmp_path / "exp"
    monkeypatch.setattr(retrain, "subset_config", subset_then_kill)
    with pytest.raises(Killed):
        RetrainJob(_retrain(retrain_inputs, out)).run()
    monkeypatch.setattr(retrain, "subset_config", real)
    assert not [p.name for p in out.iterdir() if p.name.endswith(".tmp")]
    with pytest.raises(FalsifyError, match="--resume"):   # a plain rerun says how to go on
        RetrainJob(_retrain(retrain_inputs, out)).run()
    with pytest.raises(Killed, match="before"):   # --resume reaches the first stage
        RetrainJob(_retrain(retrain_inputs, out, resume=True), on_stage=_stop_at).run()
    for name in ("validation", "retraining"):
        cfg = tomllib.loads((out / f"config-{name}.toml").read_text())
        assert cfg["dims"]["background"]["values"] == ([0] if name == "validation" else [5])
    assert json.loads((out / "stages.json").read_text())["done"] == {}


def _cross_device(monkeypatch, sources: Path) -> None:
    """Renames out of `sources` fail as between two file systems (a tmpfs /tmp and the disk);
    copies run through shutil.copyfileobj (no sendfile), so a test can stop them."""
    real_replace, real_rename = os.replace, os.rename

    def refuse(real):
        def rename(src, dst, *a, **k):
            if Path(src).is_relative_to(sources) and not Path(dst).is_relative_to(sources):
                raise OSError(errno.EXDEV, os.strerror(errno.EXDEV), str(src))
            return real(src, dst, *a, **k)
        return rename

    monkeypatch.setattr(os, "replace", refuse(real_replace))
    monkeypatch.setattr(os, "rename", refuse(real_rename))
    monkeypatch.setattr(shutil, "_USE_CP_SENDFILE", False)


def _copy_killed_after(monkeypatch, nbytes: int, after_files: int = 0) -> None:
    """The (after_files + 1)th copy writes `nbytes` and is killed."""
    real, copies = shutil.copyfileobj, []

    def copy(fsrc, fdst, length=0):
        copies.append(fsrc)
        if len(copies) <= after_files:
            return real(fsrc, fdst)
        fdst.write(fsrc.read(nbytes))
        raise Killed("mid-copy")

    monkeypatch.setattr(shutil, "copyfileobj", copy)


def test_move_file_across_file_systems_is_whole_or_absent(tmp_path, monkeypatch) -> None:
    from falsify.fileio import move_file

    src_dir, dst_dir = tmp_path / "tmpfs", tmp_path / "disk"
    src_dir.mkdir()
    data = os.urandom(300_000)
    (src_dir / "m.onnx").write_bytes(data)
    _cross_device(monkeypatch, src_dir)
    with monkeypatch.context() as mp:
        _copy_killed_after(mp, 1000)
        with pytest.raises(Killed):
            move_file(src_dir / "m.onnx", dst_dir / "m.onnx")
    assert os.listdir(dst_dir) == [] and (src_dir / "m.onnx").read_bytes() == data
    move_file(src_dir / "m.onnx", dst_dir / "m.onnx")
    assert (dst_dir / "m.onnx").read_bytes() == data and not (src_dir / "m.onnx").exists()
    assert os.listdir(dst_dir) == ["m.onnx"]


@pytest.mark.slow   # a whole trade-off run: the CRF variants exported and scored (~15 s)
def test_tradeoff_killed_while_moving_its_models_leaves_no_short_model(tmp_path,
                                                                       monkeypatch) -> None:
    """`falsify tradeoff --knobs crf` with /tmp on another file system (tmpfs), killed while it
    moves the variant models into OUT/models/ (before: shutil.move copied into the final name,
    leaving a short .onnx there); then run again, every model loads."""
    pytest.importorskip("torch")   # the CRF knob's models are exported
    import onnx

    from falsify.cli import main

    tmp = tmp_path / "tmp"
    tmp.mkdir()
    monkeypatch.setattr("tempfile.tempdir", str(tmp))
    (tmp_path / "tiny.toml").write_text(TRADEOFF_CONFIG)
    out = tmp_path / "out"
    argv = ["tradeoff", str(tmp_path / "tiny.toml"), "--out", str(out), "--knobs", "crf",
            "--limit", "1"]
    _cross_device(monkeypatch, tmp)
    monkeypatch.setattr("falsify.bench.tradeoff.TIMING_ROUNDS", 1)
    with monkeypatch.context() as mp:
        _copy_killed_after(mp, 4096, after_files=1)   # a spec moved, then its model stopped
        with pytest.raises(Killed):
            main(argv)
    for f in (out / "models").iterdir():
        assert not f.name.startswith("."), f   # no temporary file left
        if f.suffix == ".onnx":
            onnx.load(str(f))
    assert main(argv) == 0
    models = sorted(f.name for f in (out / "models").iterdir())
    assert models == sorted(f"squeezeseg-crf{k}{s}" for k in range(3) for s in (".json", ".onnx"))
    for f in (out / "models").glob("*.onnx"):
        onnx.load(str(f))


def test_atomic_path_leaves_a_users_tmp_file_alone(tmp_path: Path) -> None:
    """Its temporary was NAME.tmp: a user's m.tmp beside m.pt was overwritten, then deleted."""
    from falsify.fileio import atomic_path

    mine = tmp_path / "m.tmp"
    mine.write_bytes(b"mine")
    with atomic_path(tmp_path / "m.pt") as tmp:
        assert tmp.name == "m.pt"
        tmp.write_bytes(b"weights")
    assert mine.read_bytes() == b"mine"
    assert (tmp_path / "m.pt").read_bytes() == b"weights"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.pt", "m.tmp"]
