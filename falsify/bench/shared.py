"""`falsify bench pipeline --inference shared` (the default with `--device cuda`): samples/s
end to end with one inference process fed by CPU workers, against its two ceilings measured in
the same run: the network alone on its device in the server's batches, and the workers' scan
rate with no network. The goal is end to end >= 0.8 of the lower ceiling.
"""

from __future__ import annotations

import multiprocessing as mp
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from falsify.bench.machine import machine
from falsify.bench.scan import possible, warm
from falsify.checks import MAX_SAMPLES
from falsify.data.real_backgrounds import scanner_for
from falsify.errors import FalsifyError
from falsify.world.space import Sample, Space, load_space

GOAL = 0.8


def bench_shared(config: str | Path, samples: int = 80, workers: int = 2,
                 model: str | None = None, device: str = "cpu", batch: int = 8,
                 backend: str = "onnx") -> dict:
    """The three rates and their ratio; each timed after a warm-up chunk per worker."""
    from falsify.executors.driver import Driver, Progress
    from falsify.executors.environment import gpu_name
    from falsify.executors.evaluator import EvalSettings
    from falsify.executors.inference import MAX_BATCH
    from falsify.models.runners import backend_for, load_segmenter
    from falsify.results.store import Store

    space = load_space(config)
    space.check_size(MAX_SAMPLES, "the benchmark's limit")
    grid = possible(scanner_for(space), space.grid())
    if samples <= workers * batch or samples > len(grid):
        raise FalsifyError(f"--samples: {samples} must be more than {workers} x {batch} (the "
                           f"warm-up chunks) and at most the config's {len(grid)} samples")
    picked = grid[:samples]
    streets = tuple(sorted({s.background for s in picked}))
    backend = backend_for(model, backend)
    settings = EvalSettings(space=space, model=model, backend=backend, threads=1,
                            device=device, warm_backgrounds=streets)
    with tempfile.TemporaryDirectory() as tmp:
        store = Store(Path(tmp) / "results.sqlite", space)
        with Driver(settings, store, workers=workers, batch=batch, progress=Progress(None),
                    inference="shared") as driver:
            driver.evaluate(picked[:workers * batch])
            t0 = time.perf_counter()
            driver.evaluate(picked[workers * batch:])
            e2e = (samples - workers * batch) / (time.perf_counter() - t0)
        store.close()
    scan_rate = _scan_rate(space, picked, workers, batch, streets)

    # The network alone, as the server runs it: batches of MAX_BATCH frames on the device
    # (padded on a GPU), one frame at a time on the CPU; warm first.
    seg = load_segmenter(model, backend=backend, threads=2 if device == "cpu" else None,
                         device=device)
    if device == "cuda" and hasattr(seg, "batch"):
        seg.batch = MAX_BATCH
    ev_sim = scanner_for(space)
    warm(ev_sim, picked)
    images = np.stack([_scan(ev_sim, space, s).image for s in picked])
    step = MAX_BATCH
    seg.predict(images[:step])
    t0 = time.perf_counter()
    for i in range(0, len(images), step):
        seg.predict(images[i:i + step])
    network = len(images) / (time.perf_counter() - t0)
    ceiling = min(network, scan_rate)
    return {"benchmark": "pipeline-shared", "config": str(config), "samples": samples,
            "workers": workers, "device": device, "model": seg.spec.name, "backend": backend,
            "e2e_samples_per_s": round(e2e, 2),
            "network_alone_frames_per_s": round(network, 2),
            "scan_only_samples_per_s": round(scan_rate, 2),
            "e2e_over_lower_ceiling": round(e2e / ceiling, 3), "goal": GOAL,
            "within_goal": e2e / ceiling >= GOAL, "server_batch": MAX_BATCH,
            "network_threads": "2 on the CPU (the server's own), the device's on cuda",
            **({"gpu": gpu_name()} if device == "cuda" else {}), "machine": machine()}


def _scan(sim, space: Space, sample: Sample):
    from falsify.results.samples import sample_seed
    return sim.scan(sample, rng=np.random.default_rng(sample_seed(space, sample)))


_sim = None
_space: Space | None = None


def _init(space: Space, streets: tuple[int, ...]) -> None:
    global _sim, _space
    _space = space
    _sim = scanner_for(space)
    for bg in streets:
        _sim.background_hits(bg, _sim.ego_pose(bg))


def _cast(chunk: list[Sample]) -> int:
    assert _sim is not None and _space is not None
    for s in chunk:
        _scan(_sim, _space, s)
    return len(chunk)


def _scan_rate(space: Space, picked: list[Sample], workers: int, batch: int,
               streets: tuple[int, ...]) -> float:
    """Samples/s that `workers` processes cast and label with no network (streets built
    first, one warm-up chunk each)."""
    chunks = [picked[i:i + batch] for i in range(0, len(picked), batch)]
    with ProcessPoolExecutor(workers, mp_context=mp.get_context("spawn"), initializer=_init,
                             initargs=(space, streets)) as pool:
        list(pool.map(_cast, chunks[:workers]))
        t0 = time.perf_counter()
        n = sum(pool.map(_cast, chunks[workers:]))
        return n / (time.perf_counter() - t0)
