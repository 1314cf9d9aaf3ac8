"""sample -> scene -> scan -> network -> metrics: the unit of work every executor runs.

An Evaluator holds a Simulator (BVHs, cached background hits) and an inference session for a
whole run and scores samples in batches; executors keep one warm per worker.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from falsify.models.runner import Segmenter, load_segmenter
from falsify.results.metrics import CLASSES, Status, class_scores, confusion
from falsify.results.store import SampleResult, sample_seed
from falsify.sensor.lidar import load_sensor
from falsify.sensor.simulator import InvalidSample, Scanner, Simulator
from falsify.world.space import Sample, Space


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
