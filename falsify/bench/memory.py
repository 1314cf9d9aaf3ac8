"""`falsify bench memory`: the resident memory of a whole `falsify grid` run, driver plus workers.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

from falsify.bench.machine import (
    MemoryUse,
    RssSampler,
    machine,
)


@dataclass(frozen=True)
class MemoryBench:
    """Resident memory of a whole `falsify grid` run: this process as its driver plus its worker
    processes, summed, from start-up to the written report."""

    config: str
    workers: int
    samples: int            # computed in the run
    seconds: float          # the whole command
    machine: dict
    memory: MemoryUse | None

    def to_json(self) -> dict:
        return {"benchmark": "memory", "command": f"falsify grid {self.config} --workers "
                f"{self.workers}", "config": self.config, "workers": self.workers,
                "samples": self.samples, "seconds": round(self.seconds, 1),
                "machine": self.machine,
                "memory": None if self.memory is None else {
                    **self.memory.to_json(),
                    "window": "from the first stored chunk (workers up and warm) to the last; "
                              "the peak is over the whole command, report included"}}


def bench_memory(config: str | Path, workers: int = 2, model: str | None = None) -> MemoryBench:
    """Run the config's whole grid as `falsify grid --workers N` does (runs.execute, report
    included, into a temporary directory) and sample the summed RSS of every process meanwhile."""
    import tempfile

    from falsify.jobs.run import RunRequest, execute

    marks: dict[str, float] = {}

    def listen(progress, final: bool) -> None:
        if progress.computed and "start" not in marks:
            marks["start"] = time.perf_counter()
        if final:
            marks["stop"] = time.perf_counter()

    with tempfile.TemporaryDirectory() as tmp:
        req = RunRequest(config=Path(config), out=Path(tmp) / "run", command="grid",
                         model=model, workers=workers)
        t0 = time.perf_counter()
        with RssSampler() as rss:
            summary = execute(req, on_progress=listen)
        seconds = time.perf_counter() - t0
    return MemoryBench(str(config), workers, summary.computed_this_time, seconds, machine(),
                       rss.summary(marks.get("start"), marks.get("stop")))
