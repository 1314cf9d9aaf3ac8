"""Samplers: coverage, determinism, bounds, budgets, and NLopt on a planted minimum."""

from __future__ import annotations

import itertools
import os
import random
import signal
import sys
import threading
import time
import types
from unittest import mock

import pytest

from falsify.errors import ConfigError
from falsify.sampler import ALGORITHMS, NLOPT_ALGORITHMS, lowest_so_far, make_sampler
from falsify.sampler.base import Recorder as BaseRecorder
from falsify.sampler.nlopt import NloptSampler, discrete_combos
from falsify.world.space import Categorical, Continuous, Sample, Space, parse_space
from tests.conftest import Scorer

CARS = ("sedan", "suv")


def space_of(dims: dict) -> Space:
    """parse_space with the test's car list; stubs falsify.world.streets only while it is
    missing."""
    raw = {"seed": 0, "dims": dims}
    try:
        import falsify.world.streets  # noqa: F401
    except ImportError:
        stub = types.SimpleNamespace(MAX_BACKGROUND_ID=999_999)
        with mock.patch.dict(sys.modules, {"falsify.world.streets": stub}):
            return parse_space(raw, builtin_cars=CARS)
    return parse_space(raw, builtin_cars=CARS)


def paper_space(**extra: dict) -> Space:
    dims = {"car_model": {"values": ["sedan"]}, "x": {"min": -5, "max": 4, "step": 1},
            "y": {"min": 5, "max": 19, "step": 1}, "yaw": {"values": [0.0]},
            "background": {"values": [0]}}
    return space_of({**dims, **extra})


def small_space() -> Space:
    return space_of({"car_model": {"values": ["sedan", "suv"]},
                     "x": {"min": -1, "max": 1, "step": 1}, "y": {"min": 5, "max": 7, "step": 2},
                     "yaw": {"min": 0, "max": 90, "step": 90}, "count": {"values": [1, 2]},
                     "background": {"values": [3, 4]}, "weather": {"values": ["sun", "rain"]}})


def in_bounds(space: Space, sample: Sample) -> bool:
    return all(d.contains(sample[name]) if isinstance(d, Categorical)
               else d.lo <= sample[name] <= d.hi for name, d in space.dims.items())


def run(name: str, space: Space, budget: int | None, seed: int = 0, fn=lambda s: 0.5,
        **options) -> Scorer:
    rec = Scorer(fn)
    make_sampler(name, **options).run(space, rec, budget, seed)
    return rec


# ---- registry and helpers -------------------------------------------------------------------

def test_registry_names_and_unknown_name():
    assert ALGORITHMS[:3] == ("grid", "random", "sobol")
    for name in ("GN_DIRECT_L", "GN_CRS2_LM", "GN_ISRES", "G_MLSL_LDS", "LN_BOBYQA",
                 "LN_COBYLA", "LN_NELDERMEAD", "LN_SBPLX"):
        assert name in NLOPT_ALGORITHMS
    with pytest.raises(ConfigError,
                       match="allowed: grid, random, sobol, cross-entropy, level-set, GN_DIRECT_L"):
        make_sampler("annealing")
    with pytest.raises(ConfigError, match="unknown option 'bogus'; allowed: batch_size"):
        make_sampler("grid", bogus=1)
    with pytest.raises(ConfigError, match="local 'LN_SBPLX'"):
        run("G_MLSL_LDS", paper_space(), 10, local="LN_SBPLX")
    for name in ALGORITHMS:
        assert make_sampler(name).name == name


def test_lowest_so_far_skips_none_and_nan():
    got = lowest_so_far([None, 0.7, None, 0.9, float("nan"), 0.3, 0.4])
    assert got == [None, 0.7, 0.7, 0.7, 0.7, 0.3, 0.3]
    assert lowest_so_far([]) == []


def test_run_returns_every_score_and_the_lowest():
    space = small_space()
    scores = iter([0.9, None, 0.4, float("nan"), 0.6])

    def evaluate(batch):
        return [next(scores) for _ in batch]

    res = make_sampler("random", batch_size=2).run(space, evaluate, 5, 0)
    assert res.evaluations == 5 and res.best == 0.4
    assert res.curve[:3] == (0.9, None, 0.4) and res.lowest[-1] == 0.4
    assert res.best_sample is not None


# ---- grid -----------------------------------------------------------------------------------

def test_grid_is_the_factorial_set_in_order_and_batched():
    space = small_space()
    rec = run("grid", space, None)
    assert rec.samples == space.grid()
    assert len(set(rec.samples)) == len(rec.samples)
    assert max(rec.batches) <= 64 and sum(rec.batches) == len(rec.samples)
    names = list(space.dims)
    expected = set()
    for count in (1, 2):
        axes = [(count,) if n == "count"
                else (d.grid() if space.active(n, count) else d.grid()[:1])
                for n, d in space.dims.items()]
        expected |= {Sample(tuple(zip(names, c, strict=True))) for c in itertools.product(*axes)}
    assert set(rec.samples) == expected
    one = [s for s in rec.samples if s.count == 1]
    two = [s for s in rec.samples if s.count == 2]
    assert len(one) == 2 * 3 * 2 * 2 * 2 * 2  # car 2's dims are not enumerated for count 1
    assert len(two) == len(one) * 2 * 3 * 2 * 2
    assert {s["x_2"] for s in one} == {-1.0} and {s["x_2"] for s in two} == {-1.0, 0.0, 1.0}


def test_grid_budget_takes_the_first_samples():
    space = small_space()
    assert run("grid", space, 10).samples == space.grid()[:10]
    assert run("grid", space, 0).samples == []
    with pytest.raises(ConfigError, match="budget must be an integer >= 0"):
        run("grid", space, -1)


# ---- random and sobol -----------------------------------------------------------------------

@pytest.mark.parametrize("name", ["random", "sobol"])
def test_random_and_sobol_are_seeded_valid_and_respect_budget(name):
    space = small_space()
    a = run(name, space, 100, seed=7)
    b = run(name, space, 100, seed=7, batch_size=7)
    c = run(name, space, 100, seed=8)
    assert a.samples == b.samples  # independent of the batch size
    assert a.samples != c.samples
    assert len(a.samples) == 100 and max(a.batches) <= 64
    assert all(in_bounds(space, s) for s in a.samples)
    for s in a.samples:  # dims of cars beyond the count are pinned
        if s.count == 1:
            assert s["x_2"] == -1.0 and s["car_model_2"] == "sedan"
    for dim in space.discrete():  # every categorical value shows up in 100 draws
        assert {s[dim.name] for s in a.samples} == set(dim.values)
    xs = [s["x"] for s in a.samples]
    assert min(xs) < -0.8 and max(xs) > 0.8
    with pytest.raises(ConfigError, match="needs a budget"):
        run(name, space, None)


def test_sobol_is_more_even_than_random():
    space = paper_space()
    sob = run("sobol", space, 64, seed=1).samples
    cells = {(int((s["x"] + 5) // 2.25), int((s["y"] - 5) // 3.5)) for s in sob}
    assert len(cells) == 16  # a scrambled Sobol (0, 6, 2)-net fills every 4x4 cell


def test_sobol_with_nothing_free_evaluates_the_single_sample_once():
    space = space_of({"car_model": {"values": ["sedan"]}, "x": {"values": [1.0]},
                      "y": {"values": [8.0]}, "background": {"values": [0]}})
    assert run("sobol", space, 10).samples == [space.make({})]


# ---- nlopt ----------------------------------------------------------------------------------

def planted(s: Sample) -> float:
    return 0.2 + 0.8 * min(1.0, ((s["x"] - 1.3) ** 2 + (s["y"] - 11.7) ** 2) / 40)


@pytest.mark.parametrize("name", ["GN_DIRECT_L", "GN_CRS2_LM", "LN_BOBYQA", "LN_COBYLA",
                                  "LN_NELDERMEAD", "LN_SBPLX", "GN_ISRES", "G_MLSL_LDS"])
def test_nlopt_finds_planted_minimum_within_budget_and_bounds(name):
    space = paper_space()
    rec = run(name, space, 150, seed=3, fn=planted)
    assert 0 < len(rec.samples) <= 150
    assert min(rec.scores) <= 0.2 + 0.02
    assert all(in_bounds(space, s) and s["yaw"] == 0.0 for s in rec.samples)
    assert run(name, space, 150, seed=3, fn=planted).samples == rec.samples


@pytest.mark.parametrize("name", ["GN_CRS2_LM", "GN_ISRES", "LN_NELDERMEAD"])
def test_nlopt_seed_changes_stochastic_runs(name):
    space = paper_space()
    far = lambda s: 0.2 + 0.8 * min(1.0, ((s["x"] - 3.2) ** 2 + (s["y"] - 6.4) ** 2) / 4)  # noqa: E731
    a = run(name, space, 80, seed=1, fn=far).samples
    assert a == run(name, space, 80, seed=1, fn=far).samples
    assert a != run(name, space, 80, seed=2, fn=far).samples


def test_nlopt_local_restarts_use_the_whole_budget_and_stay_in_bounds():
    space = paper_space()
    corner = lambda s: (s["x"] - 4) ** 2 + (s["y"] - 5) ** 2  # noqa: E731 (minimum on a corner)
    for name in ("LN_BOBYQA", "LN_COBYLA", "LN_NELDERMEAD", "LN_SBPLX"):
        res = NloptSampler(name).optimise(space, Scorer(corner), 120, seed=0)
        assert res[0].evaluations == 120 and res[0].runs > 1
        assert res[0].best_score < 1e-3
        assert in_bounds(space, res[0].best_sample)


def test_nlopt_none_scores_become_a_penalty():
    space = paper_space()

    def fn(s):  # the left half of the box is invalid; the minimum is on the right
        return None if s["x"] < 0 else planted(s)

    rec = run("LN_NELDERMEAD", space, 100, fn=fn)
    assert None in rec.scores and len(rec.samples) <= 100
    assert min(v for v in rec.scores if v is not None) <= 0.22
    res = NloptSampler("GN_DIRECT_L").optimise(space, Scorer(lambda s: None), 30, seed=0)
    assert res[0].evaluations == 30 and res[0].best_score is None


def test_nlopt_stops_exactly_at_the_budget():
    space = paper_space()
    for name in NLOPT_ALGORITHMS:
        for budget in (1, 2, 7, 33):
            assert len(run(name, space, budget, fn=planted).samples) == budget, (name, budget)
    with pytest.raises(ConfigError, match="needs a budget"):
        run("LN_BOBYQA", space, None)


def test_nlopt_zero_width_dims_are_fixed():
    space = paper_space(x={"min": 2.5, "max": 2.5, "step": 1})
    assert isinstance(space.dims["x"], Continuous) and space.dims["x"].lo == space.dims["x"].hi
    rec = run("LN_BOBYQA", space, 40, fn=planted)
    assert {s["x"] for s in rec.samples} == {2.5}
    assert min(rec.scores) == pytest.approx(planted(space.make({"x": 2.5, "y": 11.7})), abs=1e-3)
    fixed = space_of({"car_model": {"values": ["sedan", "suv"]}, "x": {"values": [1.0]},
                      "y": {"min": 8, "max": 8, "step": 1}, "background": {"values": [0, 1, 2]}})
    rec = run("GN_DIRECT_L", fixed, 50, fn=planted)
    assert rec.batches == [6] and len(set(rec.samples)) == 6


def test_nlopt_outer_loop_covers_every_combination_and_splits_the_budget():
    space = small_space()
    combos = discrete_combos(space)
    # count 1: car_model x background x weather; count 2 adds car_model_2.
    assert len(combos) == 2 * 2 * 2 + 2 * 2 * 2 * 2
    assert all(c["count"] == 1 and "car_model_2" not in c for c in combos[:8])
    rec = Scorer(planted)
    res = NloptSampler("LN_COBYLA").optimise(space, rec, 24 * 5 + 3, seed=0)
    assert [dict(r.combo) for r in res] == combos
    assert [r.evaluations for r in res] == [6, 6, 6] + [5] * 21
    assert len(rec.samples) == 123
    keys = [d.name for d in space.discrete()]
    seen = {tuple(s[k] for k in keys) for s in rec.samples}
    assert seen == {tuple(space.make(c)[k] for k in keys) for c in combos}
    for r in res:
        assert all(r.best_sample[k] == v for k, v in r.combo)
    with pytest.raises(ConfigError, match="smaller than the 24 combinations"):
        run("LN_COBYLA", space, 23)


def test_direct_finds_a_narrow_off_centre_minimum():
    space = paper_space()
    far = lambda s: 0.2 + 0.8 * min(1.0, ((s["x"] - 3.2) ** 2 + (s["y"] - 6.4) ** 2) / 4)  # noqa: E731
    rec = run("GN_DIRECT_L", space, 60, fn=far)  # needs 36 evaluations to reach 0.22
    assert min(rec.scores) <= 0.22


# ---- combinations run concurrently ----------------------------------------------------------

class Jittery:
    """A thread-safe evaluate: scores with `fn` after a random pause (so the threads' calls
    interleave differently every time) and notes how many calls overlapped at most."""

    def __init__(self, fn=planted, pause: float = 0.002):
        self.fn, self.pause = fn, pause
        self.lock = threading.Lock()
        self.running = self.overlap = self.calls = 0

    def __call__(self, batch):
        with self.lock:
            self.running += 1
            self.calls += 1
            self.overlap = max(self.overlap, self.running)
        try:
            time.sleep(random.random() * self.pause)
            return [self.fn(s) for s in batch]
        finally:
            with self.lock:
                self.running -= 1


def test_recorder_orders_parts_by_key_whatever_the_timing():
    space = paper_space()
    pts = [space.make({"x": float(i % 9) - 4, "y": 6.0 + i}) for i in range(12)]
    rec = BaseRecorder(Jittery(lambda s: s["y"], pause=0.01))
    rec(pts[:2])                                    # part 0
    threads = [threading.Thread(target=lambda k=k: [rec.part(k)([p]) for p in
                                                    pts[2 + 5 * (2 - k):7 + 5 * (2 - k)]])
               for k in (2, 1)]                      # part 2 gets pts[2:7], part 1 pts[7:12]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert rec.samples == pts[:2] + pts[7:12] + pts[2:7]
    res = rec.result()
    assert res.curve == tuple(s["y"] for s in res.samples) and res.best == 6.0


@pytest.mark.parametrize("name", ["GN_CRS2_LM", "LN_BOBYQA"])
def test_concurrent_combinations_give_the_sequential_result(name):
    """W threads give the samples, curve, best and per-combination results of the sequential
    loop (GN_CRS2_LM draws from NLopt's generator, which is per thread; LN_BOBYQA does not)."""
    space = small_space()        # 24 combinations
    budget = 24 * 5 + 3
    seq_rec = Scorer(planted)
    seq = NloptSampler(name).optimise(space, seq_rec, budget, seed=5)
    want = make_sampler(name).run(space, Scorer(planted), budget, 5)
    assert list(want.samples) == seq_rec.samples and want.evaluations == budget
    combos = discrete_combos(space)
    where = [next(i for i, c in enumerate(combos) if all(s[k] == v for k, v in c.items()))
             for s in want.samples]
    assert where == sorted(where)  # the curve: combination order, then evaluation order
    for w in (2, 4):
        ev = Jittery()
        assert make_sampler(name, concurrent=w).run(space, ev, budget, 5) == want
        assert 1 < ev.overlap <= w
        again = NloptSampler(name, concurrent=w).optimise(space, Jittery(), budget, seed=5)
        assert again == seq


@pytest.mark.parametrize("name", ["LN_BOBYQA", "GN_CRS2_LM"])
@pytest.mark.parametrize("error", [RuntimeError, KeyboardInterrupt])
def test_an_error_in_one_combination_stops_the_run_promptly(name, error):
    """Raised by `evaluate` in one thread (a worker died, an interrupt reached it), the error
    itself leaves `run` within one evaluation of the others, with no thread left behind (CRS
    calls its objective once more after a stop; that call must not evaluate)."""
    space = small_space()
    calls: list[float] = []

    def evaluate(batch):
        s = batch[0]
        calls.append(time.perf_counter())
        if all(s[k] == v for k, v in failing.items()) and len(calls) > 6:
            raise error("worker died")
        time.sleep(0.01)
        return [planted(s)]

    before = threading.active_count()
    for w in (1, 2):
        failing = discrete_combos(space)[w - 1]   # with 2 threads: while the first one runs
        t0 = time.perf_counter()
        with pytest.raises(error, match="worker died"):   # 24 × 200 × 10 ms otherwise
            NloptSampler(name, concurrent=w).run(space, evaluate, 24 * 200, 0)
        assert time.perf_counter() - t0 < 2.0
        n = len(calls)
        time.sleep(0.1)
        assert len(calls) == n and threading.active_count() == before
        calls.clear()


def test_an_interrupt_in_the_calling_thread_stops_every_combination():
    space = small_space()
    calls: list[int] = []

    def evaluate(batch):
        calls.append(1)
        time.sleep(0.01)
        return [planted(s) for s in batch]

    before = threading.active_count()
    # A process a non-interactive shell starts in the background (`pytest &`, nohup) inherits
    # SIGINT ignored, and Python then installs no handler: Ctrl-C is what this test is about,
    # so it installs Python's own for its duration.
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    timer = threading.Timer(0.3, os.kill, (os.getpid(), signal.SIGINT))
    try:
        timer.start()
        t0 = time.perf_counter()
        with pytest.raises(KeyboardInterrupt):
            NloptSampler("GN_CRS2_LM", concurrent=3).run(space, evaluate, 24 * 200, 0)
    finally:
        timer.cancel()
        signal.signal(signal.SIGINT, previous)
    assert time.perf_counter() - t0 < 3.0 and calls
    n = len(calls)
    time.sleep(0.1)
    assert len(calls) == n and threading.active_count() == before


def test_concurrent_must_be_a_positive_integer():
    for bad in (0, -1, 1.5, True):
        with pytest.raises(ConfigError, match="concurrent"):
            run("LN_BOBYQA", paper_space(), 10, concurrent=bad)
