"""The driver: a sampler's `evaluate` callback over the run's store and an executor.

It answers stored samples from the run's SQLite file and has the executor compute only the
rest, so a resumed run replays the sampler without recomputing or duplicating anything. The
callback may be called from several threads at once (a search running combinations
concurrently): the store and the progress lock themselves, the in-process executor serves one
thread at a time, and the process pool and the Ray executor take concurrent callers. No lock is
held while a chunk is being scored, so callers never wait on each other's samples.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

from falsify.executors import make_executor
from falsify.executors.evaluator import EvalSettings
from falsify.models.runners import Segmenter, load_segmenter
from falsify.results.metrics import Status
from falsify.results.samples import SampleResult
from falsify.results.store import Store
from falsify.world.space import Sample

ProgressListener = Callable[["Progress", bool], None]
"""Told the progress after every batch (final=False) and once at the end (final=True)."""



@dataclass
class Progress:
    """Counts and the lowest IoU so far, told to a listener as they change (the CLI draws a
    progress bar from them; the jobs print nothing). Updates from several threads are
    serialised; the listener is called under the same lock, so it sees consistent counts (and
    must not update the progress itself)."""

    total: int | None
    listener: ProgressListener | None = None
    done: int = 0
    computed: int = 0
    lowest: float | None = None
    lowest_at: dict | None = None
    started: float = field(default_factory=time.perf_counter)
    _lock: Any = field(default_factory=threading.RLock, init=False, repr=False, compare=False)

    def update(self, results: Sequence[SampleResult], fresh: int) -> None:
        with self._lock:
            self.done += len(results)
            self.computed += fresh
            for r in results:
                s = r.score
                if s is not None and (self.lowest is None or s < self.lowest):
                    self.lowest, self.lowest_at = s, r.sample.as_dict()
            self.tell()

    def tell(self, final: bool = False) -> None:
        with self._lock:
            if self.listener is not None:
                self.listener(self, final)



class Driver:
    """Runs a sampler against the store, computing only what the store does not hold."""

    def __init__(self, settings: EvalSettings, store: Store, workers: int = 1,
                 batch: int = 8, progress: Progress | None = None,
                 model: Segmenter | None = None, executor: str = "process",
                 address: str | None = None, inference: str = "auto"):
        self.settings = settings
        self.kind = executor       # "process" (local processes) or "ray" (actors on a cluster)
        self.address = address     # the Ray head (None: the running or a new local instance)
        self.inference = inference  # "auto", "worker" or "shared": where the network runs
        self.store = store
        self.workers = workers
        self.batch = batch
        self.progress = progress or Progress(None)
        self.model = model     # this process's open model (else loaded on entry)
        self.executor: Any = None  # the open executor, between __enter__ and __exit__
        self.model_hash = ""

    def __enter__(self) -> Driver:
        inline = self.kind != "ray" and self.workers <= 1
        if self.model is None and not inline:   # workers open the model for themselves
            self.model = load_segmenter(self.settings.model, backend=self.settings.backend,
                                        threads=1, device=self.settings.device)
        self.executor = make_executor(self.kind, self.settings, self.workers, self.address,
                                      self.model, self.inference).__enter__()
        self.model_hash = self.executor.model_hash if inline else self.model.model_hash
        return self

    def __exit__(self, *exc) -> None:
        if self.executor is not None:
            self.executor.__exit__(*exc)

    def environments(self) -> list[dict]:
        """The distinct environments of the processes that score (none known: empty)."""
        tell = getattr(self.executor, "environments", None)
        return tell() if tell is not None else []

    def evaluate(self, samples: Sequence[Sample]) -> list[float | None]:
        """The samplers' callback: scores in order, stored ones read back, the rest computed.

        Safe to call from several threads. Two threads asking for the same new sample at once
        may both compute it; the store keeps the first row and counts it once. Every sample
        asked for counts as one done in the progress, a repeat of a new one too (computed once)."""
        todo: list[Sample] = []
        seen = set()
        for s in samples:
            if s not in self.store and s not in seen:
                todo.append(s)
                seen.add(s)
        known = [s for s in samples if s not in seen]
        if known:
            self.progress.update(self._stored(known), 0)
        chunks = [todo[i:i + self.batch] for i in range(0, len(todo), self.batch)]
        for chunk_results in self.executor.map(chunks):
            fresh = self.store.add(chunk_results, self.model_hash,
                                   self.settings.space.config_hash)
            self.progress.update(chunk_results, fresh)
        first: set[Sample] = set()
        repeats: list[Sample] = []
        for s in samples:
            if s in seen:
                if s in first:
                    repeats.append(s)
                first.add(s)
        if repeats:
            self.progress.update(self._stored(repeats), 0)
        return [self.store.score(s) for s in samples]

    def _stored(self, samples: Sequence[Sample]) -> list[SampleResult]:
        """Stored samples as results carrying just their score, for the progress."""
        col = self.store.scoring.score_column
        return [SampleResult(s, Status.OK, metrics={col: self.store.score(s)}, score_column=col)
                for s in samples]
