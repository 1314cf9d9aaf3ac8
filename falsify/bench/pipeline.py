"""`falsify bench pipeline`: samples per second through the whole pipeline against inference
alone, the machine's own matrix rate and the store, in one run; optionally on Ray actors.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from falsify.bench.machine import (
    InferenceRates,
    MatmulRate,
    MemoryUse,
    RssSampler,
    inference_rates,
    machine,
    matmul_rate,
)
from falsify.bench.scan import possible, warm
from falsify.checks import MAX_SAMPLES
from falsify.data.real_backgrounds import scanner_for
from falsify.errors import FalsifyError
from falsify.models.flops import FlopCount
from falsify.models.runners import BATCH
from falsify.world.space import Sample, Space, load_space


@dataclass(frozen=True)
class PipelineBench:
    """Samples/s through the pipeline in one process against inference alone, and through the
    driver and store on 1 and `workers` processes; beside them, from the same run, the
    machine's matrix-product rate, the network's FLOPs and inference-only rates in 1 and
    `workers` processes, and the memory of the `workers`-process driver run."""

    config: str
    samples: int
    model: str
    model_hash: str
    machine: dict
    batch: int              # samples per task
    t_pipeline: float       # s for all samples in one process
    t_infer: float          # s for inference alone on the same scans
    workers: int
    driver_samples: int     # samples timed through the driver
    t_driver: float
    store_rows_per_s: float   # the driver's SQLite writes, in chunks of `batch` rows
    driver_1_samples: int     # samples timed through the driver with 1 worker, 1 thread
    t_driver_1: float
    inference: InferenceRates | None   # inference alone, 1 thread a process, 1 and `workers`
    #                                    at once (ONNX models; None for a plug-in)
    matmul: MatmulRate
    flops: FlopCount | None            # None for a plug-in: its graph is not ours to count
    memory: MemoryUse | None      # the `workers`-process driver run (None without /proc)
    driver_threads: int = 1       # inference threads of each worker in the `workers` run
    streets: int = 0              # backgrounds among the samples: built by each worker first
    t_streets: float = 0.0        # s to build them all once (cold, in one process)
    ray: dict | None = None   # with executor "ray": actors against the processes above
    backend: str = "onnx"     # what ran the network: onnx, torch, or python (a plug-in)

    @property
    def samples_per_s(self) -> float:
        return round(self.e2e_n, 2)

    @property
    def overhead(self) -> float:
        return round(self.t_pipeline / self.t_infer - 1.0, 4)

    @property
    def e2e_1(self) -> float:
        return self.driver_1_samples / self.t_driver_1

    @property
    def e2e_n(self) -> float:
        return self.driver_samples / self.t_driver

    @property
    def achieved_gflops(self) -> float:
        """The network's GFLOP/s in one worker, one thread, inference alone."""
        return self.flops.total * self.inference.rate_1 / 1e9

    @property
    def achieved_gflops_per_worker_n(self) -> float:
        """The same per worker while `workers` processes infer at once."""
        return self.flops.total * self.inference.rate_n / self.inference.processes / 1e9

    def ratios(self) -> dict:
        """What the goals are read from, every one computed from the fields beside it."""
        if self.inference is None or self.flops is None:   # a plug-in: the pipeline's own
            return {"workers": self.workers,
                    "e2e_n_over_e2e_1": round(self.e2e_n / self.e2e_1, 3)}
        return {
            "workers": self.workers,
            "e2e_n_over_e2e_1": round(self.e2e_n / self.e2e_1, 3),
            "e2e_n_over_inference_only_n": round(self.e2e_n / self.inference.rate_n, 3),
            "achieved_over_matmul_1_core": round(
                self.achieved_gflops / self.matmul.gflops_1_core(), 3),
            "achieved_per_worker_n_over_matmul_per_core_n": round(
                self.achieved_gflops_per_worker_n / self.matmul.gflops_per_core(), 3),
            "inference_only_n_over_1": round(self.inference.rate_n / self.inference.rate_1, 3),
            "matmul_per_core_n_over_1_core": round(
                self.matmul.gflops_per_core() / self.matmul.gflops_1_core(), 3),
        }

    def to_json(self) -> dict:
        n, w = self.samples, self.workers
        inf = self.inference
        return {
            "benchmark": "pipeline", "config": self.config, "samples": n,
            "model": self.model, "model_hash": self.model_hash, "backend": self.backend,
            "machine": self.machine,
            "samples_per_task": self.batch, "network_batch": BATCH,
            "one_process": {
                "samples_per_s": round(n / self.t_pipeline, 2),
                "inference_only_samples_per_s": round(n / self.t_infer, 2),
                "ms_per_sample": round(self.t_pipeline / n * 1e3, 2),
                "inference_ms_per_sample": round(self.t_infer / n * 1e3, 2),
                "overhead": self.overhead,
            },
            f"{w}_workers": {"samples_per_s": self.samples_per_s,
                             "samples": self.driver_samples},
            "driver_store_rows_per_s": round(self.store_rows_per_s, 1),
            "streets": {
                "count": self.streets,
                "build_ms_each": round(self.t_streets / max(self.streets, 1) * 1e3, 1),
                "note": "the driver runs start with every street built in each worker (the "
                        "steady state of a long run); a run pays build_ms_each once per street "
                        "and worker on top",
            },
            "rates": {
                "workers": w, "threads_per_worker": 1,
                "e2e_n_threads_per_worker": self.driver_threads,
                **({} if inf is None else {
                    "inference_only_1_worker": round(inf.rate_1, 2),
                    "inference_only_1_worker_ms_per_frame": round(1e3 / inf.rate_1, 2),
                    "inference_only_n_workers": round(inf.rate_n, 2),
                    "frames_1": inf.frames_1, "frames_n": inf.frames_n}),
                "e2e_1_worker": round(self.e2e_1, 2),
                "e2e_n_workers": round(self.e2e_n, 2),
                "e2e_samples_1": self.driver_1_samples, "e2e_samples_n": self.driver_samples,
                "units": "samples (frames) per second",
            },
            "matmul": self.matmul.to_json(),
            "network": None if inf is None or self.flops is None else {
                **self.flops.to_json(),
                "achieved_gflops_1_thread": round(self.achieved_gflops, 2),
                "achieved_gflops_per_worker_n_at_once": round(
                    self.achieved_gflops_per_worker_n, 2)},
            "ratios": self.ratios(),
            "memory": None if self.memory is None else {
                **self.memory.to_json(), "run": f"the {w}-worker driver run above",
                "window": "its timed part, after the warm-up chunks"},
            **({} if self.ray is None else {"ray": self.ray}),
        }


def bench_pipeline(config: str | Path, samples: int = 80, workers: int = 2,
                   model: str | None = None, batch: int = 8,
                   executor: str = "process", backend: str = "onnx") -> PipelineBench:
    """End-to-end samples/s through the real driver and store on `workers` processes (its
    memory sampled) and on one, the pipeline's overhead over the network's own inference time on
    the same scans in the same process, the network alone in 1 and `workers` processes, its
    FLOPs and the machine's matrix-product rate; with executor "ray", also through `workers`
    Ray actors on the same samples, and Ray's cost per task."""
    import tempfile

    from falsify.executors.evaluator import EvalSettings, Evaluator
    from falsify.models.flops import count_flops
    from falsify.models.runners import backend_for, resolve_model
    from falsify.results.store import Store

    space = load_space(config)
    picked = _pick(space, config, samples, workers, batch)
    backend = backend_for(model, backend)   # a plug-in runs as "python"

    with tempfile.TemporaryDirectory() as tmp:
        # 1. Through the driver, the store and `workers` processes, as `falsify grid` runs;
        # first, while this process holds nothing else, so its memory is the driver's own.
        # The driver runs time the steady state: each worker builds every street of the picked
        # samples when it starts (a street is built once per worker and run; its cost is
        # measured on its own below), as a long run amortises it.
        streets = tuple(sorted({s.background for s in picked}))
        store = Store(Path(tmp) / "results.sqlite", space)
        settings = EvalSettings(space=space, model=model, backend=backend,
                                threads=1 if workers > 1 else 2, warm_backgrounds=streets)
        rest = picked[workers * batch:]
        with RssSampler() as rss:
            t0, t1 = _driver_window(settings, store, workers, batch, picked, "process")
        store.close()
        t_driver, memory = t1 - t0, rss.summary(t0, t1)

        # 2. What a street costs a worker: generated and cast once, cold, in this process
        # (with `workers` 1, run 1 was in this process too and left the generated streets
        # cached: then only the BVH and the cast are timed).
        t_streets = _street_build_time(space, streets)

        # 3. The same as 1 with one worker, one thread, in this process.
        store = Store(Path(tmp) / "one.sqlite", space)
        one = EvalSettings(space=space, model=model, backend=backend, threads=1,
                           warm_backgrounds=streets)
        t_driver_1 = _driver_time(one, store, 1, batch, picked, "process")
        store.close()

        # 4. In one process with 2 inference threads: the pipeline against inference alone.
        ev = Evaluator(EvalSettings(space=space, model=model, backend=backend, threads=2))
        scored, images, t_pipeline, t_infer = _one_process_times(ev, picked, batch)

        # 5. The network alone on the same scans, 1 thread a process: 1 and `workers` at once;
        # then the machine's own matrix product the same way.
        inference = (inference_rates(model, np.stack(images), workers, batch, Path(tmp))
                     if backend == "onnx" else None)
        del images
        matmul = matmul_rate(workers)

        ray = (_ray_bench(settings, Path(tmp) / "ray.sqlite", workers, batch, picked, t_driver)
               if executor == "ray" else None)
        rows_per_s = _store_rate(Path(tmp) / "writes.sqlite", space, scored, ev.model_hash)
    return PipelineBench(
        config=str(config), samples=samples, model=ev.model.spec.name,
        model_hash=ev.model_hash[:12], machine=machine(), batch=batch, t_pipeline=t_pipeline,
        t_infer=t_infer, workers=workers, driver_samples=len(rest), t_driver=t_driver,
        store_rows_per_s=rows_per_s, driver_1_samples=len(picked[batch:]),
        t_driver_1=t_driver_1, inference=inference, matmul=matmul,
        flops=count_flops(resolve_model(model)) if backend == "onnx" else None, memory=memory,
        driver_threads=settings.threads, ray=ray, streets=len(streets), t_streets=t_streets,
        backend=backend)


def _pick(space: Space, config: str | Path, samples: int, workers: int, batch: int
          ) -> list[Sample]:
    """The first `samples` of the space's grid that a real street leaves possible; FalsifyError
    where they do not outnumber the warm-up chunks or the grid holds fewer."""
    space.check_size(MAX_SAMPLES, "the benchmark's limit")
    grid = possible(scanner_for(space), space.grid())   # a real street's collisions left out
    if samples <= workers * batch:
        raise FalsifyError(f"--samples: {samples} must be more than the first chunk of each "
                           f"worker ({workers} x {batch}), which warms it up")
    if samples > len(grid):   # the driver would read the repeats back from its store
        raise FalsifyError(f"--samples: {samples} is more than the {len(grid)} samples of "
                           f"{config}; the driver would answer the repeats from its store")
    return grid[:samples]


def _street_build_time(space: Space, streets: tuple) -> float:
    """Seconds to generate and cast every street once, cold, in this process."""
    t0 = time.perf_counter()
    sim = scanner_for(space)
    for bg in streets:
        sim.background_hits(bg, sim.ego_pose(bg))
    return time.perf_counter() - t0


def _one_process_times(ev, picked: list[Sample], batch: int
                       ) -> tuple[list, list[np.ndarray], float, float]:
    """The whole pipeline in this process against inference alone on the same scans: the
    scored chunks, the scan images, and the seconds each took (after a warm-up chunk)."""
    warm(ev.sim, picked)
    ev.score_batch(picked[:batch])
    scored = []
    t0 = time.perf_counter()
    for i in range(0, len(picked), batch):
        scored.append(ev.score_batch(picked[i:i + batch]))
    t_pipeline = time.perf_counter() - t0
    images = [ev.scan(s).image for s in picked]
    t0 = time.perf_counter()
    for i in range(0, len(picked), batch):
        ev.model.predict(np.stack(images[i:i + batch]))
    return scored, images, t_pipeline, time.perf_counter() - t0


def _ray_bench(settings, path: Path, workers: int, batch: int, picked: list[Sample],
               t_driver: float) -> dict:
    """The driver's run on `workers` Ray actors, storing to `path`, against the processes'
    (`t_driver`), and Ray's own cost per task."""
    from falsify.results.store import Store

    store = Store(path, settings.space)
    t_ray = _driver_time(settings, store, workers, batch, picked, "ray")
    store.close()
    rest = picked[workers * batch:]
    return {"actors": workers, "samples_per_s": round(len(rest) / t_ray, 2),
            "against_processes": round(t_driver / t_ray, 3),
            **_ray_task_cost(settings, workers)}


def _driver_window(settings, store, workers: int, batch: int, picked: list[Sample],
                   executor: str) -> tuple[float, float]:
    """perf_counter at start and end of the driver's run over all but the first `workers`
    chunks (which warm it up)."""
    from falsify.executors.driver import Driver, Progress

    with Driver(settings, store, workers=workers, batch=batch, progress=Progress(None),
                executor=executor) as driver:
        driver.evaluate(picked[: workers * batch])  # start-up and warm caches
        t0 = time.perf_counter()
        driver.evaluate(picked[workers * batch:])
        return t0, time.perf_counter()


def _driver_time(settings, store, workers: int, batch: int, picked: list[Sample],
                 executor: str) -> float:
    """Seconds the driver takes for all but the first `workers` chunks (which warm it up)."""
    t0, t1 = _driver_window(settings, store, workers, batch, picked, executor)
    return t1 - t0


def _ray_task_cost(settings, workers: int, tasks: int = 200) -> dict:
    """Ray's own cost per task: empty chunks sent to warm actors, one at a time (round trip)
    and `workers` at a time (what a saturated driver pays per task)."""
    from falsify.executors.ray import RayExecutor

    with RayExecutor(settings, workers) as ex:
        list(ex.map([[] for _ in range(10)]))
        actor = ex.actors[0]
        t0 = time.perf_counter()
        for _ in range(tasks):
            ex.ray.get(actor.score.remote([]))
        serial = (time.perf_counter() - t0) / tasks
        t0 = time.perf_counter()
        list(ex.map([[] for _ in range(tasks)]))
        pipelined = (time.perf_counter() - t0) / tasks
    return {"task_round_trip_ms": round(serial * 1e3, 3),
            "driver_ms_per_task": round(pipelined * 1e3, 3), "tasks_timed": tasks}


def _store_rate(path: Path, space: Space, chunks: list, model_hash: str) -> float:
    """Rows/s the driver's store takes, one transaction per chunk as `Driver.evaluate` writes."""
    from falsify.results.store import Store

    store = Store(path, space)
    t0 = time.perf_counter()
    n = 0
    for chunk in chunks:
        store.add(chunk, model_hash, space.config_hash)
        n += len(chunk)
    dt = time.perf_counter() - t0
    store.close()
    return n / dt
