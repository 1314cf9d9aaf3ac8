"""Reading a run's store: `read_frame` reads columns of numbers into numpy a chunk at a time and
orders rows in numpy, and must give the frame pandas' read_sql_query gives, value for value,
dtype for dtype, byte for byte in CSV and Parquet, whatever the columns hold."""

from __future__ import annotations

import io
import sqlite3
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from falsify.results.store import FRAME_QUERY, READ_CHUNK, STORE_NAME, Store, read_frame
from falsify.world.space import load_space
from tests.runfixture import SMOKE, random_samples, write_run


def _pandas(path: Path) -> pd.DataFrame:
    """The frame as pandas reads it, the reference."""
    with sqlite3.connect(path / STORE_NAME) as db:
        return pd.read_sql_query(FRAME_QUERY, db)


def _same(path: Path) -> pd.DataFrame:
    mine, ref = read_frame(path), _pandas(path)
    pd.testing.assert_frame_equal(mine, ref, check_exact=True, check_column_type=True,
                                  check_index_type=True)
    assert list(mine.dtypes) == list(ref.dtypes) and mine.columns.dtype == ref.columns.dtype
    assert mine.to_csv(index=False) == ref.to_csv(index=False)
    pytest.importorskip("pyarrow")
    assert _parquet(mine) == _parquet(ref)
    return mine


def _parquet(frame: pd.DataFrame) -> bytes | str:
    """The frame's Parquet bytes, or the error that refuses it (a column of mixed types)."""
    buf = io.BytesIO()
    try:
        frame.to_parquet(buf, index=False)
    except Exception as exc:   # noqa: BLE001 - the error itself is compared
        return f"{type(exc).__name__}: {exc}"
    return buf.getvalue()


def _table(path: Path, columns: dict[str, str], rows: list[tuple]) -> Path:
    """A samples table of the declared `columns` holding `rows`, beside an empty run table."""
    path.mkdir()
    with sqlite3.connect(path / STORE_NAME) as db:
        db.execute("CREATE TABLE run (key TEXT PRIMARY KEY, value TEXT)")
        db.execute(f"CREATE TABLE samples ({', '.join(f'{n} {t}' for n, t in columns.items())})")
        db.executemany(f"INSERT INTO samples VALUES ({', '.join('?' * len(columns))})", rows)
    return path


def test_a_search_run_reads_as_pandas_reads_it_in_any_arrival_order(tmp_path: Path) -> None:
    """Thousands of rows over chunk boundaries, invalid and undefined rows (NULL metrics),
    columns all NULL (the other classes' IoUs); then the same rows arrived in reverse, as
    concurrent workers leave them before `renumber`."""
    n = 2 * READ_CHUNK + 77
    run = write_run(tmp_path / "run", command="search", samples=random_samples(
        load_space(SMOKE), n, seed=3), invalid_every=13, undefined_every=29)
    frame = _same(run)
    assert len(frame) == n and frame["pedestrian_iou"].dtype == object   # all NULL
    assert frame["car_iou"].dtype == np.float64 and frame["car_iou"].isna().any()
    assert frame["eval_index"].dtype == np.int64 and frame["car_points"].dtype == np.int64
    with sqlite3.connect(run / STORE_NAME) as db:
        db.execute("UPDATE samples SET eval_index = ? - eval_index", (n - 1,))
    frame = _same(run)
    assert list(frame["eval_index"]) == list(range(n))


def test_every_kind_of_column_reads_as_pandas_reads_it(tmp_path: Path) -> None:
    """Integers with a NULL in a later chunk only (float64), integers mixed with fractions,
    integers past 2**53 (exact int64), a column of numbers holding text, text with NULLs,
    floats that are integral, infinities and -0.0."""
    n = READ_CHUNK + 10
    rows = [(n - 1 - i, i, None if i == n - 1 else i, i + 0.5 if i % 7 else i,
             2 ** 60 + i, float(i), float("inf") if i == 5 else -0.0 if i == 6 else i / 3,
             None if i % 3 else f"r{i}", "ok")
            for i in range(n)]
    cols = {"eval_index": "INTEGER", "a": "INTEGER", "late_null": "INTEGER",
            "mixed": "INTEGER", "big": "INTEGER", "real_int": "REAL", "f": "REAL",
            "text": "TEXT", "status": "TEXT"}
    frame = _same(_table(tmp_path / "kinds", cols, rows))
    assert frame["big"].dtype == np.int64 and frame["big"].iloc[0] == 2 ** 60 + n - 1
    assert frame["late_null"].dtype == np.float64 and frame["mixed"].dtype == np.float64
    rows[100] = rows[100][:5] + ("oops",) + rows[100][6:]   # text in a REAL column
    assert _same(_table(tmp_path / "text", cols, rows))["real_int"].dtype == object


@pytest.mark.parametrize("case", ["empty", "ties", "null index"])
def test_tables_the_fast_path_cannot_order_read_as_pandas_reads_them(tmp_path: Path,
                                                                    case: str) -> None:
    """No rows, eval_index tied or NULL: read by pandas itself."""
    cols = {"eval_index": "INTEGER", "x": "REAL", "status": "TEXT"}
    rows = [(i % 3 if case == "ties" else None if case == "null index" and i == 4 else i,
             i / 2, "ok") for i in range(0 if case == "empty" else 9)]
    if case == "ties":   # SQLite's own order among ties: assert only the same multiset
        mine = read_frame(_table(tmp_path / "t", cols, rows))
        ref = _pandas(tmp_path / "t")
        assert sorted(map(tuple, mine.to_numpy().tolist())) == \
            sorted(map(tuple, ref.to_numpy().tolist()))
        assert list(mine["eval_index"]) == sorted(mine["eval_index"])
        return
    _same(_table(tmp_path / "t", cols, rows))


def test_a_store_being_written_reads_one_snapshot(tmp_path: Path) -> None:
    """A run still open for writing (its rows in the -wal) reads as pandas reads it."""
    space = load_space(SMOKE)
    run = write_run(tmp_path / "run", command="search",
                    samples=random_samples(space, 50, seed=1))
    from tests.runfixture import synthetic_result
    store = Store(run / STORE_NAME, space)   # held open: its next rows stay in the -wal
    try:
        store.add([synthetic_result(s, 0.4, i) for i, s in
                   enumerate(random_samples(space, 30, seed=2))], "m", "c")
        assert (run / f"{STORE_NAME}-wal").exists()
        assert len(_same(run)) == len(store)
    finally:
        store.close()
