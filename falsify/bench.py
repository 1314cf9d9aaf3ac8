"""Benchmarks behind `falsify bench`: each fast path measured beside its naive path in one run.

Speed claims live here, never in timed unit tests. Each benchmark returns a typed result whose
`to_json()` is what --json prints.
"""

from __future__ import annotations

import dataclasses
import multiprocessing as mp
import os
import platform
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from falsify.bench_machine import (
    InferenceRates,
    MatmulRate,
    MemoryUse,
    RssSampler,
    inference_rates,
    matmul_rate,
)
from falsify.checks import MAX_SAMPLES
from falsify.errors import FalsifyError
from falsify.metrics import Status
from falsify.models.flops import FlopCount
from falsify.models.runner import BATCH
from falsify.scene import Simulator
from falsify.sensor import load_sensor
from falsify.space import Sample, Space, load_space


def machine() -> dict:
    """The CPU by name (figures differ 2x between CPUs), its core count and Python."""
    return {"cpus": os.cpu_count(), "python": platform.python_version(),
            "processor": platform.processor() or platform.machine(), "cpu": cpu_name()}


def cpu_name() -> str | None:
    """The CPU's model name from /proc/cpuinfo (with its family and model numbers, which tell
    generations apart where the name does not); None where there is no /proc."""
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        return None
    fields: dict[str, str] = {}
    for line in text.splitlines():
        key, _, value = line.partition(":")
        fields.setdefault(key.strip(), value.strip())
    name = fields.get("model name")
    if name is None:
        return None
    return f"{name} (family {fields.get('cpu family', '?')}, model {fields.get('model', '?')})"


def _warm(sim: Simulator, samples: list[Sample]) -> None:
    """Build every background's hits and the car BVHs before the clock starts."""
    for bg in sorted({s.background for s in samples}):
        sim.background_hits(bg, sim.ego_pose(bg))
    for s in samples[:4]:
        sim.scan(s)


def _scan_rate(space: Space, samples: list[Sample], lod: int = 2) -> float:
    """Scans per second of the fast path in this process, caches warm."""
    sim = Simulator(load_sensor(space.sensor), space.user_cars, lod=lod)
    _warm(sim, samples)
    t0 = time.perf_counter()
    for s in samples:
        sim.scan(s)
    return len(samples) / (time.perf_counter() - t0)


def _scan_worker(args) -> tuple[int, float, float]:
    config, start, stop, lod = args
    space = load_space(config)
    samples = space.grid()[start:stop]
    sim = Simulator(load_sensor(space.sensor), space.user_cars, lod=lod)
    _warm(sim, samples)
    t0 = time.perf_counter()
    for s in samples:
        sim.scan(s)
    return len(samples), t0, time.perf_counter()


def naive_scan(space: Space, sample: Sample):
    """The naive path: rebuild the merged scene for the sample and cast every ray with trimesh's
    exact `intersects_location` (a new BVH per sample), re-casting past porous and glass
    surfaces with the same hash-decided passes as the fast path."""
    import trimesh

    from falsify.backgrounds import build_background
    from falsify.materials import PASS_PROB, STEP, unit_hash
    from falsify.scene import porosity_seed

    sensor = load_sensor(space.sensor)
    sim = Simulator(sensor, space.user_cars)
    bg = build_background(sample.background)
    meshes = [trimesh.Trimesh(bg.vertices, bg.faces, process=False)]
    mats = [bg.materials()]
    for pc in sim.placed_cars(sample):
        m = sim.car_mesh(pc.model).copy()
        m.apply_transform(pc.matrix())
        meshes.append(m)
        mats.append(sim.car_materials(pc.model))
    merged = trimesh.util.concatenate(meshes)
    face_pass = PASS_PROB[np.concatenate(mats)]
    pose = sim.ego_pose(sample.background)
    rot = pose.rotation(sensor)
    d = sensor.directions.reshape(-1, 3) @ rot.T
    o = np.broadcast_to(sim.ray_starts(pose, rot), d.shape).copy()
    ranges = np.zeros(len(d))
    todo, start = np.arange(len(d)), np.zeros(len(d))
    for _ in range(16):
        loc, idx, tri = merged.ray.intersects_location(o[todo] + d[todo] * start[todo, None],
                                                       d[todo], multiple_hits=False)
        ray = todo[idx]
        t = start[ray] + np.linalg.norm(loc - (o[ray] + d[ray] * start[ray, None]), axis=1)
        passed = unit_hash(ray, tri, porosity_seed(sample.background)) < face_pass[tri]
        ranges[ray[~passed]] = t[~passed]
        todo = ray[passed]
        start[todo] = t[passed] + STEP
        if len(todo) == 0:
            break
    ranges[ranges > sensor.max_range] = 0.0
    return ranges.reshape(sensor.shape)


@dataclass(frozen=True)
class ScanBench:
    """Scans/s of the fast path in 1 and `workers` processes against the naive path."""

    config: str
    sensor: str
    samples: int
    workers: int
    machine: dict
    fast_1: float          # scans/s, 1 process
    fast_n: float          # scans/s, `workers` processes
    naive: float           # scans/s, the naive path
    naive_samples: int
    scene_size: dict

    def to_json(self) -> dict:
        w = self.workers
        return {
            "benchmark": "scan", "config": self.config, "sensor": self.sensor,
            "samples": self.samples, "machine": self.machine,
            "fast_scans_per_s_1_process": round(self.fast_1, 1),
            f"fast_scans_per_s_{w}_processes": round(self.fast_n, 1),
            "naive_scans_per_s": round(self.naive, 3),
            "naive_samples": self.naive_samples,
            "speedup_1_process": round(self.fast_1 / self.naive, 1),
            f"speedup_{w}_processes": round(self.fast_n / self.naive, 1),
            "scene_size": self.scene_size,
        }


def bench_scan(config: str | Path, samples: int = 1000, naive_samples: int = 5,
               workers: int = 2) -> ScanBench:
    """Scans/s of the fast path (1 process and `workers` processes) against the naive path, plus
    how flat the per-scan time stays when the background grows and image-only dims change."""
    if samples <= 0 or samples < workers:
        raise FalsifyError(f"--samples: {samples} must be at least the number of workers")
    space = load_space(config)
    space.check_size(MAX_SAMPLES, "the benchmark's limit")
    grid = space.grid()
    picked = [grid[i % len(grid)] for i in range(samples)]
    single = _scan_rate(space, picked)

    chunks = np.array_split(np.arange(samples), workers)
    ctx = mp.get_context("spawn")
    with ctx.Pool(workers) as pool:
        parts = pool.map(_scan_worker, [(str(config), int(c[0]) % len(grid),
                                         int(c[0]) % len(grid) + len(c), 2) for c in chunks])
    start = min(p[1] for p in parts)
    stop = max(p[2] for p in parts)
    multi = sum(p[0] for p in parts) / (stop - start)

    naive_times = []
    for s in picked[:naive_samples]:
        t0 = time.perf_counter()
        naive_scan(space, s)
        naive_times.append(time.perf_counter() - t0)
    naive = 1.0 / float(np.mean(naive_times))

    return ScanBench(str(config), space.sensor, samples, workers, machine(), single, multi,
                     naive, naive_samples, scene_size_effect(space, picked[: min(900, samples)]))


def scene_size_effect(space: Space, samples: list[Sample]) -> dict:
    """Per-scan time with the street as built, with every triangle split in 4 twice (16× the
    triangles), and with 10× the objects far beyond max range, and with image-only dims varied."""
    from falsify.backgrounds import build_background

    def rate(transform) -> tuple[float, int]:
        tri = {}

        def source(bg_id):
            bg = transform(build_background(bg_id))
            tri[bg_id] = len(bg.faces)
            return bg
        sim = Simulator(load_sensor(space.sensor), space.user_cars, background_source=source)
        _warm(sim, samples)
        t0 = time.perf_counter()
        for s in samples:
            sim.scan(s)
        return (time.perf_counter() - t0) / len(samples) * 1e3, int(np.mean(list(tri.values())))

    def subdivided(bg):
        v, f = bg.vertices, bg.faces
        cls, inst, mat = bg.face_class, bg.face_instance, bg.materials()
        for _ in range(2):
            v, f, idx = _subdivide(v, f)
            cls, inst, mat = cls[idx], inst[idx], mat[idx]
        return dataclasses.replace(bg, vertices=v, faces=f, face_class=cls, face_instance=inst,
                                   face_material=mat)

    def far_objects(bg):
        v, f = [bg.vertices], [bg.faces]
        n = len(bg.vertices)
        for k in range(1, 10):
            v.append(bg.vertices + [1000.0 * k, 0.0, 0.0])
            f.append(bg.faces + n * k)
        return dataclasses.replace(
            bg, vertices=np.concatenate(v), faces=np.concatenate(f).astype(np.int32),
            face_class=np.tile(bg.face_class, 10), face_instance=np.tile(bg.face_instance, 10),
            face_material=np.tile(bg.materials(), 10))

    # Best of three, interleaved, so a busy moment of the machine does not land on one variant.
    runs = [(rate(lambda b: b), rate(subdivided), rate(far_objects)) for _ in range(3)]
    (base_ms, base_tri), (sub_ms, sub_tri), (far_ms, far_tri) = (
        min((r[k] for r in runs), key=lambda x: x[0]) for k in range(3))
    image_ms = min(_image_dims_rate(space, samples) for _ in range(3))
    return {
        "ms_per_scan": round(base_ms, 3), "triangles": base_tri,
        "ms_per_scan_16x_triangles": round(sub_ms, 3), "triangles_16x": sub_tri,
        "ms_per_scan_10x_objects_beyond_range": round(far_ms, 3), "triangles_10x": far_tri,
        "ms_per_scan_image_dims_varied": round(image_ms, 3),
        "ratio_16x_triangles": round(sub_ms / base_ms, 3),
        "ratio_10x_objects": round(far_ms / base_ms, 3),
        "ratio_image_dims": round(image_ms / base_ms, 3),
    }


def _image_dims_rate(space: Space, samples: list[Sample]) -> float:
    """Per-scan ms when every sample also changes colour, weather and time of day."""
    from falsify.space import IMAGE_ONLY, Categorical
    dims = dict(space.dims)
    for name, values in zip(IMAGE_ONLY, (("red", "white", "black"), ("sun", "rain", "fog"),
                                         ("noon", "dusk", "night")), strict=True):
        dims[name] = Categorical(name, values)
    wide = dataclasses.replace(space, dims=dims)
    varied = []
    for i, s in enumerate(samples):
        d = s.as_dict()
        d.update(colour=("red", "white", "black")[i % 3], weather=("sun", "rain", "fog")[i % 3],
                 time_of_day=("noon", "dusk", "night")[(i // 3) % 3])
        varied.append(wide.make(d))
    sim = Simulator(load_sensor(space.sensor), space.user_cars)
    _warm(sim, varied)
    t0 = time.perf_counter()
    for s in varied:
        sim.scan(s)
    return (time.perf_counter() - t0) / len(varied) * 1e3


def _subdivide(v: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Split every triangle into 4 at its edge midpoints (same surface, 4× the triangles)."""
    a, b, c = f[:, 0], f[:, 1], f[:, 2]
    n = len(v)
    m = len(f)
    ab, bc, ca = n + np.arange(m), n + m + np.arange(m), n + 2 * m + np.arange(m)
    v2 = np.concatenate([v, (v[a] + v[b]) / 2, (v[b] + v[c]) / 2, (v[c] + v[a]) / 2])
    f2 = np.concatenate([np.stack([a, ab, ca], 1), np.stack([ab, b, bc], 1),
                         np.stack([ca, bc, c], 1), np.stack([ab, bc, ca], 1)]).astype(np.int32)
    return v2, f2, np.tile(np.arange(m), 4)


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
    inference: InferenceRates     # inference alone, 1 thread a process, 1 and `workers` at once
    matmul: MatmulRate
    flops: FlopCount
    memory: MemoryUse | None      # the `workers`-process driver run (None without /proc)
    driver_threads: int = 1       # inference threads of each worker in the `workers` run
    streets: int = 0              # backgrounds among the samples: built by each worker first
    t_streets: float = 0.0        # s to build them all once (cold, in one process)
    ray: dict | None = None   # with executor "ray": actors against the processes above

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
            "model": self.model, "model_hash": self.model_hash, "machine": self.machine,
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
                "inference_only_1_worker": round(inf.rate_1, 2),
                "inference_only_1_worker_ms_per_frame": round(1e3 / inf.rate_1, 2),
                "inference_only_n_workers": round(inf.rate_n, 2),
                "e2e_1_worker": round(self.e2e_1, 2),
                "e2e_n_workers": round(self.e2e_n, 2),
                "frames_1": inf.frames_1, "frames_n": inf.frames_n,
                "e2e_samples_1": self.driver_1_samples, "e2e_samples_n": self.driver_samples,
                "units": "samples (frames) per second",
            },
            "matmul": self.matmul.to_json(),
            "network": {**self.flops.to_json(),
                        "achieved_gflops_1_thread": round(self.achieved_gflops, 2),
                        "achieved_gflops_per_worker_n_at_once": round(
                            self.achieved_gflops_per_worker_n, 2)},
            "ratios": self.ratios(),
            "memory": None if self.memory is None else {
                **self.memory.to_json(), "run": f"the {w}-worker driver run above",
                "window": "its timed part, after the warm-up chunks"},
            **({} if self.ray is None else {"ray": self.ray}),
        }


def bench_pipeline(config: str | Path, samples: int = 300, workers: int = 2,
                   model: str | None = None, batch: int = 8,
                   executor: str = "process") -> PipelineBench:
    """End-to-end samples/s through the real driver and store on `workers` processes (its
    memory sampled) and on one, the pipeline's overhead over the network's own inference time on
    the same scans in the same process, the network alone in 1 and `workers` processes, its
    FLOPs and the machine's matrix-product rate; with executor "ray", also through `workers`
    Ray actors on the same samples, and Ray's cost per task."""
    import tempfile

    from falsify.models.flops import count_flops
    from falsify.models.runner import resolve_model
    from falsify.pipeline import EvalSettings, Evaluator
    from falsify.store import Store

    space = load_space(config)
    space.check_size(MAX_SAMPLES, "the benchmark's limit")
    grid = space.grid()
    if samples <= workers * batch:
        raise FalsifyError(f"--samples: {samples} must be more than the first chunk of each "
                           f"worker ({workers} x {batch}), which warms it up")
    if samples > len(grid):   # the driver would read the repeats back from its store
        raise FalsifyError(f"--samples: {samples} is more than the {len(grid)} samples of "
                           f"{config}; the driver would answer the repeats from its store")
    picked = grid[:samples]

    with tempfile.TemporaryDirectory() as tmp:
        # 1. Through the driver, the store and `workers` processes, as `falsify grid` runs;
        # first, while this process holds nothing else, so its memory is the driver's own.
        # The driver runs time the steady state: each worker builds every street of the picked
        # samples when it starts (a street is built once per worker and run; its cost is
        # measured on its own below), as a long run amortises it.
        streets = tuple(sorted({s.background for s in picked}))
        store = Store(Path(tmp) / "results.sqlite", space)
        settings = EvalSettings(space=space, model=model, threads=1 if workers > 1 else 2,
                                warm_backgrounds=streets)
        rest = picked[workers * batch:]
        with RssSampler() as rss:
            t0, t1 = _driver_window(settings, store, workers, batch, picked, "process")
        store.close()
        t_driver, memory = t1 - t0, rss.summary(t0, t1)

        # 2. What a street costs a worker: generated and cast once, cold, in this process
        # (with `workers` 1, run 1 was in this process too and left the generated streets
        # cached: then only the BVH and the cast are timed).
        t0 = time.perf_counter()
        sim = Simulator(load_sensor(space.sensor), space.user_cars)
        for bg in streets:
            sim.background_hits(bg, sim.ego_pose(bg))
        t_streets = time.perf_counter() - t0
        del sim

        # 3. The same as 1 with one worker, one thread, in this process.
        store = Store(Path(tmp) / "one.sqlite", space)
        one = EvalSettings(space=space, model=model, threads=1, warm_backgrounds=streets)
        t_driver_1 = _driver_time(one, store, 1, batch, picked, "process")
        store.close()

        # 4. In one process with 2 inference threads: the pipeline against inference alone.
        ev = Evaluator(EvalSettings(space=space, model=model, threads=2))
        _warm(ev.sim, picked)
        ev.score_batch(picked[:batch])
        scored = []
        t0 = time.perf_counter()
        for i in range(0, samples, batch):
            scored.append(ev.score_batch(picked[i:i + batch]))
        t_pipeline = time.perf_counter() - t0
        images = [ev.scan(s).image for s in picked]
        t0 = time.perf_counter()
        for i in range(0, samples, batch):
            ev.model.predict(np.stack(images[i:i + batch]))
        t_infer = time.perf_counter() - t0

        # 5. The network alone on the same scans, 1 thread a process: 1 and `workers` at once;
        # then the machine's own matrix product the same way.
        inference = inference_rates(model, np.stack(images), workers, batch, Path(tmp))
        del images
        matmul = matmul_rate(workers)

        ray = None
        if executor == "ray":
            store = Store(Path(tmp) / "ray.sqlite", space)
            t_ray = _driver_time(settings, store, workers, batch, picked, "ray")
            store.close()
            ray = {"actors": workers, "samples_per_s": round(len(rest) / t_ray, 2),
                   "against_processes": round(t_driver / t_ray, 3),
                   **_ray_task_cost(settings, workers)}
        rows_per_s = _store_rate(Path(tmp) / "writes.sqlite", space, scored, ev.model_hash)
    return PipelineBench(
        config=str(config), samples=samples, model=ev.model.spec.name,
        model_hash=ev.model_hash[:12], machine=machine(), batch=batch, t_pipeline=t_pipeline,
        t_infer=t_infer, workers=workers, driver_samples=len(rest), t_driver=t_driver,
        store_rows_per_s=rows_per_s, driver_1_samples=len(picked[batch:]),
        t_driver_1=t_driver_1, inference=inference, matmul=matmul,
        flops=count_flops(resolve_model(model)), memory=memory,
        driver_threads=settings.threads, ray=ray, streets=len(streets), t_streets=t_streets)


def _driver_window(settings, store, workers: int, batch: int, picked: list[Sample],
                   executor: str) -> tuple[float, float]:
    """perf_counter at start and end of the driver's run over all but the first `workers`
    chunks (which warm it up)."""
    from falsify.pipeline import Driver, Progress

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
    from falsify.cluster import RayExecutor

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
    from falsify.store import Store

    store = Store(path, space)
    t0 = time.perf_counter()
    n = 0
    for chunk in chunks:
        store.add(chunk, model_hash, space.config_hash)
        n += len(chunk)
    dt = time.perf_counter() - t0
    store.close()
    return n / dt


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

    from falsify.runs import RunRequest, execute

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


SEARCH_ALGORITHMS = ("random", "sobol", "GN_DIRECT_L", "GN_CRS2_LM")
PER_EVALUATION_GOAL = 1.2   # an NLopt run's seconds per evaluation against random's, at most
NOT_TIMED = ("wall_s and s_per_evaluation are the run's own time (worker start-up and the "
             "search, as its elapsed_s), for runs computed in this invocation only: a run "
             "resumed from an earlier one is null (its time would mix invocations)")


def bench_search(config: str | Path, out: str | Path, algorithms=SEARCH_ALGORITHMS,
                 fraction: float = 0.2, workers: int = 2, model: str | None = None,
                 tolerance: float = 0.02) -> dict:
    """Lowest IoU against evaluations for each search algorithm, against a dense grid, and the
    seconds per evaluation of each on `workers` workers (NLopt runs that many discrete
    combinations at once), against random's.

    Every run is an ordinary run directory under `out` (resumable), so an interrupted benchmark
    continues where it stopped; only runs started in this invocation are timed."""
    import pandas as pd

    from falsify.fileio import write_bytes
    from falsify.runs import RunRequest, RunSummary, execute
    from falsify.store import read_frame

    out = Path(out)
    space = load_space(config)
    space.check_size(MAX_SAMPLES, "the benchmark's limit")
    n_grid = len(space.grid())
    budget = max(1, int(n_grid * fraction))

    def run(name: str, algorithm: str, b: int | None, command: str) -> tuple[RunSummary, bool]:
        """The run's summary, and whether it was computed from scratch in this invocation."""
        d = out / name
        resume = (d / "results.sqlite").exists()
        req = RunRequest(config=Path(config), out=d, command=command, algorithm=algorithm,
                         budget=b, model=model, workers=workers, report=False, resume=resume)
        return execute(req), not resume

    dense, _ = run("grid", "grid", None, "grid")
    g = read_frame(dense.run)
    grid_min = float(g.loc[g["status"] == Status.OK, "car_iou"].min())
    target = grid_min + tolerance
    rows, curves = [], {}
    for algo in algorithms:
        done, fresh = run(algo, algo, budget, "search")
        assert done.search is not None
        low = done.search.lowest
        curves[algo] = low
        hit = next((i + 1 for i, v in enumerate(low) if v is not None and v <= target), None)
        frame = read_frame(done.run)
        wall = float(done.elapsed_s) if fresh and done.elapsed_s is not None else None
        evals = done.search.evaluations
        rows.append({"algorithm": algo, "budget": budget, "evaluations": evals,
                     "distinct_samples": int(len(frame)),
                     "lowest": None if low[-1] is None else round(low[-1], 4),
                     "evaluations_to_target": hit,
                     "fraction_of_grid_to_target": None if hit is None else round(hit / n_grid, 4),
                     "reached": hit is not None, "timed": fresh,
                     "wall_s": None if wall is None else round(wall, 3),
                     "s_per_evaluation": None if wall is None or not evals else
                     round(wall / evals, 5)})
    base = next((r["s_per_evaluation"] for r in rows if r["algorithm"] == "random"), None)
    for r in rows:
        ratio = (None if base is None or r["s_per_evaluation"] is None
                 else round(r["s_per_evaluation"] / base, 3))
        r["s_per_evaluation_vs_random"] = ratio
        if r["algorithm"] not in ("grid", "random", "sobol"):
            r["within_goal"] = None if ratio is None else ratio <= PER_EVALUATION_GOAL
    longest = max(len(c) for c in curves.values())
    table = pd.DataFrame({a: c + [c[-1]] * (longest - len(c)) for a, c in curves.items()})
    table.insert(0, "evaluation", range(1, longest + 1))
    write_bytes(out / "search_curves.csv", table.to_csv(index=False).encode())
    return {"benchmark": "search", "config": str(config), "grid_samples": n_grid,
            "grid_lowest": round(grid_min, 4), "target": round(target, 4),
            "budget": budget, "fraction": fraction, "workers": workers, "algorithms": rows,
            "per_evaluation_goal": f"NLopt at most {PER_EVALUATION_GOAL}x random's seconds "
                                   "per evaluation",
            "timing": NOT_TIMED,
            "curves_csv": str(out / "search_curves.csv"), "machine": machine()}
