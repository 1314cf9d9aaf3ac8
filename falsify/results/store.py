"""The run's SQLite file: run metadata and one row per sample, committed as results arrive.

Rows are keyed by the sample (its dims as canonical JSON), so a resumed run finds what a killed
one finished and neither recomputes nor duplicates it. WAL mode keeps a kill -9 from losing any
committed row. A Store may be used from several threads (a search running combinations
concurrently): one connection, every use of it and of the key cache under one lock.
"""

from __future__ import annotations

import errno
import json
import os
import shlex
import sqlite3
import threading
import tomllib
from collections.abc import Iterable, Sequence
from contextlib import closing
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from falsify.errors import FalsifyError
from falsify.results.metrics import Scoring, Status
from falsify.results.miou_maps import CellMap, miou_map, with_estimates
from falsify.results.samples import CAR_SCORING, SampleResult, sample_key
from falsify.world.space import DEFAULT_THRESHOLD, RealScan, Sample, Space, parse_space

STORE_NAME = "results.sqlite"
FIXED_COLUMNS = ["eval_index", "sample_key", "status", "reason", "car_points", "label_points",
                 "t_scan", "t_infer", "t_total", "seed", "model_hash", "config_hash"]
TIMING_COLUMNS = ("t_scan", "t_infer", "t_total")


class Store:
    """Append-only result table of one run; `scoring` fixes its metric columns and the column
    `score` reads."""

    def __init__(self, path: str | Path, space: Space, scoring: Scoring = CAR_SCORING):
        self.path = Path(path)
        self.space = space
        self.scoring = scoring
        self.metric_columns = scoring.columns
        self.dim_names = list(space.dims)
        # The columns `add` writes, in its order.
        self.columns = (FIXED_COLUMNS[:2] + self.dim_names + ["status", "reason"]
                        + self.metric_columns + FIXED_COLUMNS[4:])
        # One connection shared by the driver's threads; the lock serialises every use of it.
        self.db = _open_store(self.path)
        self._lock = threading.RLock()
        try:
            self._prepare()
        except BaseException as exc:
            self.db.close()
            if isinstance(exc, sqlite3.DatabaseError) and not disk_full(exc, self.path.parent):
                raise FalsifyError(f"{self.path}: not a readable results file ({exc}); its rows "
                                   "cannot be read to go on from: start the run again in a new "
                                   "--out") from None
            raise

    def _prepare(self) -> None:
        """Make the tables of a new store, or check those of a store being resumed (before
        anything is written to it), and read the keys it holds."""
        for f in (self.path, *(self.path.with_name(self.path.name + x) for x in SIDE_FILES)):
            if f.exists() and not os.access(f, os.W_OK):
                raise FalsifyError(f"{f}: cannot be written (its permissions, a read-only mount "
                                   "or chattr +i); make it writable to go on with --resume, or "
                                   "start the run again in a new --out")
        self.db.execute("PRAGMA synchronous=NORMAL")
        tables = {row[0] for row in self.db.execute(
            "SELECT name FROM sqlite_master WHERE type = 'table'")}
        if "samples" in tables:
            self._check_samples_table()
        elif "run" in tables and self.db.execute("SELECT 1 FROM run LIMIT 1").fetchone():
            raise FalsifyError(f"{self.path}: holds a run's metadata but no samples table (a "
                               "damaged or foreign file); start the run again in a new --out")
        dims = ", ".join(f'"{d}" {_sql_type(self.space, d)}' for d in self.dim_names)
        metrics = ", ".join(f"{m} REAL" for m in self.metric_columns)
        self.db.execute("CREATE TABLE IF NOT EXISTS run (key TEXT PRIMARY KEY, value TEXT)")
        self.db.execute(
            "CREATE TABLE IF NOT EXISTS samples (eval_index INTEGER, sample_key TEXT UNIQUE "
            f"NOT NULL, {dims}, status TEXT NOT NULL, reason TEXT, {metrics}, car_points "
            "INTEGER, label_points INTEGER, t_scan REAL, t_infer REAL, t_total REAL, seed "
            "INTEGER, model_hash TEXT, config_hash TEXT)")
        self.db.commit()
        self._cache: dict[str, float | None] = {
            k: v for k, v in self.db.execute(
                f"SELECT sample_key, {self.scoring.score_column} FROM samples")}

    def _check_samples_table(self) -> None:
        """FalsifyError unless the stored samples table takes the rows `add` writes: every
        column there, and none it lacks a value for (a NOT NULL column without a default, as
        another version of falsify may have made)."""
        info = list(self.db.execute("PRAGMA table_info(samples)"))
        have = {row[1] for row in info}
        if lacking := [c for c in self.columns if c not in have]:
            what = "scores" if set(lacking) <= set(self.metric_columns) else "writes"
            raise FalsifyError(f"{self.path}: its samples table lacks the columns "
                               f"{', '.join(lacking)} that this falsify {what} (a run written "
                               "by another version); start it again in a new --out")
        written = set(self.columns)
        if unset := [row[1] for row in info
                     if row[1] not in written and row[3] and row[4] is None]:
            raise FalsifyError(f"{self.path}: its samples table requires the columns "
                               f"{', '.join(unset)} that this falsify does not write (a run "
                               "written by another version); start it again in a new --out")

    def close(self) -> None:
        with self._lock:
            self.db.close()

    # -- metadata ---------------------------------------------------------------------------
    def set_meta(self, **values) -> None:
        with self._lock, self.db:
            self.db.executemany("INSERT OR REPLACE INTO run VALUES (?, ?)",
                                [(k, json.dumps(v)) for k, v in values.items()])

    def meta(self) -> dict:
        with self._lock:
            return {k: json.loads(v) for k, v in self.db.execute("SELECT key, value FROM run")}

    # -- rows -------------------------------------------------------------------------------
    def __len__(self) -> int:
        with self._lock:
            return len(self._cache)

    def __contains__(self, sample: Sample) -> bool:
        key = sample_key(sample)
        with self._lock:
            return key in self._cache

    def score(self, sample: Sample) -> float | None:
        key = sample_key(sample)
        with self._lock:
            return self._cache[key]

    def add(self, results: Iterable[SampleResult], model_hash: str, config_hash: str) -> int:
        """Insert a batch of results in one transaction (skipping any already stored); returns
        how many rows were new. eval_index is the order of arrival (see `renumber`)."""
        with self._lock:
            rows = []
            for r in results:
                key = sample_key(r.sample)
                if key in self._cache:
                    continue
                self._cache[key] = r.score
                values = [r.sample[d] for d in self.dim_names]
                metrics = [r.metrics.get(m) for m in self.metric_columns]
                rows.append([len(self._cache) - 1, key, *values, str(r.status), r.reason,
                             *metrics, r.car_points, r.label_points, r.t_scan, r.t_infer,
                             r.t_total, r.seed, model_hash, config_hash])
            if not rows:
                return 0
            sql = (f"INSERT INTO samples ({', '.join(_q(c) for c in self.columns)}) VALUES "
                   f"({', '.join('?' * len(self.columns))})")
            try:
                with self.db:
                    self.db.executemany(sql, rows)
            except BaseException:   # rolled back (a full disk, say): forget them too
                for row in rows:
                    del self._cache[row[1]]
                raise
            return len(rows)

    def renumber(self, order: Iterable[Sample]) -> int:
        """Set eval_index to each row's first place in `order` (the sampler's order), rows not
        in it after, as they were; one transaction. Rows of concurrent callers arrive in an
        order that depends on timing; this makes the finished table independent of it (where
        rows arrived in the sampler's order already, as in a sequential run, nothing changes).
        Returns how many rows changed."""
        with self._lock:
            now = dict(self.db.execute("SELECT sample_key, eval_index FROM samples"))
            want: dict[str, int] = {}
            for s in order:
                key = sample_key(s)
                if key in now and key not in want:
                    want[key] = len(want)
            for key in sorted(set(now) - set(want), key=lambda k: now[k]):
                want[key] = len(want)
            changed = [(i, k) for k, i in want.items() if now[k] != i]
            if changed:
                with self.db:
                    self.db.executemany("UPDATE samples SET eval_index = ? WHERE sample_key = ?",
                                        changed)
            return len(changed)


SIDE_FILES = ("-wal", "-shm")   # SQLite's files beside a store in WAL mode


# SQLite's unix VFS refuses a database whose absolute path (with "-journal" added) passes 512
# bytes: past about this many, "unable to open database file" means the path is too long.
SQLITE_PATH_BYTES = 504


def _open_store(path: Path) -> sqlite3.Connection:
    """The store's connection in WAL mode; FalsifyError naming the file when SQLite cannot open
    it (a path too long for SQLite, a folder it cannot write), not a traceback."""
    try:
        db = sqlite3.connect(path, timeout=30.0, check_same_thread=False)
        try:
            db.execute("PRAGMA journal_mode=WAL")
        except BaseException:
            db.close()
            raise
        return db
    except sqlite3.OperationalError as exc:
        if disk_full(exc, path.parent):   # the run's own handler says what a full disk keeps
            raise
        size = len(os.fsencode(os.path.abspath(path)))
        why = (f"its path is {size} bytes, longer than SQLite takes (about "
               f"{SQLITE_PATH_BYTES}): choose a shorter --out" if size > SQLITE_PATH_BYTES
               else "check that its folder can be written")
        raise FalsifyError(f"{path}: SQLite cannot open the run's store ({exc}); {why}") from None
    except sqlite3.DatabaseError as exc:   # not SQLite, or damaged
        raise FalsifyError(f"{path}: not a readable results file ({exc}); start the run again "
                           "in a new --out") from None


def _read_only(path: str | Path, query):
    """Run `query(connection)` on a run's SQLite file opened read-only; clear errors."""
    path = Path(path)
    if path.is_dir():
        path = path / STORE_NAME
    if not path.exists():
        raise FalsifyError(f"{path}: no results file (is this a run directory?)")
    # Without a -wal beside it the file is complete: open it immutable, so that reading never
    # creates -wal or -shm files in a run the reader did not make.
    wal = path.with_name(path.name + "-wal")
    uri = path.absolute().as_uri() + "?mode=ro" + ("" if wal.exists() else "&immutable=1")
    try:
        with closing(sqlite3.connect(uri, uri=True)) as db:
            return query(db)
    except (sqlite3.DatabaseError, pd.errors.DatabaseError) as exc:
        if disk_full(exc, path.parent):
            raise DiskFull(f"{path}: cannot be read: the disk is full") from None
        shm = path.with_name(path.name + "-shm")
        if wal.exists() and not shm.exists() and not os.access(path.parent, os.W_OK):
            raise FalsifyError(f"{path}: cannot be read here: its write-ahead log {wal.name} "
                               "(left by a run that was killed or is still running) needs "
                               f"{shm.name} beside it, which SQLite cannot make in this "
                               "read-only folder; copy the run folder somewhere writable and "
                               "read the copy") from None
        raise FalsifyError(f"{path}: not a readable results file ({exc})") from None


class DiskFull(FalsifyError):
    """A run's file that cannot be read or written because its disk is full."""


LOW_SPACE = 1 << 20   # bytes free under which an I/O error is taken for a full disk


def disk_full(exc: BaseException, folder: Path) -> bool:
    """Whether `exc` means that the disk holding `folder` is full: the OS's or SQLite's "no
    space" (or over quota), DiskFull, or an SQLite I/O error while under LOW_SPACE bytes are
    free (SQLite reports a shared-memory file it cannot grow as an I/O error)."""
    if isinstance(exc, DiskFull):
        return True
    if isinstance(exc, OSError):
        return exc.errno in (errno.ENOSPC, errno.EDQUOT)
    if isinstance(exc, pd.errors.DatabaseError) and exc.__cause__ is not None:
        exc = exc.__cause__   # pandas wraps the sqlite3 error
    code = getattr(exc, "sqlite_errorcode", None)
    if code == sqlite3.SQLITE_FULL:
        return True
    return (code is not None and code & 0xFF == sqlite3.SQLITE_IOERR
            and free_bytes(folder) < LOW_SPACE)


def free_bytes(folder: Path) -> float:
    """Bytes free to this user on the file system of `folder` (or of its nearest existing
    parent: an empty run's folder may be gone); infinite if that cannot be told."""
    while not folder.exists() and folder != folder.parent:
        folder = folder.parent
    try:
        stat = os.statvfs(folder)
    except OSError:
        return float("inf")
    return stat.f_bavail * stat.f_frsize


def read_frame(path: str | Path) -> pd.DataFrame:
    """All sample rows of a run, in evaluation order."""
    return _read_only(path, _samples_frame)


FRAME_QUERY = "SELECT * FROM samples ORDER BY eval_index"
READ_CHUNK = 2048    # rows converted at a time: the Python objects alive at once while reading
EXACT_INT = 2 ** 53  # integers below this in size are exact as float64
MAX_ARGS = 100       # arguments per SQL max(): SQLite takes at most 127


def _samples_frame(db: sqlite3.Connection) -> pd.DataFrame:
    """The samples table as pd.read_sql_query(FRAME_QUERY) makes it, value for value and dtype
    for dtype, in about half its time and a fraction of its memory: the columns declared REAL
    or INTEGER go into one float64 array a chunk of rows at a time (pandas holds every row's
    Python objects at once, then infers each column's type from them), the others through
    pandas itself, and rows are put in evaluation order by numpy (eval_index has no index).
    What this cannot match for certain (no rows, text in a column of numbers, eval_index not
    unique integers) is read by pandas itself."""
    db.execute("BEGIN")   # one snapshot for every query below: a writer may be adding rows
    try:
        declared = {row[1]: str(row[2]).upper() for row in
                    db.execute("PRAGMA table_info(samples)")}
        numeric = [n for n, t in declared.items() if t in ("REAL", "INTEGER")]
        rows = db.execute("SELECT count(*) FROM samples").fetchone()[0]
        values = None
        if "eval_index" in numeric and rows:
            values = _numbers(db, numeric, rows)
        if values is None:
            return pd.read_sql_query(FRAME_QUERY, db)
        columns, rest = _typed(values, numeric, declared)
        del values
        index = columns.get("eval_index")
        if index is None or index.dtype != np.int64:
            return pd.read_sql_query(FRAME_QUERY, db)
        order = np.argsort(index, kind="stable")
        ranked = index[order]
        if (ranked[1:] == ranked[:-1]).any():   # ties: SQLite orders them its own way
            return pd.read_sql_query(FRAME_QUERY, db)
        if (order != np.arange(rows)).any():
            columns = {n: c[order] for n, c in columns.items()}
        rest += [n for n in declared if n not in numeric]
        out: dict[str, np.ndarray | pd.Series] = dict(columns)
        if rest:   # text; numbers pandas types otherwise (only NULLs, ints past 2**53)
            other = pd.read_sql_query(
                f"SELECT {', '.join(map(_q, rest))} FROM samples ORDER BY rowid", db)
            if len(other) != rows:
                return pd.read_sql_query(FRAME_QUERY, db)
            other = other.take(order).reset_index(drop=True)
            out.update((n, other[n]) for n in rest)
        return pd.DataFrame({n: out[n] for n in declared})
    finally:
        db.rollback()


def _numbers(db: sqlite3.Connection, names: list[str], rows: int) -> np.ndarray | None:
    """The columns `names` in rowid order as one (rows, len(names)) float64 array, NULL as
    NaN; None where one of them holds text or a blob (or the row count differs from `rows`).
    Each row also carries the largest of its values, which SQLite orders above every number
    when it is text or a blob: that one value per row tells whether a row holds any."""
    groups = [names[i:i + MAX_ARGS] for i in range(0, len(names), MAX_ARGS)]
    top = "max(" + ", ".join("max(" + ", ".join(f"coalesce({_q(n)}, 0)" for n in g) + ", 0)"
                             for g in groups) + ", 0)"
    cursor = db.execute(f"SELECT {', '.join(map(_q, names))}, {top} FROM samples ORDER BY rowid")
    values = np.empty((rows, len(names) + 1))
    done = 0
    while chunk := cursor.fetchmany(READ_CHUNK):
        if done + len(chunk) > rows or not set(map(type, [r[-1] for r in chunk])) <= _NUMBERS:
            return None
        values[done:done + len(chunk)] = chunk
        done += len(chunk)
    return values[:, :-1] if done == rows else None


def _typed(values: np.ndarray, names: list[str], declared: dict[str, str]
           ) -> tuple[dict[str, np.ndarray], list[str]]:
    """Each column of `values` with the dtype pandas infers from its Python values: int64 for
    an INTEGER column of integers only (SQLite stores an integral number there as an integer),
    else float64; and the names of the columns whose type it cannot tell from the floats (only
    NULLs: object; integers past 2**53 are not exact as floats)."""
    columns: dict[str, np.ndarray] = {}
    rest: list[str] = []
    for j, name in enumerate(names):
        col = values[:, j]
        missing = np.isnan(col)
        if missing.all():
            rest.append(name)
        elif declared[name] == "INTEGER" and not missing.any():
            if (np.abs(col) >= EXACT_INT).any():
                rest.append(name)
            elif (col == np.trunc(col)).all():
                columns[name] = col.astype(np.int64)
            else:
                columns[name] = col
        else:
            columns[name] = col
    return columns, rest


_NUMBERS = {int, float, type(None)}


def stored_samples(run: str | Path) -> int:
    """How many sample rows a run directory's store holds; 0 without a store."""
    path = Path(run) / STORE_NAME
    if not path.exists():
        return 0
    return _read_only(path, lambda db: db.execute("SELECT COUNT(*) FROM samples").fetchone()[0])


def read_meta(path: str | Path) -> dict:
    """The run's metadata (config, model, seed, curve, ...); FalsifyError where it holds none
    (a run killed as it began, or a file falsify did not finish writing)."""
    meta = _read_only(path, lambda db: {
        k: json.loads(v) for k, v in db.execute("SELECT key, value FROM run")})
    if not meta:
        path = Path(path)
        raise FalsifyError(f"{path / STORE_NAME if path.is_dir() else path}: holds no run "
                           "metadata (its run table is empty), so nothing tells how its rows "
                           "were made; start the run again in a new --out")
    return meta


def environments_of(meta: dict) -> list[dict]:
    """Every distinct environment a run was computed under (falsify's, Python's and the
    libraries' versions, CPU, backend, device, inference threads: see
    falsify/executors/environment.py), in the order first used; empty for a run made before
    sessions recorded them."""
    found: list[dict] = []
    for session in _sessions(meta):
        for env in session.get("environments") or []:
            if isinstance(env, dict) and env not in found:
                found.append(env)
    return found


def environment_changes_of(meta: dict) -> list[str]:
    """What changed between the environments a run was computed under that may change its
    numbers ("onnxruntime 1.22.0 -> 1.23.0"), as each session recorded it when it began; empty
    where nothing did (thread counts known to give the same bytes do not count)."""
    found: list[str] = []
    for session in _sessions(meta):
        found += [str(c) for c in session.get("changed") or []]
    return list(dict.fromkeys(found))


def _sessions(meta: dict) -> list[dict]:
    sessions = meta.get("sessions")
    return [s for s in sessions if isinstance(s, dict)] if isinstance(sessions, list) else []


def export(frame: pd.DataFrame, out: Path, formats: Sequence[str] = ("csv", "parquet")) -> list:
    """Write the table as CSV and Parquet (Parquet only where pyarrow is installed)."""
    from falsify.fileio import write_bytes
    written = []
    if "csv" in formats:
        write_bytes(out.with_suffix(".csv"), frame.to_csv(index=False).encode())
        written.append(out.with_suffix(".csv"))
    if "parquet" in formats:
        try:
            import pyarrow  # noqa: F401
        except ImportError:
            return written
        import io
        buf = io.BytesIO()
        frame.to_parquet(buf, index=False)
        write_bytes(out.with_suffix(".parquet"), buf.getvalue())
        written.append(out.with_suffix(".parquet"))
    return written


def _q(name: str) -> str:
    return f'"{name}"'


def _sql_type(space: Space, dim: str) -> str:
    """TEXT for named values, INTEGER for ids and counts, REAL for coordinates."""
    from falsify.world.space import Categorical
    d = space.dims[dim]
    if isinstance(d, Categorical) and any(isinstance(v, str) for v in d.values):
        return "TEXT"
    if isinstance(d, Categorical) and all(isinstance(v, int) for v in d.values):
        return "INTEGER"
    return "REAL"


# -- reading a run directory ------------------------------------------------------------------
@dataclass(frozen=True)
class Completeness:
    """How much of its plan a run holds: `samples` rows of `planned` (a search's is its most;
    None where the run does not record it), and whether its sampler ran to its end (None: the
    run does not say)."""

    samples: int
    planned: int | None
    complete: bool | None

    def to_json(self) -> dict:
        return {"samples": self.samples, "planned": self.planned, "complete": self.complete}

    def text(self) -> str:
        """'32 of 252 planned samples', or '32 samples' where the plan is not recorded."""
        if self.planned is None:
            return f"{self.samples} sample{'s' * (self.samples != 1)}"
        return f"{self.samples} of {self.planned} planned samples"


def completeness(meta: dict, samples: int, grid_size: int | None = None) -> Completeness:
    """A run's completeness from its metadata: `complete` is set when its sampler returns (and
    `computed_last` with it, in runs from before `complete`); a run holding all it planned is
    complete too (stopped before it could say so). A run that records no plan and no end is of
    unknown completeness (a killed run, or one written by another tool); `grid_size`, the size
    of its space's grid, then stands for a grid run's plan where it holds them all."""
    planned = meta.get("planned")
    recorded = isinstance(planned, int) and not isinstance(planned, bool) and planned >= 0
    if not recorded:
        whole_grid = meta.get("algorithm") == "grid" and meta.get("budget") is None
        planned = grid_size if whole_grid else None
    if meta.get("complete") is True or "computed_last" in meta:
        done: bool | None = True
    elif planned is not None and (recorded or samples >= planned):
        done = samples >= planned
    else:
        done = None
    return Completeness(samples, planned, done)


@dataclass(frozen=True)
class RunData:
    """A stored run opened for reading: metadata, rows, and the space rebuilt from its config."""

    path: Path
    meta: dict
    frame: pd.DataFrame
    space: Space

    @property
    def score_column(self) -> str:
        """The column the run minimised: car_iou unless it was run with another objective."""
        return str(self.meta.get("score_column") or "car_iou")

    @property
    def objective(self) -> str:
        return str(self.meta.get("objective") or "car")

    @property
    def ok(self) -> pd.DataFrame:
        """The valid rows (status ok)."""
        return self.frame[self.frame["status"] == Status.OK]

    def worst(self, n: int) -> pd.DataFrame:
        """The n valid rows of lowest objective, ties by evaluation order."""
        ok = self.ok
        return ok.assign(_iou=ok[self.score_column].astype(float)).sort_values(
            ["_iou", "eval_index"], kind="stable").head(n)

    @property
    def environments(self) -> list[dict]:
        """The distinct environments its rows were computed under (see `environments_of`)."""
        return environments_of(self.meta)

    @property
    def environment_changes(self) -> list[str]:
        """What changed between them that may change its numbers (`environment_changes_of`)."""
        return environment_changes_of(self.meta)

    @property
    def completeness(self) -> Completeness:
        """Whether the run holds all it set out to score (see `completeness`)."""
        return completeness(self.meta, len(self.frame), self.space.size())

    def resume_command(self) -> str:
        """The command that finishes this run, to paste in any folder: its command and config
        with the options its rows depend on (those --resume checks), and --resume; the run, its
        config and a model file by absolute paths (as typed, they named files from the folder
        the run was started in)."""
        m = self.meta
        command = str(m.get("command") or "grid")
        args = ["falsify", command, self._typed_path(m.get("config_path"), "config") or "CONFIG",
                "--out", str(Path(self.path).absolute())]
        if command == "search":
            args += ["--algorithm", str(m.get("algorithm"))]
            if m.get("budget") is not None:
                args += ["--budget", str(m["budget"])]
            confidence = (m.get("sampler_options") or {}).get("confidence")
            if confidence is not None:
                args += ["--confidence", str(confidence)]
        if m.get("model_path"):
            args += ["--model", self._typed_path(m["model_path"], "model")]
        if m.get("objective"):
            args += ["--objective", str(m["objective"])]
        if m.get("seed") is not None and m["seed"] != self.space.seed:
            args += ["--seed", str(m["seed"])]
        if m.get("threshold") is not None and m["threshold"] != self.space.threshold:
            args += ["--threshold", str(m["threshold"])]
        if m.get("fidelity") not in (None, "exact"):
            args += ["--fidelity", str(m["fidelity"])]
        return shlex.join([*args, "--resume"])

    def _typed_path(self, typed: object, kind: str) -> str | None:
        """A config or model as the run's command named it, absolute where it was a relative
        path (a bundled name, with no folder and no suffix, stays a name): the config by the
        folder it was read from, a model (or a plug-in's FILE.py:FACTORY) by the run's first
        working folder where recorded."""
        if not typed:
            return None
        text = str(typed)
        path = Path(text)
        if path.is_absolute() or (len(path.parts) == 1 and not path.suffix
                                  and ":" not in text):
            return text
        if kind == "config" and self.meta.get("config_dir"):
            return str(Path(self.meta["config_dir"]) / path.name)
        if self.meta.get("cwd"):
            return str(Path(self.meta["cwd"]) / path)
        return text

    @property
    def threshold(self) -> float:
        t = self.meta.get("threshold")
        return float(t) if isinstance(t, int | float) and not isinstance(t, bool) else \
            DEFAULT_THRESHOLD

    def cell_map(self, frame: pd.DataFrame | None = None, column: str | None = None
                 ) -> CellMap:
        """The (x, y) mIoU map of the run's objective (or of `column`), over its rows or a
        subset of them. A level-set run's own map is its estimate of the full grid's, with
        each cell's interval (the counts are of the rows it scored)."""
        cmap = miou_map(self.frame if frame is None else frame, self.space, "x", "y",
                        column or self.score_column)
        estimates = self.meta.get("cell_estimates")
        if frame is not None or column not in (None, self.score_column) or not estimates:
            return cmap
        return with_estimates(cmap, estimates)


def open_run(run: str | Path) -> RunData:
    """Read a run directory (or its results.sqlite); FalsifyError names the file if unusable."""
    path = Path(run)
    if not path.exists():
        raise FalsifyError(f"{path}: no such run directory")
    if path.is_file() and path.name == STORE_NAME:
        path = path.parent
    if not path.is_dir():
        raise FalsifyError(f"{path}: not a run directory (expected a directory holding "
                           f"{STORE_NAME})")
    meta = read_meta(path)
    frame = read_frame(path)
    text = meta.get("config_text")
    if not isinstance(text, str):
        raise FalsifyError(f"{path / STORE_NAME}: run metadata has no config_text; was the run "
                           "finished by `falsify grid` or `falsify search`?")
    try:
        raw = tomllib.loads(text.removeprefix("\ufeff"))   # a config saved with a BOM
    except tomllib.TOMLDecodeError as exc:
        raise FalsifyError(f"{path / STORE_NAME}: stored config is not valid TOML ({exc})") \
            from None
    source = str(meta.get("config_path") or "<stored config>")
    real = meta.get("real_backgrounds")
    base = meta.get("config_dir")   # absolute; runs before it resolve against the cwd
    space = parse_space(raw, source=source,
                        base_dir=Path(base) if isinstance(base, str) else Path(source).parent,
                        config_hash=str(meta.get("config_hash") or ""), builtin_cars=None,
                        real_backgrounds=None if real is None else tuple(
                            RealScan(n, Path(b), None if lab is None else Path(lab), k)
                            for n, b, lab, k in real))
    score = str(meta.get("score_column") or "car_iou")
    missing = [c for c in ("x", "y", "status", score) if c not in frame.columns]
    if missing:
        raise FalsifyError(f"{path / STORE_NAME}: samples table lacks column {missing[0]!r}")
    return RunData(path, meta, frame, space)


def check_complete(data: RunData, allow: bool, where: str = "") -> tuple[Completeness, str | None]:
    """The run's completeness and the process writing it (None: none). Unless `allow`, an
    incomplete run or one being written is a FalsifyError: what a command judges of it would be
    of the samples scored so far, and the cells not reached yet would pass unseen."""
    from falsify.results.runlock import writer

    done, busy = data.completeness, writer(data.path)
    if allow or (done.complete is not False and busy is None):
        return done, busy
    if busy is not None:
        raise FalsifyError(f"{where}{data.path}: still being written by {busy}: {done.text()} "
                           "stored so far; wait for that run to end, or pass "
                           "--allow-incomplete to read what it holds now")
    raise FalsifyError(f"{where}{data.path}: incomplete run, stopped before its end: "
                       f"{done.text()} stored; finish it with `{data.resume_command()}`, or pass "
                       "--allow-incomplete to read what it holds")
