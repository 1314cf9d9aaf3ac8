"""Stopping a command cleanly: SIGTERM and SIGINT raise, once, in the main thread."""

from __future__ import annotations

import contextlib
import shlex
import signal
import sys
import threading
from collections.abc import Iterator
from pathlib import Path


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised like Ctrl-C's KeyboardInterrupt so that a run stops the same clean way."""


_received: list[int] = []   # the stop signal the handler took: a library that catches our
#                             Terminated and raises KeyboardInterrupt (Ray's waits) keeps it


@contextlib.contextmanager
def stop_signals() -> Iterator[None]:
    """For the block: SIGTERM raises Terminated and SIGINT KeyboardInterrupt (each where not
    ignored), once; a second signal during the clean-up that follows is ignored."""
    _received.clear()
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def stop(signum: int, frame) -> None:
        for sig in old:
            signal.signal(sig, signal.SIG_IGN)
        _received.append(signum)
        raise Terminated() if signum == signal.SIGTERM else KeyboardInterrupt()

    old = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    old = {sig: h for sig, h in old.items() if h in (signal.SIG_DFL, signal.default_int_handler)}
    for sig in old:
        signal.signal(sig, stop)
    try:
        yield
    finally:
        for sig, handler in old.items():
            signal.signal(sig, handler)


def stop_name(exc: KeyboardInterrupt) -> tuple[str, int]:
    """What stopped the command, and its exit status (128 + the signal's number): SIGTERM when
    the exception says so or our handler took it, whatever the exception became on its way."""
    term = isinstance(exc, Terminated) or signal.SIGTERM in _received
    return ("terminated", 143) if term else ("interrupted", 130)


def stopped_training(exc: KeyboardInterrupt, args, checkpoint: Path, done: str) -> int:
    """Say on stderr how a stopped training goes on (with --resume where `checkpoint` holds its
    finished `done`, else run again); return the exit status."""
    from falsify.cli.run import with_resume, without_resume

    what, code = stop_name(exc)
    argv = list(getattr(args, "argv", sys.argv[1:]))
    if checkpoint.is_file():
        again = ["falsify", *with_resume(argv)]
        how = f"its finished {done} are saved in {checkpoint.parent}; continue with"
    else:
        again = ["falsify", *without_resume(argv)]
        how = f"no checkpoint was saved in {checkpoint.parent}; run it again with"
    print(f"falsify: {what}: {how}: {shlex.join(again)}", file=sys.stderr)
    return code
