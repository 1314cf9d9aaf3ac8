"""Local executors: one warm evaluator in this process, or a pool of worker processes that
each hold their own (a Simulator with cached street hits and an inference session)."""

from __future__ import annotations

import multiprocessing as mp
import os
import threading
import time
from collections.abc import Iterable, Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor

from falsify.executors.evaluator import EvalSettings, Evaluator
from falsify.models.runner import Segmenter
from falsify.results.samples import SampleResult
from falsify.world.space import Sample


class InlineExecutor:
    """Scores chunks in this process with one warm evaluator, one caller thread at a time."""

    def __init__(self, settings: EvalSettings, model: Segmenter | None = None):
        self.settings = settings
        self.model = model
        self._evaluator: Evaluator | None = None
        self._lock = threading.Lock()

    def __enter__(self) -> InlineExecutor:
        self._evaluator = Evaluator(self.settings, model=self.model)
        return self

    def __exit__(self, *exc) -> None:
        self._evaluator = None

    @property
    def model_hash(self) -> str:
        assert self._evaluator is not None
        return self._evaluator.model_hash

    def map(self, chunks: Iterable[Sequence[Sample]]) -> Iterator[list[SampleResult]]:
        for chunk in chunks:
            with self._lock:
                assert self._evaluator is not None
                result = self._evaluator.score_batch(chunk)
            yield result


class ProcessExecutor:
    """`workers` spawned processes, each with its own warm evaluator for the whole run."""

    def __init__(self, settings: EvalSettings, workers: int):
        self.settings = settings
        self.workers = workers
        self._pool: ProcessPoolExecutor | None = None

    def __enter__(self) -> ProcessExecutor:
        self._pool = ProcessPoolExecutor(self.workers, mp_context=mp.get_context("spawn"),
                                         initializer=_init_worker, initargs=(self.settings,))
        return self

    def __exit__(self, *exc) -> None:
        if self._pool is not None:
            self._pool.shutdown(cancel_futures=True)

    def map(self, chunks: Iterable[Sequence[Sample]]) -> Iterator[list[SampleResult]]:
        assert self._pool is not None
        return self._pool.map(_work, chunks)


_worker: Evaluator | None = None


def _init_worker(settings: EvalSettings) -> None:
    global _worker
    threading.Thread(target=_exit_with_parent, args=(os.getppid(),), daemon=True,
                     name="parent-watch").start()
    _worker = Evaluator(settings)


def _exit_with_parent(parent: int, every_s: float = 1.0) -> None:
    """End this worker once its driver is gone: a driver killed with -9 leaves its workers
    waiting on a task queue that they hold open themselves, so they would never see it end."""
    while os.getppid() == parent:
        time.sleep(every_s)
    os._exit(1)


def _work(samples: list[Sample]) -> list[SampleResult]:
    assert _worker is not None
    return _worker.score_batch(samples)
