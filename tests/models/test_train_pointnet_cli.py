"""`falsify train-pointnet`: option values checked before anything is written, a checkpoint each
epoch, an exact --resume after a stop, one JSON document with --json, held-out scans refused."""

from __future__ import annotations

import json
import os
import shlex
import signal
import subprocess
import sys

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from falsify.cli import build_parser  # noqa: E402
from falsify.cli import main as falsify_main  # noqa: E402
from falsify.cli.signals import Terminated  # noqa: E402
from falsify.models import train_pointnet  # noqa: E402
from tests.models.conftest import copy_of  # noqa: E402

ARGS = ["--batch", "2", "--points", "64", "--seed", "3"]


@pytest.fixture(autouse=True)
def _no_holdout_from_env(monkeypatch):
    monkeypatch.delenv("FALSIFY_HOLDOUT", raising=False)


def main(argv: list[str]) -> int:
    """`falsify train-pointnet ARGV`."""
    return falsify_main(["train-pointnet", *argv])


def _log(out) -> list[dict]:
    return [json.loads(line) for line in (out / "train_log.jsonl").read_text().splitlines()]


@pytest.mark.parametrize("argv, option", [
    (["--batch", "0"], "--batch"), (["--points", "0"], "--points"),
    (["--lr", "-1"], "--lr"), (["--lr", "nan"], "--lr"), (["--lr", "inf"], "--lr"),
    (["--epochs", "0"], "--epochs"), (["--epochs", "-3"], "--epochs"),
    (["--seed", "-1"], "--seed"), (["--time-limit-min", "0"], "--time-limit-min"),
    (["--val-data", "nosuch"], "--val-data"),
])
def test_bad_values_exit_2_in_one_line_and_write_nothing(data, tmp_path, capsys, argv, option):
    out = tmp_path / "o"
    assert main(["--data", str(data), "--out", str(out), *ARGS, *argv]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"falsify: error: {option}"), err
    assert not out.exists()


def test_kitti4_labelled_data_is_refused(data, tmp_path, capsys):
    k4 = copy_of(data, tmp_path / "k4", labels="kitti4")
    assert main(["--data", str(k4), "--out", str(tmp_path / "o"), *ARGS]) == 2
    assert "--labels semantickitti" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_a_scan_without_a_valid_point_is_named(data, tmp_path, capsys):
    empty = copy_of(data, tmp_path / "empty")
    scan = np.load(empty / "scan_2.npy")
    scan[..., 4] = 0
    np.save(empty / "scan_2.npy", scan)
    assert main(["--data", str(empty), "--out", str(tmp_path / "o"), *ARGS]) == 2
    assert "scan_2.npy: no valid point" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("how", ["env", "option", "val"])
def test_held_out_scans_are_refused(data, tmp_path, capsys, monkeypatch, how):
    manifest = tmp_path / "hold.toml"
    assert falsify_main(["holdout", str(data), "--out", str(manifest)]) == 0
    capsys.readouterr()
    out = tmp_path / "o"
    argv = ["--data", str(data), "--out", str(out), *ARGS]
    if how == "env":
        monkeypatch.setenv("FALSIFY_HOLDOUT", str(manifest))
    elif how == "option":
        argv += ["--holdout", str(manifest)]
    else:   # training data elsewhere, the held-out scans as --val-data
        train = tmp_path / "train"
        train.mkdir()
        np.save(train / "a.npy", np.load(next(data.glob("*.npy")))[::-1].copy())
        argv = ["--data", str(train), "--val-data", str(data), "--out", str(out), *ARGS,
                "--holdout", str(manifest)]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "held-out scan" in err and ("--val-data" if how == "val" else "--data") in err
    assert not out.exists()


def test_help_states_every_default():
    sub = build_parser()._subparsers._group_actions[0].choices["train-pointnet"]
    for action in sub._actions:
        if action.required or action.nargs == 0 or action.dest == "holdout":
            continue
        assert "default" in (action.help or ""), action.dest


def test_json_prints_one_document_and_a_rerun_needs_resume(data, val, tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["--data", str(data), "--out", str(out), "--epochs", "1", "--val-data",
                 str(val), *ARGS, "--json"]) == 0
    captured = capsys.readouterr()
    summary = json.loads(captured.out)   # the whole of stdout: one strict JSON document
    assert summary["stopped"] == "done" and (summary["epoch"], summary["epochs"]) == (1, 1)
    assert 0 <= summary["val_miou"] <= 1 and "epoch 1/1" in captured.err
    for name in ("checkpoint.pt", "train_log.jsonl", "pointnet.pt", "pointnet.onnx",
                 "pointnet.json"):
        assert (out / name).is_file(), name
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    # the same --out again without --resume: refused, the run untouched (no appended log)
    assert main(["--data", str(data), "--out", str(out), "--epochs", "2", *ARGS]) == 2
    assert "--resume" in capsys.readouterr().err
    # --resume with an option that decides the weights changed: refused, naming it
    for argv, key in [(["--points", "32"], "points"), (["--lr", "0.01"], "lr"),
                      (["--batch", "1"], "batch"), (["--seed", "4"], "seed")]:
        changed = dict(zip(ARGS[::2], ARGS[1::2], strict=True)) | {argv[0]: argv[1]}
        assert main(["--data", str(data), "--out", str(out), "--epochs", "2", "--resume",
                     *[v for kv in changed.items() for v in kv]]) == 2
        assert f"{key} differs" in capsys.readouterr().err
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before


def test_a_stop_after_an_epoch_resumes_bit_identical(data, tmp_path, capsys, monkeypatch):
    full, part = tmp_path / "full", tmp_path / "part"
    assert main(["--data", str(data), "--out", str(full), "--epochs", "3", *ARGS]) == 0
    capsys.readouterr()

    write_log = train_pointnet._write_log

    def stop_after_epoch_1(out, log):   # as a SIGTERM right after epoch 1's checkpoint
        write_log(out, log)
        if len(log) == 1:
            raise Terminated()

    monkeypatch.setattr(train_pointnet, "_write_log", stop_after_epoch_1)
    assert main(["--data", str(data), "--out", str(part), "--epochs", "3", *ARGS]) == 143
    monkeypatch.setattr(train_pointnet, "_write_log", write_log)
    err = capsys.readouterr().err.strip()
    assert "continue with: falsify train-pointnet" in err and err.endswith("--resume")
    assert [r["epoch"] for r in _log(part)] == [1] and not (part / "pointnet.pt").exists()
    assert torch.load(part / "checkpoint.pt", weights_only=True)["epoch"] == 1

    again = shlex.split(err.split("continue with: ", 1)[1])
    assert falsify_main(again[1:]) == 0
    assert [r["epoch"] for r in _log(part)] == [1, 2, 3]   # not recomputed, not duplicated
    assert [r["loss"] for r in _log(part)] == [r["loss"] for r in _log(full)]
    assert (part / "pointnet.pt").read_bytes() == (full / "pointnet.pt").read_bytes()
    # --epochs may grow; fewer than trained is refused
    assert main(["--data", str(data), "--out", str(part), "--epochs", "2", *ARGS,
                 "--resume"]) == 2
    assert "trained 3 epochs already" in capsys.readouterr().err


def test_time_limit_stops_after_an_epoch_and_resume_goes_on(data, tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["--data", str(data), "--out", str(out), "--epochs", "3", *ARGS,
                 "--time-limit-min", "1e-9", "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert (summary["stopped"], summary["epoch"]) == ("time_limit", 1)
    assert (out / "pointnet.pt").is_file()
    assert main(["--data", str(data), "--out", str(out), "--epochs", "2", *ARGS,
                 "--resume", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["epoch"] == 2
    assert [r["epoch"] for r in _log(out)] == [1, 2]


def test_sigterm_keeps_the_finished_epochs(data, tmp_path):
    """A real SIGTERM to a running `falsify train-pointnet`: exit 143, the command that goes on,
    and a checkpoint and log that agree on the epochs finished."""
    out = tmp_path / "run"
    cmd = [sys.executable, "-m", "falsify", "train-pointnet", "--data", str(data), "--out",
           str(out), "--epochs", "100000", *ARGS]
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=env)
    try:
        first = proc.stdout.readline()
        assert first.startswith("epoch 1/100000"), first + proc.stderr.read()
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=60)
    finally:
        proc.kill()
    assert proc.returncode == 143, err
    assert "terminated" in err and err.strip().endswith("--resume")
    done = torch.load(out / "checkpoint.pt", weights_only=True)["epoch"]
    assert [r["epoch"] for r in _log(out)] == list(range(1, done + 1))
    assert not (out / "pointnet.pt").exists()
