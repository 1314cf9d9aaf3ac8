"""The command a stopped grid or search prints to go on: pasted in a shell in another folder it
continues the same run (relative --out, config and model, options after `--`, values spelt like
options), and `--resume` from another folder goes on with the same config by any path, or names
what differs in another."""

from __future__ import annotations

import json
import os
import shlex
import signal
import sqlite3
import stat
import subprocess
import sys
import time
from pathlib import Path

import pytest

from falsify.cli import build_parser, main
from falsify.cli.run import _stopped_text, run_folder
from falsify.results.store import STORE_NAME, read_frame
from tests.conftest import CONFIGS, ROOT

BUNDLED = ROOT / "models" / "weights" / "squeezeseg.onnx"
# Stands for `falsify` on PATH: says where the shell ran it, and with which words.
RECORDER = f"""#!{sys.executable}
import json, os, sys
print(json.dumps([os.getcwd(), sys.argv[1:]]))
"""


def _shell(command: str, cwd: Path, bin_dir: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "PATH": f"{bin_dir}{os.pathsep}{os.environ['PATH']}"}
    return subprocess.run(["bash", "-c", command], cwd=cwd, env=env, capture_output=True,
                          text=True, timeout=300)


def _on_path(tmp_path: Path, script: str) -> Path:
    """A folder holding an executable `falsify` running `script`."""
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir(exist_ok=True)
    exe = bin_dir / "falsify"
    exe.write_text(script)
    exe.chmod(exe.stat().st_mode | stat.S_IXUSR)
    return bin_dir


def _resolved(args, cwd: Path) -> tuple[Path, Path, Path | None]:
    """The config, run folder and model a parsed grid or search names, seen from `cwd`."""
    def at(p: str) -> Path:
        return (cwd / p).resolve()
    return at(args.config), at(args.out), None if args.model is None else at(args.model)


@pytest.mark.parametrize(("argv", "stored", "cd"), [
    (["grid", "cfg/space.toml", "--out", "runs/r1", "--quiet"], True, True),
    (["grid", "cfg/space.toml", "--out", "runs/r1", "--quiet"], False, True),
    (["grid", "--out=-weird", "--quiet", "--", "-dash.toml"], True, True),
    (["grid", "--out=-weird", "--", "-dash.toml"], False, True),
    (["search", "ABS/space.toml", "--out", "ABS/run", "--model", "nets/my.onnx",
      "--algorithm", "random", "--budget", "5", "--threshold", "-0.5"], True, True),
    (["grid", "--out", "runs/r2", "--resume", "--", "--resume"], False, True),
    (["grid", "--out=ABS/run", "--", "-dash.toml"], True, True),
    (["grid", "--quiet", "--out", "ABS/run", "--objective", "x" * 5000, "ABS/space.toml"],
     True, False),
], ids=["relative", "relative-nothing-stored", "dashes", "dashes-nothing-stored",
        "relative-model", "config-named-resume", "relative-config-after-dashes",
        "all-absolute"])
def test_the_printed_command_continues_the_run_from_any_folder(tmp_path, monkeypatch, argv,
                                                               stored, cd):
    """Pasted in another folder, the printed command runs with the same config, run folder and
    model (before: relative paths named other files or none there; a `--` before the config
    turned the appended --resume into a stray argument, `unrecognized arguments: --resume`)."""
    start, elsewhere = tmp_path / "start", tmp_path / "elsewhere"
    for folder in (start / "cfg", start / "nets", elsewhere, start / "ABS"):
        folder.mkdir(parents=True)
    for f in ("cfg/space.toml", "-dash.toml", "nets/my.onnx", "ABS/space.toml", "--resume"):
        (start / f).write_text("")
    argv = [a.replace("ABS", str(start / "ABS")) for a in argv]
    monkeypatch.chdir(start)
    out = run_folder(argv)
    assert out is not None
    if stored:
        out.mkdir(parents=True, exist_ok=True)
        (out / STORE_NAME).write_bytes(b"")
    line = _stopped_text(argv, out, 3 if stored else None)
    command = line.split("continue with: " if stored else "run it again with: ", 1)[1]
    assert command.startswith(f"cd {shlex.quote(str(start))} && falsify ") is cd, command
    want = build_parser().parse_args(argv)

    done = _shell(command, elsewhere, _on_path(tmp_path, RECORDER))
    assert done.returncode == 0, (command, done.stderr)
    cwd, words = json.loads(done.stdout)
    got = build_parser().parse_args(words)
    assert _resolved(got, Path(cwd)) == _resolved(want, start)
    assert got.resume is stored
    assert got.quiet == want.quiet and got.threshold == want.threshold


@pytest.mark.parametrize(("argv", "out"), [
    (["grid", "c.toml", "--out", "a", "--out", "b"], "b"),
    (["grid", "c.toml", "--out=a", "--out", "b"], "b"),
    (["grid", "c.toml", "--out", "a", "--out=b"], "b"),
    (["grid", "c.toml", "--ou", "a"], "a"),
    (["search", "--out=x", "--algorithm", "random", "--", "--out"], "x"),
])
def test_the_run_folder_read_before_the_parser_is_the_one_argparse_reads(argv, out):
    """The folder locked early and named when a run stops is the --out argparse takes: the last
    one given, an abbreviation, not a positional after `--` (before: the first `--out DIR`)."""
    assert run_folder(argv) == Path(out) == Path(build_parser().parse_args(argv).out)


SMALL = (CONFIGS / "smoke.toml").read_text()


@pytest.mark.skipif(not BUNDLED.exists(), reason="bundled model not trained yet")
def test_resume_from_another_folder_goes_on_with_the_same_config_and_names_what_differs(
        tmp_path, monkeypatch, capsys):
    """The run's config is identified by its contents: a copy reached by another relative path
    from another folder goes on; another config is refused naming its keys that differ (before:
    'config_hash differs' and two hashes), a comment added naming that alone."""
    first, second = tmp_path / "first", tmp_path / "second"
    (first / "cfg").mkdir(parents=True)
    (second / "other").mkdir(parents=True)
    (first / "cfg" / "space.toml").write_text(SMALL)
    monkeypatch.chdir(first)
    assert main(["grid", "cfg/space.toml", "--out", "runs/r", "--quiet", "--no-report"]) == 0
    capsys.readouterr()
    before = (first / "runs" / "r" / STORE_NAME).read_bytes()
    monkeypatch.chdir(second)
    copy = second / "other" / "space.toml"
    copy.write_text(SMALL.replace("seed = 0", "seed = 1").replace("step = 6.0", "step = 3.0"))
    run = ["--out", "../first/runs/r", "--quiet", "--no-report", "--resume"]
    assert main(["grid", "other/space.toml", *run]) == 2
    err = capsys.readouterr().err.strip()
    assert err == ("falsify: error: --resume: config_hash differs from the run in ../first/runs/r:"
                   " other/space.toml differs from the config it started with (dims.y.step: "
                   "6.0 there, 3.0 now; seed: 0 there, 1 now); continue with the config it "
                   "started with, or choose another --out")
    copy.write_text(SMALL + "# tuned later\n")
    assert main(["grid", "other/space.toml", *run]) == 2
    assert "only in comments or layout" in capsys.readouterr().err
    assert (first / "runs" / "r" / STORE_NAME).read_bytes() == before
    copy.write_text(SMALL)
    assert main(["grid", "other/space.toml", *run, "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["samples"] == 8 and summary["computed_this_time"] == 0


def _terminate_after_rows(cmd: list[str], cwd: Path, db: Path, rows: int) -> str:
    """Start `cmd` in `cwd`, SIGTERM it once its store holds `rows` rows; its stderr."""
    proc = subprocess.Popen(cmd, cwd=cwd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            text=True)
    deadline = time.time() + 120
    while time.time() < deadline and proc.poll() is None:
        try:   # read-only: connecting would make the file, a run the command then refuses
            with sqlite3.connect(f"{db.as_uri()}?mode=ro", uri=True, timeout=1) as c:
                if c.execute("SELECT COUNT(*) FROM samples").fetchone()[0] >= rows:
                    break
        except sqlite3.Error:
            pass
        time.sleep(0.05)
    proc.send_signal(signal.SIGTERM)
    return proc.communicate(timeout=120)[1]


@pytest.mark.slow
@pytest.mark.skipif(not BUNDLED.exists(), reason="bundled model not trained yet")
def test_a_terminated_grid_goes_on_with_its_printed_command_in_another_folder(tmp_path):
    """`falsify grid cfg/space.toml --out runs/r` stopped by SIGTERM prints a command that,
    pasted in a shell in another folder, finishes that run (before: 'cfg/space.toml: no such
    config' there, or with the config found, 'runs/r holds no run to resume')."""
    start, elsewhere = tmp_path / "start", tmp_path / "elsewhere"
    (start / "cfg").mkdir(parents=True)
    elsewhere.mkdir()
    text = SMALL.replace("step = 4.0", "step = 1.0").replace("step = 6.0", "step = 2.0")
    (start / "cfg" / "space.toml").write_text(text)   # 5 x 4 positions on 2 streets: 40
    err = _terminate_after_rows([sys.executable, "-m", "falsify", "grid", "cfg/space.toml",
                                 "--out", "runs/r", "--quiet", "--no-report"],
                                start, start / "runs" / "r" / STORE_NAME, 8)
    line = err.strip().splitlines()[-1]
    assert "continue with: " in line, err
    stored = len(read_frame(start / "runs" / "r"))
    assert 8 <= stored < 40, "the run must be stopped in the middle"
    command = line.split("continue with: ", 1)[1]
    assert shlex.split(command)[:3] == ["cd", str(start), "&&"]
    falsify = _on_path(tmp_path, f'#!/bin/sh\nexec {shlex.quote(sys.executable)} -m falsify "$@"\n')
    done = _shell(command + " --json", elsewhere, falsify)
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout)["computed_this_time"] == 40 - stored
    frame = read_frame(start / "runs" / "r")
    assert len(frame) == 40 and frame["sample_key"].is_unique
    assert not list(elsewhere.iterdir())


def test_a_stopped_retrain_with_a_config_after_dashes_prints_a_command_that_parses(
        monkeypatch, capsys):
    """`falsify retrain ... -- -c.toml` stopped: --resume goes before the `--` (before: after
    it, a second config argparse refuses)."""
    import falsify.cli as cli
    from falsify.cli.signals import Terminated

    def stopped(args):
        raise Terminated()

    monkeypatch.setattr(cli.retrain, "run", stopped)
    argv = ["retrain", "--model", "m.onnx", "--train-data", "d", "--validation-backgrounds",
            "0", "--retraining-backgrounds", "5", "--out", "t", "--", "-c.toml"]
    assert cli.main(argv) == 143
    command = capsys.readouterr().err.split("continue with: ", 1)[1]
    words = shlex.split(command)
    assert words[0] == "falsify"
    args = build_parser().parse_args(words[1:])
    assert args.resume and args.config == "-c.toml"


@pytest.mark.skipif(not BUNDLED.exists(), reason="bundled model not trained yet")
def test_gate_names_a_finish_command_that_works_from_its_own_folder(tmp_path, monkeypatch,
                                                                     capsys):
    """A stopped run started in one folder with relative paths, gated from another: the
    command gate prints to finish it names the config, the model and the run as they are seen
    from anywhere (it printed the config and model as typed, relative to the first folder)."""
    first, second = tmp_path / "first", tmp_path / "second"
    (first / "cfg").mkdir(parents=True)
    second.mkdir()
    (first / "cfg" / "space.toml").write_text(SMALL.replace("values = [0, 1]",
                                                            "values = [0, 1, 2]"))
    (first / "net.onnx").write_bytes(BUNDLED.read_bytes())
    (first / "net.json").write_bytes(BUNDLED.with_suffix(".json").read_bytes())
    monkeypatch.chdir(first)
    from falsify.jobs.run import RunRequest, execute

    def stop(progress, final: bool) -> None:
        if progress.done >= 8 and not final:
            raise KeyboardInterrupt   # after the first batch, 8 of 12

    req = RunRequest(config=Path("cfg/space.toml"), out=Path("runs/r"), command="grid",
                     model="net.onnx", report=False)
    with pytest.raises(KeyboardInterrupt):
        execute(req, stop)
    monkeypatch.chdir(second)
    capsys.readouterr()
    assert main(["gate", "../first/runs/r"]) == 2
    err = capsys.readouterr().err
    command = err.split("finish it with `")[1].split("`")[0]
    args = build_parser().parse_args(shlex.split(command)[1:])
    assert _resolved(args, second) == (first / "cfg" / "space.toml", first / "runs" / "r",
                                       first / "net.onnx")
    assert args.resume


@pytest.mark.parametrize("saved", [True, False])
def test_a_stopped_trainings_command_keeps_resume_among_the_options(tmp_path, capsys, saved):
    """train's stop message put --resume after a `--`, where argparse reads it as a stray
    argument; it now goes before it (and a re-run drops only the option)."""
    from types import SimpleNamespace

    from falsify.cli.signals import stopped_training

    checkpoint = tmp_path / "out" / "checkpoint.pt"
    checkpoint.parent.mkdir()
    if saved:
        checkpoint.write_bytes(b"x")
    argv = ["train", "--out", str(checkpoint.parent), "--", "-data"]
    stopped_training(KeyboardInterrupt(), SimpleNamespace(argv=argv), checkpoint, "epochs")
    words = shlex.split(capsys.readouterr().err.rsplit("with: ", 1)[1])
    assert words[words.index("--"):] == ["--", "-data"]
    assert ("--resume" in words[:words.index("--")]) is saved
