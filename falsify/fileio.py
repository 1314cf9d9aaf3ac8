"""File I/O: atomic writes (a reader or a crash never sees half a file) and reads whose failure
names the file, as one line for the user."""

from __future__ import annotations

import contextlib
import errno
import hashlib
import io
import json
import os
import shutil
import tempfile
import tomllib
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from falsify.errors import FalsifyError

_UMASK = os.umask(0)
os.umask(_UMASK)


def read_bytes(path: str | Path, what: str = "",
               error: type[FalsifyError] = FalsifyError) -> bytes:
    """A file's bytes; `error` naming the file (and `what` it should hold) if it cannot be read."""
    try:
        return Path(path).read_bytes()
    except OSError as exc:
        raise error(f"{path}: cannot read{' ' + what if what else ''} ({exc.strerror})") from None


def parse_toml(data: bytes, path: str | Path, what: str = "TOML",
               error: type[FalsifyError] = FalsifyError) -> dict:
    """A TOML document's table from its bytes, UTF-8 whatever the locale, a leading byte-order
    mark (as Windows editors write) skipped; `error` naming the file if it is not valid."""
    try:
        return tomllib.loads(data.decode("utf-8-sig"))
    except UnicodeDecodeError as exc:
        raise error(f"{path}: not valid {what} (not UTF-8: {exc.reason} at byte "
                    f"{exc.start})") from None
    except tomllib.TOMLDecodeError as exc:
        raise error(f"{path}: not valid {what} ({exc})") from None


def read_text(path: str | Path, what: str = "", error: type[FalsifyError] = FalsifyError) -> str:
    """A UTF-8 text file's text; `error` naming the file if it cannot be read or decoded."""
    try:
        return read_bytes(path, what, error).decode("utf-8")
    except UnicodeDecodeError:
        raise error(f"{path}: not UTF-8 text{' (' + what + ')' if what else ''}") from None


def file_sha256(path: str | Path) -> str:
    """The SHA-256 (hex) of a file's bytes, read a megabyte at a time (OSError if unreadable)."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def write_bytes(path: str | Path, data: bytes) -> None:
    """Write to a temporary file beside `path`, fsync, then rename over it."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    os.chmod(tmp, 0o666 & ~_UMASK)  # mkstemp makes 0600; give the file the usual mode
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def move_file(src: str | Path, dst: str | Path) -> None:
    """Move a file to `dst` whole or not at all: a rename, or across file systems (a tmpfs
    /tmp) a copy beside `dst` renamed over it, then `src` removed; shutil.move's copy writes
    `dst` itself, so a kill mid-copy left a short file under the final name."""
    src, dst = Path(src), Path(dst)
    try:
        os.replace(src, dst)
        return
    except OSError as exc:
        if exc.errno != errno.EXDEV:
            raise
    dst.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=dst.parent, prefix=f".{dst.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as out, open(src, "rb") as inp:
            shutil.copyfileobj(inp, out, 1 << 20)
            out.flush()
            os.fsync(out.fileno())
        shutil.copymode(src, tmp)
        os.replace(tmp, dst)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    src.unlink()


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """A temporary path beside `path`, for a writer that takes a path (torch.save, ONNX export),
    renamed over `path` once the block succeeds and removed if it fails: no half file at `path`.
    Same name as `path` (torch.save names its archive by it, so the bytes are a direct write's),
    in a hidden folder of its own: a user's `NAME.tmp`, or another file's temporary, is safe."""
    path = Path(path)
    folder = Path(tempfile.mkdtemp(dir=path.parent, prefix=f".{path.name}."))
    tmp = folder / path.name
    try:
        yield tmp
        tmp.replace(path)
    finally:
        shutil.rmtree(folder, ignore_errors=True)


def write_text(path: str | Path, text: str) -> None:
    """Write `text` as UTF-8; a path of non-UTF-8 bytes in it (argv holds those as surrogates)
    is written as its own bytes, not a UnicodeEncodeError after the run."""
    write_bytes(path, text.encode("utf-8", "surrogateescape"))


def write_json(path: str | Path, obj) -> None:
    write_text(path, json.dumps(obj, indent=2, sort_keys=True) + "\n")


def npy_bytes(array: np.ndarray) -> bytes:
    """`array` as the bytes of a .npy file (no pickles)."""
    buf = io.BytesIO()
    np.save(buf, array, allow_pickle=False)
    return buf.getvalue()


def write_npy(path: str | Path, array: np.ndarray) -> None:
    write_bytes(path, npy_bytes(array))
