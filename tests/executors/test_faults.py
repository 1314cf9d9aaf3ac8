"""The faults users hit mid-run, on the real CLI in subprocesses: a second run on a live run
folder, a full disk, SIGTERM and Ctrl-C. Each ends with exit 2 (or 143 / 130) and one line, no
traceback, no process left behind, and a `--resume` that completes with every sample once."""

from __future__ import annotations

import errno
import fcntl
import os
import re
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import pytest

from falsify.errors import FalsifyError
from falsify.results.runlock import LOCK_NAME, RunLock
from falsify.results.store import disk_full
from tests.conftest import ROOT

BUNDLED = ROOT / "models" / "weights" / "squeezeseg.onnx"
SMALL_GRID = ROOT / "tests" / "data" / "small-grid.toml"   # 24 samples: three chunks of 8
SMOKE = ROOT / "configs" / "smoke.toml"                     # 8 samples
pytestmark = pytest.mark.skipif(not BUNDLED.exists(), reason="bundled model not trained yet")


def falsify(*args: object) -> list[str]:
    return [sys.executable, "-m", "falsify", *map(str, args)]


def stored(run: Path) -> tuple[int, int]:
    """(rows, distinct sample keys) in a run's store, read without writing anything."""
    db = run / "results.sqlite"
    if not db.exists():
        return 0, 0
    try:
        with sqlite3.connect(f"{db.as_uri()}?mode=ro", uri=True, timeout=1) as c:
            return c.execute("SELECT COUNT(*), COUNT(DISTINCT sample_key) FROM samples"
                             ).fetchone()
    except sqlite3.Error:   # not made yet
        return 0, 0


def wait_rows(proc: subprocess.Popen, run: Path, rows: int, timeout: float = 120) -> int:
    """Wait until the run stores at least `rows` rows (or `proc` ends); the rows seen."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and proc.poll() is None:
        n = stored(run)[0]
        if n >= rows:
            return n
        time.sleep(0.05)
    return stored(run)[0]


def session_processes(sid: int) -> list[str]:
    """The live (not zombie) processes of session `sid`: 'pid command' each."""
    out = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            text = stat.read_text()
            cmd = (stat.parent / "cmdline").read_bytes().replace(b"\0", b" ").decode()
        except OSError:   # ended meanwhile
            continue
        state, _ppid, _pgrp, session = text[text.rindex(")") + 2:].split()[:4]
        if int(session) == sid and state != "Z":
            out.append(f"{stat.parent.name} {cmd}")
    return out


def one_line(stderr: str) -> str:
    assert "Traceback" not in stderr, stderr
    lines = [line for line in stderr.splitlines() if line.strip()]
    assert len(lines) == 1, stderr
    return lines[0]


def test_the_run_lock_is_taken_again_by_its_holder_and_leaves_nothing(tmp_path):
    run = tmp_path / "a" / "run"
    with RunLock(run, command="falsify grid x") as outer:
        assert outer.made == [run, run.parent]
        assert (run / LOCK_NAME).read_text() == f"{os.getpid()}\nfalsify grid x\n"
        with RunLock(run) as inner:   # the CLI holds it, then the run job takes it again
            assert inner.made == outer.made
        assert (run / LOCK_NAME).exists()
        fd = os.open(run / LOCK_NAME, os.O_RDWR)   # as another process would: refused
        try:
            with pytest.raises(BlockingIOError):
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        finally:
            os.close(fd)
    assert not (tmp_path / "a").exists()   # the folders it made, empty again, are gone


def test_a_lock_file_left_by_a_killed_run_is_taken_over(tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    (run / "results.sqlite").write_bytes(b"")
    (run / LOCK_NAME).write_text("999999\nfalsify grid killed\n")   # no process holds it
    with RunLock(run):
        assert (run / LOCK_NAME).read_text().startswith(f"{os.getpid()}\n")
    assert sorted(p.name for p in run.iterdir()) == ["results.sqlite"]


def test_a_held_lock_names_its_holder(tmp_path):
    run = tmp_path / "run"
    code = (f"from falsify.results.runlock import RunLock\n"
            f"with RunLock({str(run)!r}, command='falsify grid held'):\n"
            "    print('held', flush=True)\n    input()\n")
    holder = subprocess.Popen([sys.executable, "-c", code], stdin=subprocess.PIPE,
                              stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline() == "held\n"
        with pytest.raises(FalsifyError, match=rf"in use by process {holder.pid} "
                                                r"\(falsify grid held\)"):
            RunLock(run).__enter__()
    finally:
        holder.communicate("\n", timeout=30)
    with RunLock(run):   # released with its holder
        pass


def test_full_disks_are_told_from_other_errors(tmp_path):
    full = sqlite3.OperationalError("database or disk is full")
    full.sqlite_errorcode = sqlite3.SQLITE_FULL
    io = sqlite3.OperationalError("disk I/O error")
    io.sqlite_errorcode = 4874   # SQLITE_IOERR_SHMSIZE: full only where no space is left
    locked = sqlite3.OperationalError("database is locked")
    locked.sqlite_errorcode = sqlite3.SQLITE_BUSY
    assert disk_full(full, tmp_path) and disk_full(OSError(errno.ENOSPC, "full"), tmp_path)
    assert not disk_full(io, tmp_path)   # tmp_path has room
    assert not disk_full(locked, tmp_path) and not disk_full(PermissionError(13, "x"), tmp_path)


def test_a_second_run_on_a_live_run_is_refused_at_once(tmp_path):
    run = tmp_path / "run"
    cmd = falsify("grid", SMOKE, "--out", run, "--quiet", "--no-report")
    first = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 60
        while f"{first.pid}\n" not in _read(run / LOCK_NAME) and time.monotonic() < deadline:
            assert first.poll() is None, first.stderr.read()
            time.sleep(0.02)
        for extra in ([], ["--resume"]):
            started = time.monotonic()
            second = subprocess.run(cmd + extra, capture_output=True, text=True, timeout=60)
            took = time.monotonic() - started
            line = one_line(second.stderr)
            assert second.returncode == 2, second.stderr
            assert f"in use by process {first.pid}" in line and str(run) in line, line
            assert took < 2.0, f"the second run took {took:.2f} s to be refused"
            assert first.poll() is None, "the first run ended before the second was refused"
    finally:
        assert first.wait(timeout=120) == 0, first.stderr.read()
    assert stored(run) == (8, 8)
    assert not (run / LOCK_NAME).exists()


def _read(path: Path) -> str:
    try:
        return path.read_text()
    except OSError:
        return ""


@pytest.fixture
def small_disk(tmp_path):
    """A 400 KB tmpfs (skipped where mounting is not allowed: it needs root, or CAP_SYS_ADMIN)."""
    disk = tmp_path / "disk"
    disk.mkdir()
    try:
        r = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=400k", "tmpfs", str(disk)],
                           capture_output=True, text=True, timeout=30)
    except OSError as exc:
        pytest.skip(f"no mount command to make a small file system: {exc}")
    if r.returncode:
        pytest.skip(f"cannot mount a small tmpfs here: {r.stderr.strip()}")
    yield disk
    subprocess.run(["umount", "-l", str(disk)], capture_output=True, timeout=30)


def fill(disk: Path) -> Path:
    """Take every free byte of `disk` with one file; that file."""
    filler = disk / "filler"
    block = b"\0" * 4096
    with open(filler, "wb", buffering=0) as fh:
        try:
            while True:
                fh.write(block)
        except OSError as exc:
            assert exc.errno == 28, exc   # ENOSPC
    return filler


@pytest.mark.slow
def test_a_full_disk_ends_the_run_in_one_line_and_resume_completes(small_disk):
    run = small_disk / "run"
    cmd = falsify("grid", SMALL_GRID, "--out", run, "--quiet", "--no-report")
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        assert wait_rows(proc, run, 8) < 24, "the run must be stopped in the middle"
        filler = fill(small_disk)
    finally:
        _, err = proc.communicate(timeout=120)
    line = one_line(err)
    assert proc.returncode == 2, err
    n = stored(run)[0]
    assert 8 <= n < 24
    assert str(run) in line and "disk is full" in line, line
    assert f"{n} samples are stored safely" in line, line
    assert line.endswith(f"continue with: falsify grid {SMALL_GRID} --out {run} --quiet "
                         "--no-report --resume"), line
    io = sqlite3.OperationalError("disk I/O error")
    io.sqlite_errorcode = 4874   # SQLITE_IOERR_SHMSIZE, as a store opened on a full disk gets
    assert disk_full(io, run)
    filler.unlink()
    r = subprocess.run(cmd + ["--resume"], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert stored(run) == (24, 24)


def _default_sigint() -> None:
    signal.signal(signal.SIGINT, signal.SIG_DFL)


@pytest.mark.slow
@pytest.mark.parametrize("sig, code, executor", [(signal.SIGTERM, 143, "process"),
                                                 (signal.SIGINT, 130, "process"),
                                                 (signal.SIGTERM, 143, "ray")],
                         ids=["SIGTERM", "Ctrl-C", "SIGTERM-ray"])
def test_a_signal_stops_workers_and_keeps_the_rows(tmp_path, sig, code, executor):
    """Ray's own SIGTERM handler (ray.init installs one) must not replace the clean stop. The
    grid has six streets (72 samples, nine chunks): warm workers or actors finished all 24 of
    two streets between two polls of a busy machine, and the run was never stopped."""
    run = tmp_path / "run"
    grid, total = tmp_path / "grid.toml", 72
    grid.write_text(SMALL_GRID.read_text().replace("values = [0, 5]",
                                                   "values = [0, 5, 1, 2, 3, 4]"))
    cmd = falsify("grid", grid, "--out", run, "--quiet", "--no-report", "--workers", 2,
                  *(["--executor", "ray"] if executor == "ray" else []))
    # As from a terminal: SIGINT at its default even where this test runs in a background job,
    # which ignores it (an ignored SIGINT falsify rightly leaves ignored, as nohup asks).
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                            start_new_session=True, preexec_fn=_default_sigint)
    try:
        assert wait_rows(proc, run, 8) < total, "the run must be stopped in the middle"
        assert len(session_processes(proc.pid)) >= 3   # the driver and its two workers
        if sig == signal.SIGINT:   # Ctrl-C: the terminal signals the whole process group
            os.killpg(proc.pid, sig)
        else:
            os.kill(proc.pid, sig)
        started = time.monotonic()
        _, err = proc.communicate(timeout=60)
        took = time.monotonic() - started
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == code, err
    line = one_line(err)
    assert "resource_tracker" not in err and "leaked" not in err, err
    n = stored(run)[0]
    assert re.search(rf"\b{n} samples are stored safely in {re.escape(str(run))}", line), line
    assert line.endswith(f"continue with: falsify grid {grid} --out {run} --quiet "
                         f"--no-report --workers 2{' --executor ray' * (executor == 'ray')} "
                         "--resume"), line
    # The workers end with the driver; the resource tracker a moment after it.
    left = [p for p in session_processes(proc.pid) if "spawn_main" in p]
    assert not left, left
    deadline = time.monotonic() + 5
    while session_processes(proc.pid) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not session_processes(proc.pid)
    assert took < 10, f"{took:.1f} s from the signal to the end"
    r = subprocess.run(cmd + ["--resume"], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert stored(run) == (total, total)


@pytest.mark.parametrize("command", ["train", "retrain"])
def test_a_stopped_training_names_the_command_that_continues_it(monkeypatch, capsys, command):
    """train and retrain keep their state as they go; stopped, they say how to go on."""
    import falsify.cli as cli
    from falsify.cli.signals import Terminated

    def stopped(args):
        raise Terminated()

    module = next(c.module for c in cli.COMMANDS if c.name == command)
    monkeypatch.setattr(module, "run", stopped)
    argv = [command, "--data", "my scans", "--out", "t"] if command == "train" else [
        command, "c.toml", "--model", "m.onnx", "--train-data", "d", "--validation-backgrounds",
        "0", "--retraining-backgrounds", "5", "--out", "t", "--resume"]
    assert cli.main(argv) == 143
    err = capsys.readouterr().err
    want = "falsify " + " ".join(f"'{a}'" if " " in a else a for a in argv)
    assert err == f"falsify: terminated; continue with: {want}" + (
        "" if "--resume" in argv else " --resume") + "\n"


def test_a_sigterm_stays_a_sigterm_when_a_library_reraises_it_as_ctrl_c():
    """Ray's waits catch the Terminated our handler raises and raise KeyboardInterrupt: the
    exit status still says SIGTERM (143), from the signal the handler took."""
    from falsify.cli.signals import stop_name, stop_signals

    with pytest.raises(KeyboardInterrupt):
        with stop_signals():
            try:
                os.kill(os.getpid(), signal.SIGTERM)
                time.sleep(1)
            except KeyboardInterrupt:
                raise KeyboardInterrupt() from None   # what Ray's ray.wait turned it into
    assert stop_name(KeyboardInterrupt()) == ("terminated", 143)
    with stop_signals():   # the next command starts afresh: a Ctrl-C there is no SIGTERM
        pass
    assert stop_name(KeyboardInterrupt()) == ("interrupted", 130)
