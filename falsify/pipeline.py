"""sample → scene → scan → network → metrics → store, spread over warm worker processes.

Each worker holds a Simulator (BVHs, cached background hits) and an inference session for the
whole run and scores samples in batches. The driver hands the samplers an `evaluate` callback
that answers stored samples from the run's SQLite file and computes only the rest, so a resumed
run replays the sampler without recomputing or duplicating anything. The callback may be called
from several threads at once (a search running combinations concurrently): the store and the
progress lock themselves, the in-process evaluator is used by one thread at a time, and the
process pool and the Ray executor take concurrent callers. No lock is held while a chunk is
being scored, so callers never wait on each other's samples.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from falsify.metrics import CLASSES, Status, class_scores, confusion
from falsify.models.runner import Segmenter, load_segmenter
from falsify.scene import InvalidSample, Scanner, Simulator
from falsify.sensor import load_sensor
from falsify.space import Sample, Space
from falsify.store import SampleResult, Store, sample_seed


@dataclass(frozen=True)
class EvalSettings:
    """What a worker needs to rebuild its warm state."""

    space: Space
    model: str | None = None
    backend: str = "onnx"
    threads: int = 1
    lod: int = 2
    # Streets to build when the worker starts (benchmarks time the steady state with them)
    warm_backgrounds: tuple[int, ...] = ()


class Evaluator:
    """Scores batches of samples with one warm scanner and one inference session; both can be
    handed in (an open model, another scanner), else they are built from the settings."""

    def __init__(self, settings: EvalSettings, model: Segmenter | None = None,
                 scanner: Scanner | None = None):
        self.settings = settings
        self.space = settings.space
        self.sim = scanner or Simulator(load_sensor(self.space.sensor), self.space.user_cars,
                                        lod=settings.lod)
        self.model = model or load_segmenter(settings.model, backend=settings.backend,
                                             threads=settings.threads)
        self.model.spec.check_fits(self.sim.sensor, settings.model or "bundled")
        for bg in settings.warm_backgrounds:
            self.sim.background_hits(bg, self.sim.ego_pose(bg))

    @property
    def model_hash(self) -> str:
        return self.model.model_hash

    def scan(self, sample: Sample):
        rng = np.random.default_rng(sample_seed(self.space, sample))
        return self.sim.scan(sample, rng=rng)

    def score_batch(self, samples: Sequence[Sample]) -> list[SampleResult]:
        results: list[SampleResult | None] = [None] * len(samples)
        images, where, t_scans = [], [], []
        for i, sample in enumerate(samples):
            t0 = time.perf_counter()
            try:
                scan = self.scan(sample)
            except InvalidSample as exc:
                results[i] = SampleResult(sample, Status.INVALID, str(exc),
                                          t_scan=time.perf_counter() - t0,
                                          seed=sample_seed(self.space, sample))
                continue
            images.append(scan.image)
            where.append(i)
            t_scans.append(time.perf_counter() - t0)
        if images:
            t0 = time.perf_counter()
            pred = self.model.predict(np.stack(images))
            t_infer = (time.perf_counter() - t0) / len(images)
            for k, i in enumerate(where):
                label = images[k][..., 5].astype(np.uint8)
                counts = confusion(pred.classes[k], label, len(CLASSES))
                metrics: dict[str, float | int | None] = {}
                notes = {}
                for cs in class_scores(counts):
                    for m in ("tp", "fp", "fn", "iou", "precision", "recall"):
                        metrics[f"{cs.name}_{m}"] = getattr(cs, m)
                    notes[cs.name] = cs.note
                status = Status.OK if metrics["car_iou"] is not None else Status.UNDEFINED
                results[i] = SampleResult(
                    samples[i], status, "" if status == Status.OK else notes["car"], metrics,
                    car_points=int((pred.classes[k] == 1).sum()),
                    label_points=int((label == 1).sum()),
                    t_scan=t_scans[k], t_infer=t_infer, t_total=t_scans[k] + t_infer,
                    seed=sample_seed(self.space, samples[i]))
        return [r for r in results if r is not None]


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
                 address: str | None = None):
        self.settings = settings
        self.executor = executor   # "process" (local processes) or "ray" (actors on a cluster)
        self.address = address     # the Ray head (None: the running or a new local instance)
        self.store = store
        self.workers = workers
        self.batch = batch
        self.progress = progress or Progress(None)
        self.model = model     # this process's open model (else loaded on entry)
        self._local: Evaluator | None = None
        self._local_lock = threading.Lock()   # one warm scanner and session: one thread at a time
        self._pool: ProcessPoolExecutor | None = None
        self.ray = None            # the RayExecutor with --executor ray
        self.model_hash = ""

    def __enter__(self) -> Driver:
        if self.executor == "ray":
            from falsify.cluster import RayExecutor
            if self.model is None:
                self.model = load_segmenter(self.settings.model, backend=self.settings.backend,
                                            threads=1)
            self.model_hash = self.model.model_hash
            self.ray = RayExecutor(self.settings, self.workers, self.address).__enter__()
        elif self.workers <= 1:
            self._local = Evaluator(self.settings, model=self.model)
            self.model_hash = self._local.model_hash
        else:   # each worker process opens the model once for itself
            if self.model is None:
                self.model = load_segmenter(self.settings.model, backend=self.settings.backend,
                                            threads=1)
            self.model_hash = self.model.model_hash
            ctx = mp.get_context("spawn")
            self._pool = ProcessPoolExecutor(self.workers, mp_context=ctx,
                                             initializer=_init_worker,
                                             initargs=(self.settings,))
        return self

    def __exit__(self, *exc) -> None:
        if self._pool is not None:
            self._pool.shutdown(cancel_futures=True)
        if self.ray is not None:
            self.ray.__exit__(*exc)

    def evaluate(self, samples: Sequence[Sample]) -> list[float | None]:
        """The samplers' callback: scores in order, stored ones read back, the rest computed.

        Safe to call from several threads. Two threads asking for the same new sample at once
        may both compute it; the store keeps the first row and counts it once."""
        todo: list[Sample] = []
        seen = set()
        for s in samples:
            if s not in self.store and s not in seen:
                todo.append(s)
                seen.add(s)
        known = [s for s in samples if s in self.store and s not in seen]
        if known:
            self.progress.update([SampleResult(s, Status.OK,
                                               metrics={"car_iou": self.store.score(s)})
                                  for s in known], 0)
        chunks = [todo[i:i + self.batch] for i in range(0, len(todo), self.batch)]
        if self.ray is not None:
            outputs = self.ray.map(chunks)
        elif self._local is not None:
            outputs = map(self._score_locally, chunks)
        else:
            assert self._pool is not None
            outputs = self._pool.map(_work, chunks)
        for chunk_results in outputs:
            fresh = self.store.add(chunk_results, self.model_hash,
                                   self.settings.space.config_hash)
            self.progress.update(chunk_results, fresh)
        return [self.store.score(s) for s in samples]

    def _score_locally(self, chunk: list[Sample]) -> list[SampleResult]:
        assert self._local is not None
        with self._local_lock:
            return self._local.score_batch(chunk)
