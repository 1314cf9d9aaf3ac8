"""`falsify bench map`: what the level-set sampler's map costs and how far it is from the grid's.

The full grid is run once (an ordinary, resumable run in OUT/grid). Each level-set run at each
budget and seed then draws its samples from the grid's own rows (the samples are grid samples and
a sample's score is a function of the sample and the network alone, so the scores are those a
live run would get). Each row says what was spent (evaluations, share of the grid) and how the
estimated map stands against the grid's: blind-cell agreement (cells classified alike), false safe
cells (blind in the grid, called safe), false blind cells, mean and max absolute error, and how
many grid values lie inside their cell's interval. Beside it, at the same spend, uniform
sub-sampling: every cell the same number of random samples, the naive way to thin a grid.
`--timed` also runs the level-set search for real (OUT/level-set, no budget) and compares its
wall time with the grid's: the saving a slow network sees.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from falsify.bench.machine import machine
from falsify.checks import MAX_SAMPLES, check_range
from falsify.errors import FalsifyError
from falsify.results.metrics import Status
from falsify.world.space import Continuous, Sample, Space, load_space

BUDGETS = (0.1, 0.2, 0.3)   # shares of the grid's evaluations
SEEDS = 3
MAX_SEEDS = 100


def sample_key(space: Space, values: dict) -> tuple:
    """A sample's dims as comparable text: floats to 6 significant digits (the store's floats
    and the grid's agree to far more), everything else as written."""
    out = []
    for name, dim in space.dims.items():
        v = values[name]
        out.append(f"{float(v):.6g}" if isinstance(dim, Continuous) else str(v))
    return tuple(out)


@dataclass(frozen=True)
class Lookup:
    """The grid's score of every sample, and an evaluate that answers from it and counts."""

    space: Space
    scores: dict[tuple, float | None]

    def evaluate(self, counter: list[int]):
        def ev(batch: Sequence[Sample]) -> list[float | None]:
            counter[0] += len(batch)
            out = []
            for s in batch:
                key = sample_key(self.space, s.as_dict())
                if key not in self.scores:
                    raise FalsifyError(f"bench map: sample {s.as_dict()} is not in the grid run")
                out.append(self.scores[key])
            return out
        return ev


def lookup_of(data) -> Lookup:
    """The scores of a finished grid run's rows (None where invalid or undefined)."""
    col = data.score_column
    dims = list(data.space.dims)
    scores: dict[tuple, float | None] = {}
    for row in data.frame[[*dims, "status", col]].itertuples(index=False):
        r = dict(zip([*dims, "status", col], row, strict=True))
        v = r[col]
        ok = r["status"] == Status.OK and v is not None and not (
            isinstance(v, float) and math.isnan(v))
        scores[sample_key(data.space, r)] = float(v) if ok else None
    return Lookup(data.space, scores)


def compare_cells(ref: dict[tuple, float], est: dict[tuple, float | None],
                  intervals: dict[tuple, tuple[float, float]] | None, threshold: float) -> dict:
    """How an estimated map stands against the grid's over the cells the grid defines."""
    agree = false_safe = false_blind = inside = 0
    errors = []
    for key, r in ref.items():
        e = est.get(key)
        if e is None:   # the estimate has nothing there: counted as safe (nothing found)
            e_blind, err = False, None
        else:
            e_blind, err = e < threshold, abs(e - r)
        r_blind = r < threshold
        agree += e_blind == r_blind
        false_safe += r_blind and not e_blind
        false_blind += e_blind and not r_blind
        if err is not None:
            errors.append(err)
        if intervals is not None and key in intervals:
            lo, hi = intervals[key]
            inside += lo - 1e-9 <= r <= hi + 1e-9
    n = len(ref)
    return {"agreement": round(agree / n, 4) if n else None, "false_safe": false_safe,
            "false_blind": false_blind,
            "mae": round(float(np.mean(errors)), 4) if errors else None,
            "max_abs_error": round(float(np.max(errors)), 4) if errors else None,
            "interval_coverage": None if intervals is None or not n else round(inside / n, 4)}


def uniform_map(space: Space, lookup: Lookup, spend: int, seed: int) -> dict[tuple, float | None]:
    """Each cell's mean over the same number of its samples, drawn at random (seeded): the
    naive thinning of a grid at `spend` evaluations."""
    from falsify.sampler.level_set import cells_of

    cells = cells_of(space, seed)
    rng = np.random.default_rng(seed)
    per = max(1, spend // max(len(cells.keys), 1))
    out: dict[tuple, float | None] = {}
    for key, samples in zip(cells.keys, cells.samples, strict=True):
        pick = rng.permutation(len(samples))[:per]
        got = [lookup.scores[sample_key(space, samples[k].as_dict())] for k in pick]
        vals = [g for g in got if g is not None]
        out[_cell(key)] = float(np.mean(vals)) if vals else None
    return out


def _cell(key) -> tuple:
    return tuple(f"{float(v):.6g}" if not isinstance(v, str) else v for v in key)


def bench_map(config: str | Path, out: str | Path, budgets: Sequence[float] = BUDGETS,
              seeds: int = SEEDS, model: str | None = None, threshold: float | None = None,
              confidence: float | None = None, workers: int = 2, timed: bool = False) -> dict:
    """The level-set sampler against the full grid at each budget (a share of the grid's
    evaluations; and without one, until every cell is decided), over `seeds` seeds from the
    config's; uniform sub-sampling at the same spend beside it."""
    from falsify.jobs.run import RunRequest, execute
    from falsify.results.store import open_run
    from falsify.sampler.level_set import LevelSetSampler

    check_range(seeds, "--seeds", 1, MAX_SEEDS)
    for b in budgets:
        if not 0 < b <= 1:
            raise FalsifyError(f"--budgets: {b} must be a share of the grid in (0, 1]")
    if threshold is not None and not 0 < threshold <= 1:
        raise FalsifyError(f"--threshold: {threshold} must be in (0, 1]")
    if confidence is not None and not 0.5 <= confidence < 1:   # before the grid's minutes
        raise FalsifyError(f"--confidence: {confidence} must be in [0.5, 1)")
    out = Path(out)
    space = load_space(config)
    space.check_size(MAX_SAMPLES, "the benchmark's limit")
    grid_dir = out / "grid"
    grid = execute(RunRequest(config=Path(config), out=grid_dir, command="grid", model=model,
                              workers=workers, report=False,
                              resume=(grid_dir / "results.sqlite").exists()))
    data = open_run(grid_dir)
    t = threshold if threshold is not None else data.threshold
    lookup = lookup_of(data)
    cmap = data.cell_map()
    ref = {_cell((c.a, c.b)): c.miou for c in cmap.cells() if c.miou is not None}
    n_grid = len(data.frame)
    options = {} if confidence is None else {"confidence": confidence}
    rows = []
    for budget in [*budgets, None]:
        for seed in range(space.seed, space.seed + seeds):
            used = [0]
            res = LevelSetSampler(threshold=t, **options).run(
                space, lookup.evaluate(used), None if budget is None else
                max(1, int(round(budget * n_grid))), seed)
            est = {_cell((c.x, c.y)): c.estimate for c in res.cells}
            iv = {_cell((c.x, c.y)): (c.lower, c.upper) for c in res.cells
                  if c.lower is not None and c.upper is not None}
            row = {"sampler": "level-set", "budget": budget, "seed": seed,
                   "evaluations": used[0], "share": round(used[0] / n_grid, 4),
                   "undecided": sum(not c.decided for c in res.cells),
                   **compare_cells(ref, est, iv, t)}
            rows.append(row)
            uni = uniform_map(space, lookup, used[0], seed)
            rows.append({"sampler": "uniform", "budget": budget, "seed": seed,
                         "evaluations": used[0], "share": round(used[0] / n_grid, 4),
                         "undecided": None, **compare_cells(ref, uni, None, t)})
    summary = [summarise(rows, s, b) for b in [*budgets, None] for s in ("level-set", "uniform")]
    result = {"benchmark": "map", "config": str(config), "model": data.meta.get("model_name"),
              "threshold": t, "grid_samples": n_grid, "cells": len(ref),
              "grid_blind_cells": sum(v < t for v in ref.values()),
              "grid_wall_s": grid.elapsed_s, "seeds": list(range(space.seed, space.seed + seeds)),
              "confidence": confidence or LevelSetSampler().confidence,
              "summary": summary, "rows": rows, "machine": machine()}
    if timed:
        result["timed"] = timed_run(config, out, model, threshold, confidence, workers,
                                    grid.elapsed_s)
    return result


def summarise(rows: list[dict], sampler: str, budget: float | None) -> dict:
    """One budget's rows over seeds: mean spend, worst agreement and false safe cells."""
    mine = [r for r in rows if r["sampler"] == sampler and r["budget"] == budget]
    mae = [r["mae"] for r in mine if r["mae"] is not None]
    return {"sampler": sampler, "budget": budget,
            "share_mean": round(float(np.mean([r["share"] for r in mine])), 4),
            "share_max": max(r["share"] for r in mine),
            "agreement_min": min(r["agreement"] for r in mine),
            "agreement_mean": round(float(np.mean([r["agreement"] for r in mine])), 4),
            "false_safe_max": max(r["false_safe"] for r in mine),
            "false_blind_max": max(r["false_blind"] for r in mine),
            "mae_mean": round(float(np.mean(mae)), 4) if mae else None}


def timed_run(config, out: Path, model, threshold, confidence, workers: int,
              grid_wall: float | None) -> dict:
    """The level-set search run for real, without a budget; its wall time against the grid's
    and its blind cells against the offline figure (the same samples, so the same map)."""
    from falsify.jobs.run import RunRequest, execute

    d = out / "level-set"
    run = execute(RunRequest(config=Path(config), out=d, command="search",
                             algorithm="level-set", model=model, workers=workers, report=False,
                             threshold=threshold, confidence=confidence,
                             resume=(d / "results.sqlite").exists()))
    return {"run": str(d), "evaluations": run.samples, "wall_s": run.elapsed_s,
            "grid_wall_s": grid_wall, "blind_spots": run.blind_spots,
            "speedup": None if not run.elapsed_s or not grid_wall else
            round(grid_wall / run.elapsed_s, 2)}


def map_text(result: dict) -> str:
    """The summary table, a line per sampler and budget."""
    lines = [f"{result['config']}: {result['grid_samples']} grid samples, {result['cells']} "
             f"cells, {result['grid_blind_cells']} blind below {result['threshold']} "
             f"({result['model']}); seeds {result['seeds']}"]
    for s in result["summary"]:
        b = "none" if s["budget"] is None else f"{s['budget']:.0%}"
        lines.append(f"{s['sampler']:10s} budget {b:>5s}: {s['share_mean']:.1%} of the grid "
                     f"(max {s['share_max']:.1%}), agreement min {s['agreement_min']:.1%}, "
                     f"false safe max {s['false_safe_max']}, false blind max "
                     f"{s['false_blind_max']}, MAE {s['mae_mean']}")
    if "timed" in result:
        t = result["timed"]
        lines.append(f"timed: level-set {t['evaluations']} evaluations in {t['wall_s']} s, grid "
                     f"{result['grid_samples']} in {t['grid_wall_s']} s ({t['speedup']}x)")
    return "\n".join(lines)
