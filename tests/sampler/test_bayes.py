"""The Bayesian-optimisation sampler (`bo`, Optuna's TPE): it keeps to the space, its categorical
values and its count, replays the same samples for the same seed and scores (in another process
too), steers away from samples without a score, finds a lower minimum than random at equal
budget, and says how to install Optuna where it is missing."""

from __future__ import annotations

import importlib.util
import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from falsify.errors import ConfigError, FalsifyError
from falsify.sampler import ALGORITHMS, make_sampler
from falsify.world.space import Categorical, Continuous, Space, parse_space
from tests.conftest import scored

needs_optuna = pytest.mark.skipif(importlib.util.find_spec("optuna") is None,
                                  reason='Optuna not installed (pip install "falsify[bo]")')

ROOT = Path(__file__).resolve().parents[2]
CARS = ("sedan", "suv")
DIMS = {"car_model": {"values": ["sedan", "suv"]}, "x": {"min": -5, "max": 4, "step": 1},
        "y": {"min": 5, "max": 19, "step": 1}, "yaw": {"min": -180, "max": 90, "step": 90},
        "background": {"values": [0, 1, 2, 3, 4, 5]}}


def space(**extra: dict) -> Space:
    return parse_space({"seed": 0, "threshold": 0.65, "dims": {**DIMS, **extra}},
                       builtin_cars=CARS)


def pit(s) -> float:
    """A narrow pit at (1.7, 14.3) on street 4 with the SUV: a sampler that learns finds it."""
    d2 = (s["x"] - 1.7) ** 2 + (s["y"] - 14.3) ** 2
    return (0.95 - 0.4 * math.exp(-d2 / 2) - (0.1 if s["background"] == 4 else 0.0)
            - (0.03 if s["car_model"] == "suv" else 0.0))



@needs_optuna
def test_registered_and_keeps_budget_bounds_and_values():
    assert "bo" in ALGORITHMS
    sp = space(weather={"values": ["sun", "rain", "fog"]})
    ev, calls = scored(pit)
    res = make_sampler("bo").run(sp, ev, 50, seed=1)
    assert res.evaluations == 50 and sum(calls) == 50 and max(calls) <= 8
    for name, dim in sp.dims.items():
        got = [s[name] for s in res.samples]
        if isinstance(dim, Categorical):
            assert set(got) <= set(dim.values), name
            assert set(got) == set(dim.values) or len(dim.values) == 1, name
        else:
            assert isinstance(dim, Continuous)
            assert all(isinstance(v, float) and dim.lo <= v <= dim.hi for v in got), name
            span = dim.hi - dim.lo
            assert min(got) < dim.lo + span / 4 and max(got) > dim.hi - span / 4, name
    assert res.best == min(v for v in res.curve if v is not None)


@needs_optuna
def test_same_seed_same_samples_other_seed_others():
    sp = space()
    a = make_sampler("bo").run(sp, scored(pit)[0], 40, seed=7)
    b = make_sampler("bo").run(sp, scored(pit)[0], 40, seed=7)
    assert a.samples == b.samples and a.curve == b.curve
    assert make_sampler("bo").run(sp, scored(pit)[0], 40, seed=8).samples != a.samples


DETERMINISM = """
import json, math, sys
from falsify.sampler import make_sampler
from falsify.world.space import parse_space
sys.path.insert(0, {tests!r})
from tests.sampler.test_bayes import DIMS, pit
sp = parse_space({{"seed": 0, "threshold": 0.65, "dims": DIMS}}, builtin_cars=("sedan", "suv"))
res = make_sampler("bo").run(sp, lambda b: [pit(s) for s in b], 30, 7)
print(json.dumps([list(s.values) for s in res.samples]))
"""


@needs_optuna
def test_another_process_replays_the_same_samples():
    """A resumed run replays the sampler in a new process (another string hash seed)."""
    sp = space()
    here = make_sampler("bo").run(sp, scored(pit)[0], 30, seed=7)
    env = {**os.environ, "PYTHONHASHSEED": "12345"}
    out = subprocess.run([sys.executable, "-c", DETERMINISM.format(tests=str(ROOT / "tests"))],
                         capture_output=True, text=True, env=env, cwd=ROOT, check=True).stdout
    assert json.loads(out) == [[list(kv) for kv in s.values] for s in here.samples]


@needs_optuna
def test_count_gates_the_second_cars_dims():
    sp = space(count={"values": [1, 2]}, x_2={"min": -5, "max": 4, "step": 1})
    res = make_sampler("bo").run(sp, scored(pit)[0], 40, seed=3)
    ones = [s for s in res.samples if s.count == 1]
    twos = [s for s in res.samples if s.count == 2]
    assert ones and twos
    pinned = {name: sp.dims[name].grid()[0] for name in sp.dims if not sp.active(name, 1)}
    assert "x_2" in pinned and "car_model_2" in pinned
    for s in ones:   # car 2 is not in the scene: its dims keep their first value
        assert {n: s[n] for n in pinned} == pinned
    assert len({s["x_2"] for s in twos}) > 1


@needs_optuna
def test_samples_without_a_score_are_told_as_the_penalty():
    """None (invalid) and nan (undefined) for x < -2, a third of the space, and a flat score
    elsewhere: the run finishes, and the penalty alone steers it out of that third."""
    sp = space()

    def flat(s):
        if s["x"] < -2:
            return None if s["y"] < 12 else float("nan")
        return 0.8
    res = make_sampler("bo").run(sp, scored(flat)[0], 80, seed=0)
    assert res.evaluations == 80 and res.best == 0.8
    assert any(v is None for v in res.curve) and any(v is not None and math.isnan(v)
                                                    for v in res.curve)
    late = sum(s["x"] < -2 for s in res.samples[-32:]) / 32
    assert late <= 0.15, late
    nothing = make_sampler("bo").run(sp, scored(lambda s: None)[0], 20, seed=0)
    assert nothing.evaluations == 20 and nothing.best is None


@needs_optuna
def test_finds_a_lower_minimum_than_random_at_equal_budget():
    sp = space()
    bo, rnd = [], []
    for seed in range(4):
        bo.append(make_sampler("bo").run(sp, scored(pit)[0], 60, seed=seed).best)
        rnd.append(make_sampler("random").run(sp, scored(pit)[0], 60, seed=seed).best)
    assert all(b < r for b, r in zip(bo, rnd, strict=True)), (bo, rnd)
    assert np.mean(bo) < np.mean(rnd) - 0.05, (bo, rnd)


@needs_optuna
@pytest.mark.parametrize("options", [{"batch_size": 0}, {"startup": 0},
                                     {"penalty": float("nan")}])
def test_bad_options_are_named(options):
    with pytest.raises(ConfigError, match=next(iter(options))):
        make_sampler("bo", **options)


def test_without_optuna_it_says_how_to_install(tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "optuna", None)   # `import optuna` raises ImportError
    with pytest.raises(FalsifyError, match=r'pip install "falsify\[bo\]"'):
        make_sampler("bo")
    from falsify.cli import main
    monkeypatch.chdir(ROOT)
    out = tmp_path / "bo"
    code = main(["search", "configs/smoke.toml", "--algorithm", "bo", "--budget", "4",
                 "--out", str(out), "--quiet"])
    assert code == 2 and 'pip install "falsify[bo]"' in capsys.readouterr().err
    assert not out.exists()
    from falsify.bench.search import available
    runnable, skipped = available(("random", "bo"))   # the bench runs the others
    assert runnable == ["random"] and 'pip install "falsify[bo]"' in skipped["bo"]


def test_scoring_and_gating_do_not_import_optuna():
    code = ("import sys, falsify.executors.evaluator, falsify.jobs.gate, falsify.jobs.run, "
            "falsify.sampler, falsify.cli; print('optuna' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         cwd=ROOT, check=True).stdout
    assert out.strip() == "False"


@needs_optuna
def test_search_command_runs_it_and_resumes(tmp_path, capsys, monkeypatch):
    """Through the CLI on the smoke config: a resume replays the samples from the store, and the
    bench's count of what a run found agrees with the run's summary."""
    from falsify.bench.search import found
    from falsify.cli import main
    monkeypatch.chdir(ROOT)
    out = tmp_path / "bo"
    argv = ["search", "configs/smoke.toml", "--algorithm", "bo", "--budget", "12",
            "--out", str(out), "--quiet", "--json"]
    assert main(argv) == 0
    first = json.loads(capsys.readouterr().out)
    assert main([*argv, "--resume"]) == 0
    again = json.loads(capsys.readouterr().out)
    assert again["samples"] == first["samples"] == 12 and again["computed_this_time"] == 0
    got = found(out)
    assert got["lowest"] == first["lowest"]["car_iou"] and got["seed"] == 0
    assert 0 <= got["counterexamples"] <= 12 and got["regions"] == len(got["rules"])


@needs_optuna
def test_bench_search_reports_what_each_seed_found(tmp_path):
    """`bench search` over 2 seeds: each seed's run in its own directory, and the mean, min and
    max of counterexamples, lowest IoU and regions over them."""
    from falsify.bench.search import bench_search, over_seeds_text
    from falsify.results.store import read_meta

    out = tmp_path / "b"
    r = bench_search(ROOT / "configs" / "smoke.toml", out, algorithms=("bo",), fraction=1.0,
                     workers=1, seeds=2)
    assert r["seeds"] == [0, 1] and r["threshold"] == 0.65 and r["skipped"] == {}
    assert read_meta(out / "bo")["seed"] == 0 and read_meta(out / "bo-seed1")["seed"] == 1
    o = r["algorithms"][0]["over_seeds"]
    assert o["seeds"] == [0, 1] and [p["seed"] for p in o["per_seed"]] == [0, 1]
    for key in ("counterexamples", "lowest", "regions"):
        values = [p[key] for p in o["per_seed"]]
        assert o[key]["min"] == min(values) and o[key]["max"] == max(values)
        assert o[key]["mean"] == pytest.approx(sum(values) / 2, abs=1e-4)
    assert o["per_seed"][0]["lowest"] == r["algorithms"][0]["lowest"]
    assert all(p["regions"] == len(p["rules"]) for p in o["per_seed"])
    assert "bo            counterexamples" in over_seeds_text(r)
    with pytest.raises(FalsifyError, match="--seeds"):
        bench_search(ROOT / "configs" / "smoke.toml", out, seeds=0)
