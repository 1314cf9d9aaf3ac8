"""`falsify bench search`: each search algorithm's lowest IoU and cost per evaluation on one
space, in one run, and over several seeds what each finds: counterexamples, lowest IoU and the
distinct failing regions `falsify explain` draws from its rows.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from falsify.bench.machine import machine
from falsify.checks import MAX_SAMPLES, check_range
from falsify.errors import FalsifyError
from falsify.results.metrics import Status
from falsify.world.space import Space, load_space

SEARCH_ALGORITHMS = ("random", "sobol", "cross-entropy", "bo", "GN_DIRECT_L", "GN_CRS2_LM")
SEEDS = 3             # runs per algorithm: the config's seed and the ones after it
MAX_SEEDS = 100
REGION_DEPTH = 2      # `falsify explain`'s default rule depth
REGION_RULES = 20     # `falsify explain --rules 20`, its most: its default 5 would cap counts
PER_EVALUATION_GOAL = 1.2   # an NLopt run's seconds per evaluation against random's, at most
NOT_TIMED = ("wall_s and s_per_evaluation are the run's own time (worker start-up and the "
             "search, as its elapsed_s), for runs computed in this invocation only: a run "
             "resumed from an earlier one is null (its time would mix invocations)")
FIRST_SEED = ("lowest, evaluations_to_target, the timing and the curves are the first seed's "
              "run; over_seeds holds every seed's counterexamples (distinct samples below the "
              "threshold), lowest IoU and regions (the rules `falsify explain --rules "
              f"{REGION_RULES}` finds on the run's rows), with mean, min and max")


def bench_search(config: str | Path, out: str | Path, algorithms=SEARCH_ALGORITHMS,
                 fraction: float = 0.2, workers: int = 2, model: str | None = None,
                 tolerance: float = 0.02, seeds: int = SEEDS) -> dict:
    """Lowest IoU against evaluations for each search algorithm, against a dense grid, and the
    seconds per evaluation of each on `workers` workers (NLopt runs that many discrete
    combinations at once), against random's; then, over `seeds` runs of each (the config's seed
    and the ones after it), counterexamples, lowest IoU and failing regions.

    Every run is an ordinary run directory under `out` (resumable: the first seed's in
    out/ALGORITHM, the others' in out/ALGORITHM-seedS), so an interrupted benchmark continues
    where it stopped; only runs started in this invocation are timed. `bo` is skipped, and said
    so, where Optuna is not installed."""
    from falsify.jobs.run import RunRequest, RunSummary, execute
    from falsify.results.store import read_frame

    check_range(seeds, "--seeds", 1, MAX_SEEDS)
    out = Path(out)
    space = load_space(config)
    space.check_size(MAX_SAMPLES, "the benchmark's limit")
    n_grid = len(space.grid())
    budget = max(1, int(n_grid * fraction))
    seed_list = [space.seed + k for k in range(seeds)]
    algorithms, skipped = available(algorithms)
    _check_budget(space, algorithms, budget, fraction)

    def run(name: str, algorithm: str, b: int | None, command: str,
            seed: int | None = None) -> tuple[RunSummary, bool]:
        """The run's summary, and whether it was computed from scratch in this invocation."""
        d = out / name
        resume = (d / "results.sqlite").exists()
        req = RunRequest(config=Path(config), out=d, command=command, algorithm=algorithm,
                         budget=b, seed=seed, model=model, workers=workers, report=False,
                         resume=resume)
        return execute(req), not resume

    dense, _ = run("grid", "grid", None, "grid")
    g = read_frame(dense.run)
    grid_min = float(g.loc[g["status"] == Status.OK, "car_iou"].min())
    target = grid_min + tolerance
    rows, curves = [], {}
    for algo in algorithms:
        done, fresh = run(algo, algo, budget, "search", seed_list[0])
        per_seed = [found(done.run)]
        for seed in seed_list[1:]:
            other, _ = run(f"{algo}-seed{seed}", algo, budget, "search", seed)
            per_seed.append(found(other.run))
        assert done.search is not None
        curves[algo] = done.search.lowest
        rows.append(_algorithm_row(algo, done, fresh, per_seed, budget, n_grid, target))
    _compare_with_random(rows)
    _write_curves(curves, out / "search_curves.csv")
    return {"benchmark": "search", "config": str(config), "grid_samples": n_grid,
            "grid_lowest": round(grid_min, 4), "target": round(target, 4),
            "budget": budget, "fraction": fraction, "workers": workers, "algorithms": rows,
            "seeds": seed_list, "threshold": space.threshold, "skipped": skipped,
            "per_evaluation_goal": f"NLopt at most {PER_EVALUATION_GOAL}x random's seconds "
                                   "per evaluation",
            "timing": NOT_TIMED, "first_seed": FIRST_SEED,
            "curves_csv": str(out / "search_curves.csv"), "machine": machine()}


def _check_budget(space: Space, algorithms: Sequence[str], budget: int, fraction: float) -> None:
    """FalsifyError before any run where the budget cannot hold an NLopt algorithm's discrete
    combinations (found only after the grid and the algorithms before it had run)."""
    from falsify.sampler import NLOPT_ALGORITHMS
    from falsify.sampler.nlopt import combo_count

    nlopt = [a for a in algorithms if a in NLOPT_ALGORITHMS]
    needed = combo_count(space) if nlopt else 0
    if budget < needed:
        raise FalsifyError(f"--fraction {fraction:g}: a budget of {budget:,} evaluation"
                           f"{'s' * (budget != 1)} is smaller than the {needed:,} "
                           f"combinations of discrete dims that {nlopt[0]} needs; allowed: "
                           f"--fraction of at least {needed / len(space.grid()):.3g} for "
                           "this config")


def _algorithm_row(algo: str, done, fresh: bool, per_seed: list[dict], budget: int,
                   n_grid: int, target: float) -> dict:
    """An algorithm's row from its first seed's run `done`: evaluations to reach `target`, its
    lowest score, its seconds per evaluation (only where `fresh`: run in this invocation) and
    what it found over the seeds."""
    from falsify.results.store import read_frame

    low = done.search.lowest
    hit = next((i + 1 for i, v in enumerate(low) if v is not None and v <= target), None)
    frame = read_frame(done.run)
    wall = float(done.elapsed_s) if fresh and done.elapsed_s is not None else None
    evals = done.search.evaluations
    return {"algorithm": algo, "budget": budget, "evaluations": evals,
            "distinct_samples": int(len(frame)),
            "lowest": None if low[-1] is None else round(low[-1], 4),
            "evaluations_to_target": hit,
            "fraction_of_grid_to_target": None if hit is None else round(hit / n_grid, 4),
            "reached": hit is not None, "timed": fresh,
            "wall_s": None if wall is None else round(wall, 3),
            "s_per_evaluation": None if wall is None or not evals else
            round(wall / evals, 5),
            "over_seeds": over_seeds(per_seed)}


def _compare_with_random(rows: list[dict]) -> None:
    """Add each row's seconds per evaluation over random's, and for NLopt whether that meets
    PER_EVALUATION_GOAL."""
    from falsify.sampler import NLOPT_ALGORITHMS

    base = next((r["s_per_evaluation"] for r in rows if r["algorithm"] == "random"), None)
    for r in rows:
        ratio = (None if base is None or r["s_per_evaluation"] is None
                 else round(r["s_per_evaluation"] / base, 3))
        r["s_per_evaluation_vs_random"] = ratio
        if r["algorithm"] in NLOPT_ALGORITHMS:
            r["within_goal"] = None if ratio is None else ratio <= PER_EVALUATION_GOAL


def _write_curves(curves: dict[str, list], path: Path) -> None:
    """Each algorithm's lowest score against evaluations as one CSV column, a shorter curve
    held at its last value."""
    import pandas as pd

    from falsify.fileio import write_bytes

    longest = max((len(c) for c in curves.values()), default=0)
    table = pd.DataFrame({a: c + [c[-1]] * (longest - len(c)) for a, c in curves.items()})
    table.insert(0, "evaluation", range(1, longest + 1))
    write_bytes(path, table.to_csv(index=False).encode())


def available(algorithms) -> tuple[list[str], dict[str, str]]:
    """The algorithms that can run here, and why each other one cannot (bo without Optuna)."""
    from falsify.errors import FalsifyError
    from falsify.sampler.bayes import import_optuna

    runnable, skipped = [], {}
    for algo in algorithms:
        if algo == "bo":
            try:
                import_optuna()
            except FalsifyError as exc:
                skipped[algo] = str(exc)
                continue
        runnable.append(algo)
    return runnable, skipped


def found(run: str | Path) -> dict:
    """What one search run found: distinct samples below its threshold, its lowest score, and
    its failing regions as the rules `falsify explain --rules REGION_RULES` finds."""
    from falsify.results.explain import find_rules
    from falsify.results.store import open_run

    data = open_run(run)
    ok = data.ok.reset_index(drop=True)
    col, thr = data.score_column, data.threshold
    scores = ok[col].astype(float)
    rules = find_rules(ok, data.space, thr, REGION_DEPTH, REGION_RULES, col) if len(ok) else ()
    return {"seed": data.meta.get("seed"), "counterexamples": int((scores < thr).sum()),
            "lowest": None if not len(ok) else round(float(scores.min()), 4),
            "regions": len(rules), "rules": [r.text() for r in rules]}


def spread(values: list) -> dict:
    """Mean, min and max of the defined values (all None when none is)."""
    v = [float(x) for x in values if x is not None]
    if not v:
        return {"mean": None, "min": None, "max": None}
    return {"mean": round(sum(v) / len(v), 4), "min": min(v), "max": max(v)}


def over_seeds(per_seed: list[dict]) -> dict:
    """Counterexamples, lowest score and regions over an algorithm's seeds, and each seed's."""
    return {"seeds": [p["seed"] for p in per_seed],
            **{key: spread([p[key] for p in per_seed])
               for key in ("counterexamples", "lowest", "regions")},
            "per_seed": per_seed}


def over_seeds_text(result: dict) -> str:
    """One line per algorithm: what it found over the seeds, mean (min-max)."""
    def fmt(d: dict, digits: int, ends: int) -> str:
        if d["mean"] is None:
            return "none"
        return f"{d['mean']:.{digits}f} ({d['min']:.{ends}f}-{d['max']:.{ends}f})"

    seeds = ", ".join(str(s) for s in result["seeds"])
    lines = [f"over seeds {seeds}, {result['budget']} evaluations each, threshold "
             f"{result['threshold']:g}: mean (min-max)"]
    for r in result["algorithms"]:
        o = r["over_seeds"]
        lines.append(f"{r['algorithm']:13s} counterexamples {fmt(o['counterexamples'], 1, 0)}, "
                     f"lowest IoU {fmt(o['lowest'], 3, 3)}, regions {fmt(o['regions'], 1, 0)}")
    lines += [f"{a}: skipped ({why})" for a, why in result["skipped"].items()]
    return "\n".join(lines)
