"""Local executors: one warm evaluator in this process, or a pool of worker processes that
each hold their own (a Simulator with cached street hits and an inference session).

Workers ignore SIGINT: Ctrl-C reaches the whole process group, and only the driver acts on it.
A run that ends on an exception (KeyboardInterrupt, a full disk) terminates its workers and joins
them before the driver goes on, so none outlives it and no semaphore leaks.
"""

from __future__ import annotations

import contextlib
import multiprocessing as mp
import os
import signal
import threading
import time
from collections.abc import Iterable, Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor

from falsify.executors.environment import environment
from falsify.executors.evaluator import EvalSettings, Evaluator
from falsify.models.runners import Segmenter
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

    def environments(self) -> list[dict]:
        """This process's, with the threads its network was opened with."""
        assert self._evaluator is not None
        threads = getattr(self._evaluator.model, "threads", self.settings.threads)
        return [environment(self.settings.backend, self.settings.device, threads)]

    def map(self, chunks: Iterable[Sequence[Sample]]) -> Iterator[list[SampleResult]]:
        for chunk in chunks:
            with self._lock:
                assert self._evaluator is not None
                result = self._evaluator.score_batch(chunk)
            yield result


class ProcessExecutor:
    """`workers` spawned processes, each with its own warm evaluator for the whole run; with
    `shared_inference` they cast scans only and one inference process runs the network for
    all of them in batches (`falsify/executors/inference.py`)."""

    def __init__(self, settings: EvalSettings, workers: int, shared_inference: bool = False):
        self.settings = settings
        self.workers = workers
        self.shared_inference = shared_inference
        self._pool: ProcessPoolExecutor | None = None
        self._server = None

    def __enter__(self) -> ProcessExecutor:
        client = None
        if self.shared_inference:
            from falsify.executors.inference import InferenceServer
            self._server = InferenceServer(self.settings, self.workers)
            self._server.start()
            client = self._server.client_args()
        self._pool = ProcessPoolExecutor(self.workers, mp_context=mp.get_context("spawn"),
                                         initializer=_init_worker,
                                         initargs=(self.settings, client))
        try:
            # Start every worker now (else each starts with its first task): they ignore
            # SIGINT from their first instruction on, which the initializer is too late for.
            with _starting_workers():
                for _ in range(self.workers):
                    self._pool.submit(_nothing)
        except BaseException:
            self._stop()
            raise
        return self

    def __exit__(self, exc_type, *exc) -> None:
        if self._pool is not None:
            if exc_type is None:
                self._pool.shutdown(cancel_futures=True)
            else:
                self._stop()
            self._pool = None
        if self._server is not None:
            self._server.stop()
            self._server = None

    def _stop(self) -> None:
        """End the workers now (their unfinished chunks are lost; stored rows are whole chunks)
        and join them and the pool's thread, so that the pool's queues are released."""
        pool = self._pool
        assert pool is not None
        # shutdown() forgets both: keep them. It goes first so that the pool's thread drops the
        # cancelled futures before it finds the workers gone (it would fail on them after).
        processes = list((getattr(pool, "_processes", None) or {}).values())
        manager = getattr(pool, "_executor_manager_thread", None)
        pool.shutdown(wait=False, cancel_futures=True)
        for p in processes:
            p.terminate()
        for p in processes:
            p.join(_JOIN_S)
            if p.is_alive():
                p.kill()
                p.join()
        if manager is not None:
            manager.join(_JOIN_S)

    def environments(self) -> list[dict]:
        """This process's (the workers are spawned from this interpreter on this machine), with
        the threads a worker's network, or the shared inference process's, runs on."""
        threads = self._server.threads if self._server is not None else self.settings.threads
        return [environment(self.settings.backend, self.settings.device, threads)]

    def map(self, chunks: Iterable[Sequence[Sample]]) -> Iterator[list[SampleResult]]:
        assert self._pool is not None
        return self._pool.map(_work, chunks)


_worker: Evaluator | None = None
_JOIN_S = 5.0   # how long a terminated worker may take to end before it is killed


@contextlib.contextmanager
def _starting_workers() -> Iterator[None]:
    """For the block (in the main thread; signals are its alone): SIGINT ignored, which the
    workers started here inherit, and SIGTERM held to its end, so that a worker being started
    when it comes is known to the pool and ended with the others."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    held: list[int] = []
    old_int = signal.signal(signal.SIGINT, signal.SIG_IGN)
    old_term = signal.signal(signal.SIGTERM, lambda signum, frame: held.append(signum))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, old_int)
        signal.signal(signal.SIGTERM, old_term)
        if held:
            signal.raise_signal(signal.SIGTERM)


def _nothing() -> None:
    """A task that only makes the pool start a worker."""


def _init_worker(settings: EvalSettings, client: tuple | None = None) -> None:
    """A worker's warm evaluator; `client` (the inference server's queues) makes its network
    the shared inference process."""
    global _worker
    signal.signal(signal.SIGINT, signal.SIG_IGN)   # Ctrl-C is the driver's to handle
    threading.Thread(target=_exit_with_parent, args=(os.getppid(),), daemon=True,
                     name="parent-watch").start()
    model = None
    if client is not None:
        from falsify.executors.inference import remote_segmenter
        model = remote_segmenter(settings, *client)
    _worker = Evaluator(settings, model=model)


def _exit_with_parent(parent: int, every_s: float = 1.0) -> None:
    """End this worker once its driver is gone: a driver killed with -9 leaves its workers
    waiting on a task queue that they hold open themselves, so they would never see it end."""
    while os.getppid() == parent:
        time.sleep(every_s)
    os._exit(1)


def _work(samples: list[Sample]) -> list[SampleResult]:
    assert _worker is not None
    return _worker.score_batch(samples)
