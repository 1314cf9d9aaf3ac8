"""sample -> scene -> scan -> network -> metrics: the unit of work every executor runs.

An Evaluator holds a Simulator (BVHs, cached background hits) and an inference session for a
whole run and scores samples in batches; executors keep one warm per worker.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from falsify.data.real_backgrounds import scanner_for
from falsify.errors import FalsifyError
from falsify.models.runners import Segmenter, load_segmenter
from falsify.results.metrics import Scoring, Status
from falsify.results.samples import CAR_SCORING, SampleResult, sample_seed
from falsify.semantic import train_ids
from falsify.sensor.simulator import InvalidSample, Scanner, release_free_heap
from falsify.sensor.weather import effects_of
from falsify.world.space import Sample, Space

# A scene whose placed objects return no point tests nothing of them; in clear weather that is
# geometry (out of view, or behind the scene), so the sample is invalid, not scored on the rest.
UNSEEN = ("no point of the placed object reaches the sensor: it stands outside the sensor's "
          "view or hidden behind the scene")


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
    device: str = "cpu"          # "cpu" or "cuda": where the network runs
    scoring: Scoring = CAR_SCORING   # the classes scored and the objective


class Evaluator:
    """Scores batches of samples with one warm scanner and one inference session; both can be
    handed in (an open model, another scanner), else they are built from the settings."""

    def __init__(self, settings: EvalSettings, model: Segmenter | None = None,
                 scanner: Scanner | None = None):
        self.settings = settings
        self.space = settings.space
        self.sim = scanner or scanner_for(self.space, lod=settings.lod)
        self.model = model or load_segmenter(settings.model, backend=settings.backend,
                                             threads=settings.threads, device=settings.device)
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
        images, truths, where, t_scans, inserted = [], [], [], [], []
        scoring = self.settings.scoring
        for i, sample in enumerate(samples):
            t0 = time.perf_counter()
            try:
                scan = self.scan(sample)
            except InvalidSample as exc:
                results[i] = SampleResult(sample, Status.INVALID, str(exc),
                                          t_scan=time.perf_counter() - t0,
                                          seed=sample_seed(self.space, sample))
                continue
            placed = self.sim.placed_pixels(scan)
            if not placed.any() and effects_of(sample).clear:
                results[i] = SampleResult(sample, Status.INVALID, UNSEEN,
                                          t_scan=time.perf_counter() - t0,
                                          seed=sample_seed(self.space, sample))
                continue
            images.append(scan.image)
            truths.append(truth_ids(scan, scoring))
            inserted.append(placed if scoring.parts else None)
            where.append(i)
            t_scans.append(time.perf_counter() - t0)
        if images:
            t0 = time.perf_counter()
            pred = self.model.predict(np.stack(images))
            t_infer = (time.perf_counter() - t0) / len(images)
            ids = pred.train_ids if scoring.semantic else pred.classes
            for k, i in enumerate(where):
                label = images[k][..., 5].astype(np.uint8)
                metrics, note = scoring.score(ids[k], truths[k], inserted[k],
                                              real_labelled=labelled(self.space, samples[i]))
                col = scoring.score_column
                status = Status.OK if metrics[col] is not None else Status.UNDEFINED
                results[i] = SampleResult(
                    samples[i], status, "" if status == Status.OK else note, metrics,
                    car_points=int((pred.classes[k] == 1).sum()),
                    label_points=int((label == 1).sum()),
                    t_scan=t_scans[k], t_infer=t_infer, t_total=t_scans[k] + t_infer,
                    seed=sample_seed(self.space, samples[i]), score_column=col)
        # A batch's scans and tensors are freed by now; glibc would keep their pages (about
        # 60 MB a worker) for the rest of the run. 3 ms, under 1 % of a batch.
        release_free_heap()
        return [r for r in results if r is not None]


def labelled(space: Space, sample: Sample) -> bool:
    """Whether the sample's background labels its own objects: a street, or a real scan with
    labels (one without, a bare .bin or a scan of `labels = "optional"`, has none to score)."""
    if not space.real_backgrounds:
        return True
    return space.real_backgrounds[int(sample.background)].kind != "none"


def truth_ids(scan, scoring: Scoring) -> np.ndarray:
    """The scan's labels as class ids of `scoring`: the four-class label channel, or the
    SemanticKITTI train ids of its semantic image (FalsifyError if the scan has none)."""
    if not scoring.semantic:
        return scan.image[..., 5].astype(np.uint8)
    if scan.semantic is None:
        raise FalsifyError("this scan carries no SemanticKITTI labels, which a model with "
                           "SemanticKITTI classes is scored on")
    return train_ids(scan.semantic)
