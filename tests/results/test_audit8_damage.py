"""A damaged run store met by --resume (the run's Store) or by a reader: a clear FalsifyError
naming the file and what is wrong, before anything is written to it, never a traceback."""

from __future__ import annotations

import os
import shutil
import sqlite3
import subprocess
from contextlib import closing
from pathlib import Path

import pytest

from falsify.cli import main
from falsify.errors import FalsifyError
from falsify.results.store import STORE_NAME, Store, read_frame, read_meta
from falsify.world.space import load_space
from tests.runfixture import SMOKE, random_samples, synthetic_result, write_run

PAGE = 4096


def _run(tmp_path: Path, n: int = 8) -> Path:
    return write_run(tmp_path / "run", command="search",
                     samples=random_samples(load_space(SMOKE), n, seed=5))


def _sql(run: Path, *statements: str) -> bytes:
    """Run `statements` on the run's store, closed after (its -wal checkpointed); its bytes."""
    with closing(sqlite3.connect(run / STORE_NAME)) as db, db:
        for s in statements:
            db.execute(s)
    return (run / STORE_NAME).read_bytes()


def test_resume_of_a_store_whose_rows_are_damaged_names_the_file(tmp_path: Path) -> None:
    """A page of rows lost (zeroed) while the run's metadata still reads: the run's Store
    refused it with sqlite3.DatabaseError, a traceback out of `grid --resume`."""
    run = _run(tmp_path, 300)
    good = (run / STORE_NAME).read_bytes()
    for page in range(2, len(good) // PAGE + 1):
        bad = bytearray(good)
        bad[(page - 1) * PAGE:page * PAGE] = bytes(PAGE)
        (run / STORE_NAME).write_bytes(bytes(bad))
        try:
            read_meta(run)
            read_frame(run)
        except FalsifyError as exc:
            if "malformed" in str(exc):
                try:
                    read_meta(run)
                    break   # the metadata reads, the rows do not
                except FalsifyError:
                    continue
    else:
        pytest.fail("no page of rows alone to damage")
    with pytest.raises(FalsifyError, match=rf"{STORE_NAME}: not a readable results file "
                       r"\(database disk image is malformed\).* new --out"):
        Store(run / STORE_NAME, load_space(SMOKE))
    assert (run / STORE_NAME).read_bytes() == bytes(bad)


@pytest.mark.parametrize("change, match", [
    ("ALTER TABLE samples DROP COLUMN t_scan", "lacks the columns t_scan that this falsify "
     "writes"),
    ("ALTER TABLE samples DROP COLUMN x", "lacks the columns x that this falsify writes"),
])
def test_a_store_lacking_a_column_is_refused_before_a_sample(tmp_path: Path, change: str,
                                                             match: str) -> None:
    """A store of another version without a column `add` writes (before: accepted, then the
    first batch of results failed to insert, a traceback mid-run)."""
    run = _run(tmp_path)
    before = _sql(run, change)
    with pytest.raises(FalsifyError, match=f"{STORE_NAME}: its samples table {match}"):
        Store(run / STORE_NAME, load_space(SMOKE))
    assert (run / STORE_NAME).read_bytes() == before


def test_a_store_requiring_a_column_falsify_does_not_write_is_refused(tmp_path: Path) -> None:
    """A newer store's NOT NULL column without a default (before: IntegrityError on the first
    insert, a traceback mid-run)."""
    run = _run(tmp_path)
    with closing(sqlite3.connect(run / STORE_NAME)) as db:
        sql = db.execute("SELECT sql FROM sqlite_master WHERE name = 'samples'").fetchone()[0]
    before = _sql(run, "ALTER TABLE samples RENAME TO old",
                  sql.replace("config_hash TEXT", "config_hash TEXT, future TEXT NOT NULL"),
                  "INSERT INTO samples SELECT *, 'x' FROM old", "DROP TABLE old")
    with pytest.raises(FalsifyError, match="requires the columns future that this falsify "
                       "does not write"):
        Store(run / STORE_NAME, load_space(SMOKE))
    assert (run / STORE_NAME).read_bytes() == before


def test_metadata_without_a_samples_table_is_refused(tmp_path: Path) -> None:
    """Before: the samples table was made afresh and every sample computed again, as if the
    damaged file were a new run."""
    run = _run(tmp_path)
    before = _sql(run, "DROP TABLE samples")
    with pytest.raises(FalsifyError, match="holds a run's metadata but no samples table"):
        Store(run / STORE_NAME, load_space(SMOKE))
    assert (run / STORE_NAME).read_bytes() == before


def test_resume_of_a_store_without_metadata_says_so(tmp_path: Path, capsys) -> None:
    """Before: '--resume: config_hash differs (None there, ...)', as if the config had
    changed; readers said its metadata had no config_text."""
    run = write_run(tmp_path / "run")
    before = _sql(run, "DELETE FROM run")
    with pytest.raises(FalsifyError, match=f"{STORE_NAME}: holds no run metadata"):
        read_meta(run)
    assert main(["grid", str(SMOKE), "--out", str(run), "--resume", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "holds no run metadata" in err and str(run) in err and "Traceback" not in err
    assert err.count("\n") == 1 and (run / STORE_NAME).read_bytes() == before
    assert sorted(p.name for p in run.iterdir()) == [STORE_NAME]


def _read_only(path: Path):
    """Make `path` read-only for this process (chmod; chattr +i where run as root), or skip;
    returns the undo."""
    if os.geteuid() != 0:
        mode = path.stat().st_mode
        path.chmod(0o444)
        return lambda: path.chmod(mode)
    if not shutil.which("chattr") or subprocess.run(["chattr", "+i", str(path)],
                                                    capture_output=True).returncode:
        pytest.skip("root, and chattr +i does not work here")
    return lambda: subprocess.run(["chattr", "-i", str(path)], check=True)


def test_resume_of_a_read_only_store_is_refused_before_a_sample(tmp_path: Path) -> None:
    """Before: opened, then the first write (the session's metadata) failed with
    'attempt to write a readonly database', a traceback."""
    run = _run(tmp_path)
    undo = _read_only(run / STORE_NAME)
    try:
        with pytest.raises(FalsifyError, match=f"{STORE_NAME}: cannot be written"):
            Store(run / STORE_NAME, load_space(SMOKE))
    finally:
        undo()
    assert len(read_frame(run)) == 8


def test_a_killed_runs_log_in_a_read_only_folder_is_explained(tmp_path: Path) -> None:
    """A killed run's rows in its -wal, its -shm gone and its folder read-only (a copied or
    mounted artefact): SQLite cannot read it there. Before: 'not a readable results file
    (unable to open database file)', as if the file were damaged."""
    if os.geteuid() != 0:
        pytest.skip("needs a read-only bind mount (root)")
    space = load_space(SMOKE)
    run = write_run(tmp_path / "run", command="search", samples=random_samples(space, 5))
    store = Store(run / STORE_NAME, space)   # held open: its rows stay in the -wal
    store.add([synthetic_result(s, 0.4, i) for i, s in
               enumerate(random_samples(space, 5, seed=9))], "m", "c")
    copy = tmp_path / "copy"
    copy.mkdir()
    for name in (STORE_NAME, f"{STORE_NAME}-wal"):
        shutil.copy(run / name, copy / name)
    store.close()
    ro = tmp_path / "ro"
    ro.mkdir()
    if subprocess.run(["mount", "--bind", str(copy), str(ro)], capture_output=True).returncode:
        pytest.skip("mount --bind is not permitted here")
    try:
        if subprocess.run(["mount", "-o", "remount,bind,ro", str(ro)],
                          capture_output=True).returncode:
            pytest.skip("a read-only remount is not permitted here")
        with pytest.raises(FalsifyError, match=f"{STORE_NAME}-wal .* needs {STORE_NAME}-shm "
                           "beside it.* read-only folder; copy the run folder"):
            read_frame(ro)
    finally:
        subprocess.run(["umount", str(ro)], check=True)
    assert len(read_frame(copy)) == 10   # the rows were all there
