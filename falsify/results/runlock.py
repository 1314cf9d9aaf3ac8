"""One writer per run folder: an advisory lock (`fcntl.flock`) on RUN/.lock, held by the process
computing on the run and released by the kernel when that process ends, however it ends.

Two `grid`/`search` on one folder would compute the same samples and collide on the store's
unique keys; the second is refused instead, with a message naming the holder (its pid and
command line, which the holder writes into the lock file). A process that holds the lock may
take it again (the CLI takes it before its slow imports, the run job for API callers); readers
(`report`, `gate`) take none (`writer` tells `gate` whether a process is computing on the run).
The lock file is removed on release; one left by a killed process holds no lock and is taken over.
"""

from __future__ import annotations

import fcntl
import os
import shlex
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

from falsify.checks import check_out_dir
from falsify.errors import FalsifyError

LOCK_NAME = ".lock"


@dataclass
class _Held:
    """This process's hold on one run folder: the locked file, the folders made for it."""

    fd: int
    path: Path
    made: list[Path]
    depth: int = 1


_HELD: dict[str, _Held] = {}
_GUARD = threading.Lock()


class RunLock:
    """Context manager: make the run folder if needed and hold its lock; FalsifyError naming the
    holder if another process holds it. `made` lists the folders made for it, deepest first:
    those still empty on release are removed, so a refused run leaves nothing behind."""

    def __init__(self, run: str | Path, command: str | None = None):
        self.run = Path(run)
        self.command = command if command is not None else shlex.join(sys.argv)
        self.made: list[Path] = []
        self._key = ""

    def __enter__(self) -> RunLock:
        check_out_dir(self.run)
        made = missing_folders(self.run)
        try:
            self.run.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            remove_empty(made)
            raise FalsifyError(f"--out {self.run}: cannot be made ({exc.strerror})") from None
        self._key = os.path.realpath(self.run)
        with _GUARD:
            held = _HELD.get(self._key)
            if held is not None:
                held.depth += 1
            else:
                try:
                    held = _HELD[self._key] = _acquire(self.run / LOCK_NAME, self.command, made)
                except BaseException:
                    remove_empty(made)
                    raise
        self.made = held.made
        return self

    def __exit__(self, *exc) -> None:
        with _GUARD:
            held = _HELD[self._key]
            held.depth -= 1
            if held.depth:
                return
            del _HELD[self._key]
        if _same_file(held.fd, held.path):   # ours still: remove it (a later holder makes its own)
            held.path.unlink(missing_ok=True)
        os.close(held.fd)
        remove_empty(held.made)


def _acquire(path: Path, command: str, made: list[Path]) -> _Held:
    """Lock `path` (made if missing) without waiting, and write this process's pid and command
    into it; FalsifyError naming the holder when another process holds it."""
    while True:
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o666)
        except OSError as exc:
            raise FalsifyError(f"--out {path.parent}: cannot be locked ({exc.strerror})") \
                from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            raise FalsifyError(f"--out {path.parent}: in use by {holder(path)}; one run takes "
                               "one grid or search at a time: wait for it to end or stop it"
                               ) from None
        except OSError as exc:
            os.close(fd)
            raise FalsifyError(f"--out {path.parent}: cannot be locked ({exc.strerror})") \
                from None
        if _same_file(fd, path):   # else its holder removed it as we opened it: lock the new one
            break
        os.close(fd)
    try:
        os.ftruncate(fd, 0)
        # surrogateescape: a path of non-UTF-8 bytes (argv decodes them so) is written as given
        os.write(fd, f"{os.getpid()}\n{command}\n".encode("utf-8", "surrogateescape"))
    except OSError:   # a full disk: the lock holds all the same, its holder goes unnamed
        pass
    return _Held(fd, path, made)


def writer(run: str | Path) -> str | None:
    """Who is computing on `run` now ('process PID (COMMAND)'), or None when no process is.
    For readers: the lock file is opened read-only (never made) and a shared lock tried and
    dropped at once, so a writer starting in that instant is refused as if the run were busy."""
    path = Path(run) / LOCK_NAME
    with _GUARD:
        if os.path.realpath(run) in _HELD:
            return f"this process ({os.getpid()})"
    try:
        fd = os.open(path, os.O_RDONLY | os.O_CLOEXEC)
    except OSError:   # no lock file: no writer (one that cannot be read says nothing either)
        return None
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except BlockingIOError:
        return holder(path)
    except OSError:
        return None
    finally:
        os.close(fd)   # closing drops the shared lock
    return None


def holder(path: Path, wait_s: float = 0.5) -> str:
    """Who holds the lock, as its holder wrote it: 'process PID (COMMAND)'; a holder that has
    only just taken it is given `wait_s` to write it."""
    deadline = time.monotonic() + wait_s
    while True:
        try:
            text = path.read_bytes().decode("utf-8", "replace")   # any locale, any path
            pid, _, command = text.partition("\n")
        except OSError:
            pid, command = "", ""
        if pid.strip().isdigit():
            command = command.strip()
            return f"process {pid.strip()}" + (f" ({command})" if command else "")
        if time.monotonic() > deadline:
            return "another process"
        time.sleep(0.05)


def _same_file(fd: int, path: Path) -> bool:
    """Whether `path` still names the file open as `fd`."""
    try:
        now = path.stat()
    except OSError:
        return False
    mine = os.fstat(fd)
    return (mine.st_dev, mine.st_ino) == (now.st_dev, now.st_ino)


def missing_folders(path: Path) -> list[Path]:
    """`path` and those of its parents that do not exist yet, deepest first (what mkdir makes)."""
    out = []
    while not path.exists() and path != path.parent:
        out.append(path)
        path = path.parent
    return out


def remove_empty(folders: list[Path]) -> None:
    """Remove `folders` (deepest first) while they are empty; stop at the first that is not."""
    for folder in folders:
        try:
            folder.rmdir()
        except OSError:   # not empty (or gone): keep it and its parents
            break
