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


class ScanCounter:
    """`what: done/total scans, rate, ETA` as one line on stderr, redrawn in place, for commands
    that read thousands of real scans (predict, realism). Only on a terminal: a log or CI keeps
    the command's own lines."""

    def __init__(self, what: str, total: int, stream=None) -> None:
        self.what, self.total, self.done = what, total, 0
        self.stream = stream if stream is not None else sys.stderr
        self.live = self.stream.isatty()
        self._start = self._last = time.perf_counter()
        self._drawn = False

    def __call__(self, scans: int) -> None:
        """`scans` more are done."""
        self.done += scans
        now = time.perf_counter()
        if not self.live or (now - self._last < 0.25 and self.done < self.total):
            return
        self._last = now
        rate = self.done / max(now - self._start, 1e-9)
        eta = f"  ETA {max(0.0, (self.total - self.done) / rate):5.0f}s" if rate > 0 else ""
        self.stream.write(f"\r{self.what}: {self.done}/{self.total} scans  {rate:6.1f}/s{eta}")
        self.stream.flush()
        self._drawn = True

    def close(self) -> None:
        """End the line, if one was drawn, so what is printed next starts on its own."""
        if self._drawn:
            self.stream.write("\n")
            self.stream.flush()
            self._drawn = False
