"""Audit 7: odd paths given to grid, search, scan, dataset, report and gate (too long for SQLite
or for the file system, bytes that are not UTF-8, a non-UTF-8 locale) work or exit 2 with one
line naming the file, never a traceback and never a half-written output."""

from __future__ import annotations

import json
import os
import sqlite3
import subprocess
import sys
from pathlib import Path

import pytest

from falsify.cli import main
from falsify.fileio import write_text
from falsify.results.runlock import LOCK_NAME, RunLock, holder
from falsify.results.store import STORE_NAME
from tests.runfixture import SMOKE, write_run


def deep(base: Path, total: int, name: str = "D" * 200) -> Path:
    """A path under `base` of about `total` bytes, in components of `len(name)` bytes."""
    path = base.absolute()
    while len(os.fsencode(path)) + len(name) + 1 < total:
        path = path / name
    return path


def one_error_line(capsys) -> str:
    """The single line a refused command printed on stderr."""
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("falsify: error: "), err
    return err[0]


def test_out_too_long_for_sqlite_exits_2_and_leaves_nothing(tmp_path, capsys):
    """Before: a traceback (sqlite3.OperationalError: unable to open database file) for an --out
    whose store path passes SQLite's 512 bytes; after: exit 2 naming the store and the cause."""
    out = deep(tmp_path, 700) / "run"
    assert main(["grid", str(SMOKE), "--out", str(out), "--quiet", "--no-report"]) == 2
    line = one_error_line(capsys)
    assert STORE_NAME in line and "longer than SQLite takes" in line
    assert list(tmp_path.iterdir()) == []   # no run folder, lock or store left


@pytest.mark.parametrize("command", [
    ["grid", str(SMOKE), "--quiet"], ["scan", str(SMOKE)], ["dataset", str(SMOKE), "--scans", "1"],
    ["report", "RUN", "--no-predict"]])
def test_out_past_path_max_exits_2(command, tmp_path, capsys):
    """Before: OSError [Errno 36] File name too long, as a traceback from Path.exists; after:
    exit 2, one line naming --out, nothing written."""
    (tmp_path / "d").mkdir()
    out = deep(tmp_path / "d", 4300, "L" * 255) / ("r.html" if command[0] == "report" else "o")
    argv = [a if a != "RUN" else str(tmp_path) for a in command]
    assert main([*argv, "--out", str(out)]) == 2
    assert "--out" in one_error_line(capsys)
    assert list((tmp_path / "d").iterdir()) == []


def test_gate_junit_past_path_max_exits_2(tmp_path, capsys):
    """Before: a traceback from the JUnit writer; after: exit 2 naming the path."""
    write_run(tmp_path / "run")
    junit = deep(tmp_path, 4300, "J" * 255) / "j.xml"
    assert main(["gate", str(tmp_path / "run"), "--max-blind-spots", "99", "--junit",
                 str(junit)]) == 2
    capsys.readouterr()   # the verdict was printed before the JUnit file was tried


def test_lock_of_a_non_utf8_path_is_written_and_read(tmp_path):
    """Before: UnicodeEncodeError writing the lock of `--out $'o\\xe9'` (argv holds the byte as
    a surrogate), leaving the folder and its .lock; after: its bytes, read back by `holder`."""
    out = tmp_path / os.fsdecode(b"o\xe9")
    command = f"falsify grid smoke.toml --out {out}"
    with RunLock(out, command=command):
        assert (out / LOCK_NAME).read_bytes().endswith(os.fsencode(command) + b"\n")
        assert holder(out / LOCK_NAME).startswith(f"process {os.getpid()} (falsify grid")
    assert not out.exists()


def test_write_text_keeps_the_bytes_of_a_non_utf8_path(tmp_path):
    """Before: UnicodeEncodeError writing report.html of a run whose path holds a Latin-1 byte
    (after every sample was scored); after: the path's own bytes."""
    path = os.fsdecode(b"runs/caf\xe9")
    write_text(tmp_path / "page.html", f"<p>{path}</p>")
    assert (tmp_path / "page.html").read_bytes() == b"<p>runs/caf\xe9</p>"


def test_grid_with_a_non_utf8_out_writes_its_report(tmp_path, capsys):
    """The whole run on such a folder: rows, summary and report written, exit 0."""
    out = tmp_path / os.fsdecode(b"caf\xe9 run")
    assert main(["grid", str(SMOKE), "--out", str(out), "--quiet", "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["samples"] == 8
    assert (out / "report.html").stat().st_size > 0 and not (out / LOCK_NAME).exists()
    with sqlite3.connect(out / STORE_NAME) as db:
        assert db.execute("SELECT count(*) FROM samples").fetchone() == (8,)


def test_utf8_config_runs_under_a_non_utf8_locale(tmp_path):
    """Before: `falsify grid` of a UTF-8 config with a non-ASCII comment died with a
    UnicodeDecodeError under LC_ALL=C (no locale coercion): the stored config text was read in
    the locale's encoding; after: read as UTF-8, the bytes of the file, in any locale."""
    config = tmp_path / "smoke.toml"
    config.write_bytes(b"# caf\xc3\xa9 \xc3\xbc\n" + SMOKE.read_bytes())
    env = {**os.environ, "LC_ALL": "C", "LANG": "C", "PYTHONCOERCECLOCALE": "0",
           "PYTHONUTF8": "0", "PYTHONIOENCODING": ""}
    code = ("import sys; from falsify.cli import main; sys.exit(main(['grid', sys.argv[1], "
            "'--out', sys.argv[2], '--quiet', '--no-report']))")
    done = subprocess.run([sys.executable, "-c", code, str(config), str(tmp_path / "run")],
                          env=env, capture_output=True, text=True, timeout=120,
                          cwd=Path(__file__).resolve().parents[2])
    assert done.returncode == 0, done.stderr[-2000:]
    with sqlite3.connect(tmp_path / "run" / STORE_NAME) as db:
        text = json.loads(db.execute("SELECT value FROM run WHERE key = 'config_text'")
                          .fetchone()[0])
    assert text.encode("utf-8") == config.read_bytes()
