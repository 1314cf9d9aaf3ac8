"""Write small, realistic run directories (results.sqlite + run metadata) without the network.

Car IoU comes from a smooth function of position (low near the sensor and at the edges of the
view, as in the paper) plus per-background noise, so maps have blind spots where a real run
would; TP/FP/FN are chosen to give that IoU. Every value is fixed by the seed.
"""

from __future__ import annotations

import hashlib
import math
import tomllib
import zlib
from collections.abc import Callable, Mapping
from pathlib import Path

import numpy as np

from falsify.results.samples import SampleResult, sample_key
from falsify.results.store import STORE_NAME, Store
from falsify.world.space import Sample, Space, parse_space

ROOT = Path(__file__).resolve().parent.parent
CONFIGS = ROOT / "configs"
SMOKE = CONFIGS / "smoke.toml"
PAPER = CONFIGS / "paper.toml"

IouFn = Callable[[Sample], float | None]


def default_iou(sample: Sample, seed: int = 0) -> float:
    """Paper-like car IoU: weak close to the sensor and off to the sides, noisy per background."""
    x, y = float(sample["x"]), float(sample["y"])
    near = math.exp(-(((y - 5.0) / 3.0) ** 2)) * (0.35 + 0.05 * abs(x))
    far = 0.01 * max(0.0, y - 12.0)
    noise = (zlib.crc32(f"{seed}:{sample_key(sample)}".encode()) % 1000) / 1000.0 - 0.5
    return float(np.clip(0.88 - near - far + 0.12 * noise, 0.0, 1.0))


def synthetic_result(sample: Sample, iou: float | None, index: int, status: str = "ok",
                     reason: str = "") -> SampleResult:
    """A SampleResult whose car TP/FP/FN give `iou` (to within one point)."""
    if status == "invalid":
        return SampleResult(sample, "invalid", reason or "car 1 overlaps the ego car",
                            t_scan=0.004, t_total=0.004, seed=index)
    d = math.hypot(float(sample["x"]), float(sample["y"]))
    label = max(40, int(4000 * (8.0 / max(d, 1.0)) ** 2))
    metrics: dict[str, float | int | None] = {}
    for cls in ("unknown", "pedestrian", "cyclist"):
        metrics.update({f"{cls}_tp": 0, f"{cls}_fp": 0, f"{cls}_fn": 0, f"{cls}_iou": None,
                        f"{cls}_precision": None, f"{cls}_recall": None})
    metrics.update({"unknown_tp": 25000 - label, "unknown_fp": 30, "unknown_fn": 30,
                    "unknown_iou": 0.99, "unknown_precision": 0.995, "unknown_recall": 0.995})
    if status == "undefined" or iou is None:
        metrics.update({"car_tp": 0, "car_fp": 0, "car_fn": 0})
        return SampleResult(sample, "undefined", reason or "no car in label or prediction",
                            metrics, 0, 0, 0.02, 0.03, 0.05, index)
    fn = round(label * (1.0 - iou) * 0.6)
    tp = label - fn
    fp = max(0, round(tp / iou - tp - fn)) if iou > 0 else label
    if iou <= 0:
        tp, fn = 0, label
    union = tp + fp + fn
    metrics.update({"car_tp": tp, "car_fp": fp, "car_fn": fn, "car_iou": tp / union,
                    "car_precision": tp / (tp + fp) if tp + fp else None,
                    "car_recall": tp / (tp + fn)})
    return SampleResult(sample, "ok", "", metrics, tp + fp, label, 0.02, 0.03, 0.05, index)


def write_run(run: Path, config: Path | str = SMOKE, *, command: str = "grid",
              iou: IouFn | None = None, seed: int = 0, samples: list[Sample] | None = None,
              meta: Mapping[str, object] | None = None, undefined_every: int = 0,
              invalid_every: int = 0, invalid_reason: str | Callable[[int], str] = "") -> Path:
    """Write `run`/results.sqlite for `config` (a path or TOML text) and return `run`.

    Grid runs score every grid sample; search runs score `samples` (default: 40 seeded random
    points). `iou(sample)` overrides the IoU (None marks the sample undefined); every k-th
    sample can be made undefined or invalid (with `invalid_reason`, or `invalid_reason(i)` for
    the i-th sample). `meta` overrides
    metadata keys.
    """
    if isinstance(config, Path):
        text, config_path = config.read_text(), str(config)
    else:
        text, config_path = config, "inline.toml"
    config_hash = hashlib.sha256(text.encode()).hexdigest()
    space = parse_space(tomllib.loads(text), source=config_path, config_hash=config_hash)
    if samples is None:
        samples = space.grid() if command == "grid" else random_samples(space, 40, seed)
    run.mkdir(parents=True, exist_ok=True)
    store = Store(run / STORE_NAME, space)
    results = []
    for i, s in enumerate(samples):
        if invalid_every and i % invalid_every == invalid_every - 1:
            reason = invalid_reason(i) if callable(invalid_reason) else invalid_reason
            results.append(synthetic_result(s, None, i, "invalid", reason))
            continue
        value = iou(s) if iou is not None else default_iou(s, seed)
        undefined = value is None or (undefined_every and i % undefined_every == 0)
        results.append(synthetic_result(s, None if undefined else value, i,
                                        "undefined" if undefined else "ok"))
    model_hash = "5e6f" * 16
    store.add(results, model_hash=model_hash, config_hash=config_hash)
    curve = [r.score for r in results]
    values = {
        "command": command, "config_path": config_path, "config_text": text,
        "config_hash": config_hash, "sensor": space.sensor,
        # the config's own name (Space.name is shadowed in parse_space by an image-dim loop)
        "space_name": tomllib.loads(text).get("name", space.name),
        "model_path": None, "model_name": "squeezeseg", "model_hash": model_hash,
        "backend": "onnx", "seed": seed, "algorithm": "grid" if command == "grid" else "nlopt",
        "budget": None if command == "grid" else len(samples), "threshold": space.threshold,
        "started": "2024-05-01T12:00:00+00:00", "elapsed_s": 12.5, "workers": 2,
        "curve": curve,
    }
    values.update(meta or {})
    store.set_meta(**values)
    store.close()
    return run


def random_samples(space: Space, n: int, seed: int = 0) -> list[Sample]:
    """`n` seeded random samples of car 1's position over the space's backgrounds."""
    rng = np.random.default_rng(seed)
    x, y = space.dims["x"], space.dims["y"]
    bgs = space.dims["background"].grid()
    out: list[Sample] = []
    for _ in range(n):
        out.append(space.make({"x": round(float(rng.uniform(x.lo, x.hi)), 3),
                               "y": round(float(rng.uniform(y.lo, y.hi)), 3),
                               "background": bgs[int(rng.integers(len(bgs)))]}))
    return out
