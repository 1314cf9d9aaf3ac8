"""Checks of command arguments, paths and the libraries a command needs, run before anything is
created: a bad value or path raises FalsifyError naming the option (or file) and what is allowed."""

from __future__ import annotations

import errno
import os
import tempfile
from pathlib import Path

from falsify.errors import FalsifyError

SEED_MAX = 2**32 - 1   # seeds are 32-bit: numpy, NLopt and the stored runs agree on them
MAX_SAMPLES = 1_000_000   # default limit on the samples one run or benchmark may take


def check_range(value: int | None, option: str, lo: int, hi: int | None = None) -> None:
    """`value` (when given) is an integer in lo..hi (hi None: no upper bound)."""
    if value is None:
        return
    if hi is None and value < lo:
        raise FalsifyError(f"{option}: {value} must be >= {lo}")
    if hi is not None and not lo <= value <= hi:
        raise FalsifyError(f"{option}: {value} must be between {lo} and {hi}")


def check_seed(value: int | None, option: str = "--seed") -> None:
    check_range(value, option, 0, SEED_MAX)


def check_path_length(path: str | Path, option: str) -> None:
    """FalsifyError naming `option` when `path` is too long for the file system (a name over
    255 bytes, a path over PATH_MAX): `Path.exists` raises on it rather than answer."""
    try:
        os.stat(path)
    except OSError as exc:
        if exc.errno == errno.ENAMETOOLONG:
            raise FalsifyError(f"{option} {path}: too long a path ({exc.strerror}); choose a "
                               "shorter one") from None


def check_out_dir(path: str | Path, option: str = "--out") -> Path:
    """An output directory that exists, or can be made, and can be written; leaves nothing.

    Writability is tried, not inferred from permission bits (root ignores those, a read-only
    file system does not): a probe file is made in the nearest existing directory and removed."""
    path = Path(path)
    check_path_length(path, option)
    if path.exists() and not path.is_dir():
        raise FalsifyError(f"{option} {path}: is a file, not a directory")
    parent = path.absolute()
    while not parent.exists():
        parent = parent.parent
    if not parent.is_dir():
        raise FalsifyError(f"{option} {path}: {parent} is a file, so no directory can be made "
                           "there")
    try:
        fd, probe = tempfile.mkstemp(dir=parent, prefix=".falsify-probe-")
    except OSError as exc:
        raise FalsifyError(f"{option} {path}: cannot be written ({parent}: "
                           f"{exc.strerror})") from None
    os.close(fd)
    os.unlink(probe)
    return path


def check_out_file(path: str | Path, option: str = "--out",
                   suffixes: tuple[str, ...] = ()) -> Path:
    """An output file: not a directory (nor a name ending in /, which means one), in a
    directory that exists or can be made, and ending in one of `suffixes` where given, so that
    a slip of the name (`report --out RUN/results.sqlite`) cannot overwrite a store or a scan."""
    if str(path).endswith(("/", os.sep)):
        raise FalsifyError(f"{option} {path}: names a folder; give a file name")
    path = Path(path)
    if suffixes and path.suffix.lower() not in suffixes:
        raise FalsifyError(f"{option} {path}: must end in {' or '.join(suffixes)}")
    check_path_length(path, option)
    if path.is_dir():
        raise FalsifyError(f"{option} {path}: is a directory")
    check_out_dir(path.parent, option)
    return path


TORCH_INSTALL = ('pip install "falsify[torch]" (torch 2.13.0; install its CPU or CUDA build '
                 "first, as the README's set-up says)")


def require_torch(what: str) -> None:
    """FalsifyError (exit 2) before any work where `what` needs torch and torch does not
    import: scoring, reports and the gate run without it, so a plain install lacks it."""
    try:
        import torch  # noqa: F401
    except ImportError as exc:
        raise FalsifyError(f"{what} needs torch, which does not import here ({exc}): "
                           f"{TORCH_INSTALL}") from None
