"""Our samplers against VerifAI's, side by side, on one street where the network fails.

Every sampler gets the same budget of evaluations of the same Evaluator (scan, network, car IoU)
over the same space. A counterexample is a sample whose car IoU is below the space's threshold;
an invalid sample (the car would stand in a real object) spends an evaluation and is no
counterexample. VerifAI's samplers are told rho = IoU - threshold, so rho < 0 is a
counterexample, as VerifAI's falsifier reads it; an invalid sample is told the rho of IoU 1.

Run it in a virtual environment of its own holding VerifAI and falsify:

    python -m venv /tmp/vfenv && /tmp/vfenv/bin/pip install verifai -e .
    /tmp/vfenv/bin/python research/experiments/verifai_compare.py \
        --out research/experiments/verifai-compare.json

The street is scan 10/000005 of semantickitti-mini's fit split
(research/experiments/verifai-compare.toml), chosen among the fit scans as one where about half of a
coarse grid of positions fails.
"""

from __future__ import annotations

import argparse
import json
import math
import random
import time
from pathlib import Path

import numpy as np

from falsify.executors.evaluator import EvalSettings, Evaluator
from falsify.sampler import make_sampler
from falsify.world.space import Space, load_space

HERE = Path(__file__).resolve().parent
CONFIG = HERE / "verifai-compare.toml"
OURS = ("random", "sobol", "cross-entropy", "bo", "GN_DIRECT_L")
THEIRS = ("random", "halton", "cross-entropy", "simulated-annealing", "multi-armed-bandit",
          "bayesian-optimization")


class Scores:
    """The Evaluator as a function of samples, counting every evaluation it makes."""

    def __init__(self, space: Space):
        self.space = space
        self.evaluator = Evaluator(EvalSettings(space=space, threads=2))
        self.calls = 0

    def __call__(self, samples) -> list[float | None]:
        self.calls += len(samples)
        return [r.score for r in self.evaluator.score_batch(list(samples))]


def ours(name: str, scores: Scores, budget: int, seed: int) -> list[float | None]:
    """The scores of our sampler's evaluations, in its order."""
    return list(make_sampler(name).run(scores.space, scores, budget, seed).curve)


def theirs(name: str, scores: Scores, budget: int, seed: int) -> list[float | None]:
    """The scores of VerifAI's sampler's evaluations: one sample at a time, told its rho."""
    from dotmap import DotMap
    from verifai.features import Box, Feature, FeatureSpace
    from verifai.samplers import FeatureSampler

    space = scores.space
    dims = {d: space.dims[d] for d in ("x", "y", "yaw")}
    features = FeatureSpace({d: Feature(Box([dim.lo, dim.hi])) for d, dim in dims.items()})
    make = {"random": FeatureSampler.randomSamplerFor,
            "halton": FeatureSampler.haltonSamplerFor,
            "cross-entropy": FeatureSampler.crossEntropySamplerFor,
            "simulated-annealing": FeatureSampler.simulatedAnnealingSamplerFor,
            "multi-armed-bandit": FeatureSampler.multiArmedBanditSamplerFor,
            "epsilon-greedy": FeatureSampler.epsilonGreedySamplerFor,
            "bayesian-optimization": FeatureSampler.bayesianOptimizationSamplerFor}[name]
    random.seed(seed)
    np.random.seed(seed)
    # Simulated annealing has no defaults in VerifAI; these restart the temperature every 10
    # evaluations, far more epochs than a budget uses. The other samplers take their defaults.
    sampler = (make(features, DotMap(T=1.0, decay_rate=0.9, iterations=10, num_epoch=1000))
               if name == "simulated-annealing" else make(features))
    out: list[float | None] = []
    rho = None
    for _ in range(budget):
        point = sampler.nextSample(rho)
        sample = space.make({d: float(getattr(point, d)[0]) for d in dims})
        score = scores([sample])[0]
        out.append(score)
        rho = (1.0 if score is None else score) - space.threshold
    return out


def summary(curves: list[list[float | None]], threshold: float) -> dict:
    """Counterexamples and the lowest IoU per seed, with their mean and range."""
    found = [sum(1 for s in c if s is not None and s < threshold) for c in curves]
    lowest = [min((s for s in c if s is not None), default=math.nan) for c in curves]
    return {"counterexamples": found, "lowest": [round(v, 4) for v in lowest],
            "counterexamples_mean": round(float(np.mean(found)), 2),
            "lowest_mean": round(float(np.mean(lowest)), 4),
            "invalid": [sum(1 for s in c if s is None) for c in curves]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--budget", type=int, default=100)
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    space = load_space(CONFIG)
    scores = Scores(space)
    rows = {}
    for side, names, run in (("falsify", OURS, ours), ("verifai", THEIRS, theirs)):
        for name in names:
            t0 = time.perf_counter()
            try:
                curves = [run(name, scores, args.budget, seed) for seed in range(args.seeds)]
            except ImportError as exc:   # VerifAI's BO needs GPyOpt
                rows[f"{side} {name}"] = {"unavailable": str(exc)}
                print(f"{side:8s} {name:22s} unavailable: {exc}")
                continue
            row = summary(curves, space.threshold)
            row["seconds"] = round(time.perf_counter() - t0, 1)
            rows[f"{side} {name}"] = row
            print(f"{side:8s} {name:22s} counterexamples {row['counterexamples']} "
                  f"lowest {row['lowest']} invalid {row['invalid']} ({row['seconds']} s)")
    result = {"config": str(CONFIG.relative_to(HERE.parent.parent)), "budget": args.budget,
              "seeds": args.seeds, "threshold": space.threshold, "samplers": rows}
    if args.out is not None:
        args.out.write_text(json.dumps(result, indent=1) + "\n")


if __name__ == "__main__":
    main()
