"""Bayesian optimisation: Optuna's TPE sampler, asked for a round of samples at a time.

Why Optuna and TPE: Optuna is maintained and widely used, its TPE (tree-structured Parzen
estimator; Bergstra et al., NeurIPS 2011; multivariate, as Falkner et al.'s BOHB) models mixed
continuous and categorical dims and define-by-run conditional dims natively, needs no torch (its
GP samplers do), and Optuna's ask/tell interface lets this sampler hand the driver whole batches
to score in parallel. Optuna is an optional dependency (`pip install "falsify[bo]"`), imported
only when a `bo` sampler is made, so scoring and gating never import it.

- Each trial suggests `count` first (when it has more than one value), then every other dim
  active for that count, in dim order: continuous dims as floats in [lo, hi], categorical dims
  as categorical parameters over their values; a dim with one value is not a parameter. Dims of
  cars beyond the count are not suggested, and Space.make pins them.
- Rounds of `batch_size` asks, then one tell per trial. Within a round TPE's constant liar
  counts the trials asked but not yet told among the bad ones, so a round's asks spread out
  instead of repeating one point. Until `startup` trials are told, asks are seeded uniform.
  The round (default 8, the driver's chunk for one worker) is part of the algorithm, as
  cross-entropy's is, so it does not follow --workers and the samples never depend on them;
  smaller rounds learn more per evaluation, larger ones keep more workers busy.
- A None (or non-finite) score (an invalid sample, an undefined IoU) is told as `penalty`
  (default 1.0, the best possible IoU, as NLopt's penalty), not as a failed trial: TPE ignores
  failed trials, and would keep proposing the region; the penalty steers it away.
- Deterministic: the TPE sampler is seeded with the run's seed, and Optuna draws nothing else at
  random, so the samples are a function of (space, budget, seed, the scores told).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

from falsify.errors import ConfigError, FalsifyError
from falsify.sampler.base import (
    Evaluate,
    Recorder,
    SearchResult,
    check_batch,
    check_budget,
    covering_grid,
    defined,
    evaluate_all,
)
from falsify.world.space import Categorical, Sample, Space

INSTALL = 'pip install "falsify[bo]"'


def import_optuna() -> Any:
    """The optuna module, or a FalsifyError (exit 2) saying how to install it."""
    try:
        import optuna
    except ImportError:
        raise FalsifyError(f"sampler bo needs Optuna, an optional dependency: {INSTALL}") from None
    return optuna


@dataclass(frozen=True)
class BayesSampler:
    """Rounds of `batch_size` TPE suggestions; `startup` seeded uniform trials first; `penalty`
    the value told for a sample without a score. Making one checks that Optuna is installed. A
    budget that covers a finite space (every dim discrete) scores its grid once, in order."""

    batch_size: int = 8
    startup: int = 10
    penalty: float = 1.0
    name: str = field(default="bo", init=False)

    def __post_init__(self) -> None:
        check_batch(self.name, self.batch_size)
        if isinstance(self.startup, bool) or not isinstance(self.startup, int) or \
                self.startup < 1:
            raise ConfigError(f"sampler {self.name}: startup must be an integer >= 1")
        if isinstance(self.penalty, bool) or not isinstance(self.penalty, int | float) or \
                not math.isfinite(self.penalty):
            raise ConfigError(f"sampler {self.name}: penalty must be a finite number")
        import_optuna()

    def run(self, space: Space, evaluate: Evaluate, budget: int | None,
            seed: int) -> SearchResult:
        n = check_budget(self.name, budget, required=True)
        assert n is not None
        grid = covering_grid(space, n)
        if grid is not None:
            return evaluate_all(self.name, evaluate, grid, self.batch_size)
        optuna = import_optuna()
        optuna.logging.set_verbosity(optuna.logging.WARNING)   # no line per trial
        tpe = optuna.samplers.TPESampler(seed=seed, n_startup_trials=self.startup,
                                         multivariate=True, constant_liar=True)
        study = optuna.create_study(direction="minimize", sampler=tpe)
        rec = Recorder(evaluate)
        done = 0
        while done < n:
            trials = [study.ask() for _ in range(min(self.batch_size, n - done))]
            batch = [self._suggest(space, trial) for trial in trials]
            scores = rec(batch)
            if len(scores) != len(batch):
                raise RuntimeError(f"evaluate returned {len(scores)} scores for "
                                   f"{len(batch)} samples")
            for trial, s in zip(trials, scores, strict=True):
                v = defined(s)
                study.tell(trial, float(self.penalty) if v is None else v)
            done += len(batch)
        return rec.result()

    @staticmethod
    def _suggest(space: Space, trial: Any) -> Sample:
        """The trial's sample: count first, then each dim active for that count."""
        values: dict[str, Any] = {}
        count_dim = space.dims.get("count")
        if count_dim is not None:
            values["count"] = _param(trial, count_dim)
        count = int(values.get("count", 1))
        for name, dim in space.dims.items():
            if name != "count" and space.active(name, count):
                values[name] = _param(trial, dim)
        return space.make(values)


def _param(trial: Any, dim) -> Any:
    """One dim's value from the trial: a parameter when the dim can vary, else its one value."""
    if isinstance(dim, Categorical):
        if len(dim.values) == 1:
            return dim.values[0]
        return trial.suggest_categorical(dim.name, list(dim.values))
    if dim.hi <= dim.lo:
        return float(dim.lo)
    return min(max(trial.suggest_float(dim.name, dim.lo, dim.hi), dim.lo), dim.hi)
