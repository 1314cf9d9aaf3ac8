"""`falsify explain`: a stored run's failing region as rules, per-dim sensitivity and clusters.

Reads the run's store read-only through `open_run`; the analysis itself is in
falsify.results.explain and works on any table of samples.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from falsify.checks import check_seed
from falsify.errors import FalsifyError
from falsify.results.explain import MIN_SUPPORT, Explanation, explain, score_name
from falsify.results.store import RunData, check_complete, open_run

MAX_DEPTH = 4
MAX_RULES = 20
MAX_CLUSTERS = 20


@dataclass(frozen=True)
class ExplainResult:
    """A run's explanation and where it came from."""

    run: str
    algorithm: str
    explanation: Explanation

    def to_json(self) -> dict:
        return {"run": self.run, "algorithm": self.algorithm, **self.explanation.to_json()}


def explain_run(run: str | Path, threshold: float | None = None, depth: int = 2,
                rules: int = 5, clusters: int = 4, seed: int = 0,
                allow_incomplete: bool = False) -> ExplainResult:
    """Explain a run's samples below `threshold` (default: the run's own threshold); an
    incomplete run is an error unless allowed (its rules would be of the samples scored)."""
    if not 1 <= depth <= MAX_DEPTH:
        raise FalsifyError(f"--depth {depth}: must be in 1..{MAX_DEPTH}")
    if not 1 <= rules <= MAX_RULES:
        raise FalsifyError(f"--rules {rules}: must be in 1..{MAX_RULES}")
    if not 1 <= clusters <= MAX_CLUSTERS:
        raise FalsifyError(f"--clusters {clusters}: must be in 1..{MAX_CLUSTERS}")
    check_seed(seed)
    if threshold is not None and not 0.0 < threshold <= 1.0:
        raise FalsifyError(f"--threshold {threshold}: must be in (0, 1]")
    data = open_run(run)
    check_complete(data, allow_incomplete)
    return explain_data(data, threshold, depth, rules, clusters, seed)


def explain_data(data: RunData, threshold: float | None = None, depth: int = 2,
                 rules: int = 5, clusters: int = 4, seed: int = 0) -> ExplainResult:
    """Explain a run already opened (the report's, so its store is not read twice)."""
    t = data.threshold if threshold is None else threshold
    algorithm = str(data.meta.get("algorithm") or "grid")
    return ExplainResult(str(data.path), algorithm,
                         explain(data.frame, data.space, t, depth, rules, clusters, seed,
                                 data.score_column))


def format_text(result: ExplainResult) -> str:
    """Rules first (what a user acts on), then the dims by sensitivity, then clusters."""
    e = result.explanation
    lines = [f"{result.run}: {e.failing} of {e.samples} samples with {score_name(e.score)} "
             f"below {e.threshold:g}"]
    if e.rules:
        lines.append(f"rules (support, precision, mean {score_name(e.score)} of the samples each "
                     "covers):")
        for r in e.rules:
            lines.append(f"  {r.text()}: {r.failing} of {r.support} samples below "
                         f"{e.threshold:g}, mean {r.mean_iou:.3f}")
    elif e.samples < MIN_SUPPORT:   # no rule could be found: say so, not that none fits
        lines.append(f"too few valid samples to explain ({e.samples}; a rule needs at least "
                     f"{MIN_SUPPORT})")
    elif e.failing:
        lines.append("no rule covers the failing samples better than the run as a whole")
    if e.sensitivity:
        lines.append(f"share of {score_name(e.score)} variance each dim explains alone "
                     "(first-order index):")
        lines += [f"  {d:12s} {s:.3f}" for d, s in e.sensitivity.items()]
    if e.clusters and result.algorithm != "grid":
        lines.append("clusters of failing samples:")
        for c in e.clusters:
            centre = ", ".join(f"{k}={v}" for k, v in c.centre.items())
            lines.append(f"  {c.size:4d} samples, mean {c.mean_iou:.3f}: {centre}")
    return "\n".join(lines)
