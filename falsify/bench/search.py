"""`falsify bench search`: each search algorithm's lowest IoU and cost per evaluation on one
space, in one run.
"""

from __future__ import annotations

from pathlib import Path

from falsify.bench.machine import machine
from falsify.checks import MAX_SAMPLES
from falsify.results.metrics import Status
from falsify.world.space import load_space

SEARCH_ALGORITHMS = ("random", "sobol", "GN_DIRECT_L", "GN_CRS2_LM")
PER_EVALUATION_GOAL = 1.2   # an NLopt run's seconds per evaluation against random's, at most
NOT_TIMED = ("wall_s and s_per_evaluation are the run's own time (worker start-up and the "
             "search, as its elapsed_s), for runs computed in this invocation only: a run "
             "resumed from an earlier one is null (its time would mix invocations)")


def bench_search(config: str | Path, out: str | Path, algorithms=SEARCH_ALGORITHMS,
                 fraction: float = 0.2, workers: int = 2, model: str | None = None,
                 tolerance: float = 0.02) -> dict:
    """Lowest IoU against evaluations for each search algorithm, against a dense grid, and the
    seconds per evaluation of each on `workers` workers (NLopt runs that many discrete
    combinations at once), against random's.

    Every run is an ordinary run directory under `out` (resumable), so an interrupted benchmark
    continues where it stopped; only runs started in this invocation are timed."""
    import pandas as pd

    from falsify.fileio import write_bytes
    from falsify.jobs.run import RunRequest, RunSummary, execute
    from falsify.results.store import read_frame

    out = Path(out)
    space = load_space(config)
    space.check_size(MAX_SAMPLES, "the benchmark's limit")
    n_grid = len(space.grid())
    budget = max(1, int(n_grid * fraction))

    def run(name: str, algorithm: str, b: int | None, command: str) -> tuple[RunSummary, bool]:
        """The run's summary, and whether it was computed from scratch in this invocation."""
        d = out / name
        resume = (d / "results.sqlite").exists()
        req = RunRequest(config=Path(config), out=d, command=command, algorithm=algorithm,
                         budget=b, model=model, workers=workers, report=False, resume=resume)
        return execute(req), not resume

    dense, _ = run("grid", "grid", None, "grid")
    g = read_frame(dense.run)
    grid_min = float(g.loc[g["status"] == Status.OK, "car_iou"].min())
    target = grid_min + tolerance
    rows, curves = [], {}
    for algo in algorithms:
        done, fresh = run(algo, algo, budget, "search")
        assert done.search is not None
        low = done.search.lowest
        curves[algo] = low
        hit = next((i + 1 for i, v in enumerate(low) if v is not None and v <= target), None)
        frame = read_frame(done.run)
        wall = float(done.elapsed_s) if fresh and done.elapsed_s is not None else None
        evals = done.search.evaluations
        rows.append({"algorithm": algo, "budget": budget, "evaluations": evals,
                     "distinct_samples": int(len(frame)),
                     "lowest": None if low[-1] is None else round(low[-1], 4),
                     "evaluations_to_target": hit,
                     "fraction_of_grid_to_target": None if hit is None else round(hit / n_grid, 4),
                     "reached": hit is not None, "timed": fresh,
                     "wall_s": None if wall is None else round(wall, 3),
                     "s_per_evaluation": None if wall is None or not evals else
                     round(wall / evals, 5)})
    base = next((r["s_per_evaluation"] for r in rows if r["algorithm"] == "random"), None)
    for r in rows:
        ratio = (None if base is None or r["s_per_evaluation"] is None
                 else round(r["s_per_evaluation"] / base, 3))
        r["s_per_evaluation_vs_random"] = ratio
        if r["algorithm"] not in ("grid", "random", "sobol"):
            r["within_goal"] = None if ratio is None else ratio <= PER_EVALUATION_GOAL
    longest = max(len(c) for c in curves.values())
    table = pd.DataFrame({a: c + [c[-1]] * (longest - len(c)) for a, c in curves.items()})
    table.insert(0, "evaluation", range(1, longest + 1))
    write_bytes(out / "search_curves.csv", table.to_csv(index=False).encode())
    return {"benchmark": "search", "config": str(config), "grid_samples": n_grid,
            "grid_lowest": round(grid_min, 4), "target": round(target, 4),
            "budget": budget, "fraction": fraction, "workers": workers, "algorithms": rows,
            "per_evaluation_goal": f"NLopt at most {PER_EVALUATION_GOAL}x random's seconds "
                                   "per evaluation",
            "timing": NOT_TIMED,
            "curves_csv": str(out / "search_curves.csv"), "machine": machine()}
