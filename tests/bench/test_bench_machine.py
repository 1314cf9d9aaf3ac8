"""The machine-side measurements of `bench pipeline`: processes started together, their errors
reported, and the memory of a process tree summed from /proc. No timing is asserted."""

from __future__ import annotations

import subprocess
import sys
import time

import pytest

from falsify.bench.machine import MemorySample, RssSampler, in_processes
from falsify.errors import FalsifyError


def test_memory_sampler_sums_the_children():
    """A child holding 200 MB shows in the sampled sum of this process and its descendants. Each
    sample is read against this process's own RSS in it: a long-lived test process (an xdist
    worker) can free memory between samples, so its RSS before the child is no baseline."""
    if not RssSampler().available:
        pytest.skip("no /proc")
    hold = "import sys, time; b = b'x' * 200_000_000; print(1, flush=True); time.sleep(30)"
    with RssSampler(interval=0.02, pss_every=1) as rss:
        child = subprocess.Popen([sys.executable, "-c", hold], stdout=subprocess.PIPE)
        try:
            child.stdout.readline()        # the child has touched its 200 MB
            t0 = time.perf_counter()
            while len([s for s in rss.samples if s[0] > t0]) < 8:
                time.sleep(0.02)
            t1 = time.perf_counter()
        finally:
            child.kill()
            child.wait()
    m = rss.summary(t0, t1)
    window = [x for x in rss.samples if t0 <= x.t <= t1]
    assert m.max_processes >= 2 and m.samples >= 8 and len(window) >= 8
    assert all(x.rss - x.root_rss > 150e6 and x.child_rss > 150e6 for x in window)
    assert m.window_peak_bytes > 150e6 and m.worker_peak_bytes > 150e6
    assert m.peak_pss_bytes is None or 150e6 < m.peak_pss_bytes <= m.peak_bytes


def test_processes_report_their_errors():
    assert in_processes(_rank_and_size, 2) == [(0, 2), (1, 2)]
    with pytest.raises(FalsifyError, match="process 1: ValueError: rank 1 fails"):
        in_processes(_fail_at_rank_1, 2)


def _rank_and_size(rank, n, barrier):
    barrier.wait(60)
    return rank, n


def _fail_at_rank_1(rank, n, barrier):
    if rank == 1:
        raise ValueError("rank 1 fails")
    barrier.wait(60)


def test_early_and_late_are_quarters_of_the_window():
    rss = RssSampler()
    rss.samples = [MemorySample(float(t), 100 + t, 1 + t % 3, 50 + t, 10 + t) for t in range(10)]
    m = rss.summary(2, 9)                     # 8 samples in the window: quarters of 2
    assert (m.peak_bytes, m.window_peak_bytes, m.samples, m.max_processes) == (109, 109, 8, 3)
    assert (m.early_bytes, m.late_bytes, m.seconds) == (102.5, 108.5, 7.0)
    assert (m.peak_pss_bytes, m.root_at_peak_bytes) == (59, 19)
    empty = rss.summary(20, 30)               # a window too short: no early or late figure
    assert empty.early_bytes is None and empty.to_json()["late_over_early"] is None
