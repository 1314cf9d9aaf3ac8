"""The progress bar of long commands (grid, search, retrain): one line on stderr."""

from __future__ import annotations

import sys
import time


class ProgressBar:
    """Draws a run's progress as one line on stderr: a bar, rate, ETA and the lowest IoU."""

    def __init__(self) -> None:
        self._last = 0.0

    def __call__(self, p, final: bool) -> None:
        now = time.perf_counter()
        if not final and now - self._last < 0.25:
            return
        self._last = now
        elapsed = now - p.started
        rate = p.computed / elapsed if elapsed > 0 else 0.0
        total = f"/{p.total}" if p.total else ""
        eta = ""
        if p.total and rate > 0:
            eta = f" ETA {max(0.0, (p.total - p.done) / rate):5.0f}s"
        low = "-" if p.lowest is None else f"{p.lowest:.3f}"
        bar = ""
        if p.total:
            filled = int(24 * min(1.0, p.done / p.total))
            bar = "[" + "#" * filled + "." * (24 - filled) + "] "
        tty = sys.stderr.isatty()
        end = "\n" if final or not tty else "\r"
        if not tty and not final and p.done % 200 and p.done != p.total:
            return
        sys.stderr.write(f"{bar}{p.done}{total} samples  {rate:6.1f}/s{eta}  "
                         f"lowest IoU {low}{end}")
        sys.stderr.flush()
