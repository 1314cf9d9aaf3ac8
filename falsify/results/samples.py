"""What one evaluated sample produced, its key and its seed: all a worker needs of results
(no pandas, which the store's readers need and a worker process does not)."""

from __future__ import annotations

import json
import zlib
from dataclasses import dataclass, field

from falsify.results.metrics import Scoring, Status
from falsify.world.space import Sample, Space

CAR_SCORING = Scoring()   # four classes, car IoU the objective: every run until told otherwise


@dataclass(frozen=True)
class SampleResult:
    """What one evaluated sample produced; metrics are None where undefined or invalid."""

    sample: Sample
    status: Status
    reason: str = ""
    metrics: dict[str, float | int | None] = field(default_factory=dict)
    car_points: int = 0         # points predicted car
    label_points: int = 0       # points labelled car
    t_scan: float = 0.0
    t_infer: float = 0.0
    t_total: float = 0.0
    seed: int = 0
    score_column: str = "car_iou"   # the metric the samplers minimise (Scoring.score_column)

    @property
    def score(self) -> float | None:
        """The objective (car IoU unless the run says otherwise) the samplers minimise; None
        when invalid or undefined."""
        v = self.metrics.get(self.score_column)
        return None if v is None else float(v)


def sample_key(sample: Sample) -> str:
    return json.dumps(sample.values, separators=(",", ":"))


def sample_seed(space: Space, sample: Sample) -> int:
    """A per-sample seed for sensor effects: fixed by the space's seed and the sample's LiDAR
    dims alone, so a camera-only dim (colour, weather, time of day) leaves the scan as it is."""
    key = json.dumps(sample.lidar_values, separators=(",", ":"))
    return (space.seed * 1_000_003 + zlib.crc32(key.encode())) % (2**31)
