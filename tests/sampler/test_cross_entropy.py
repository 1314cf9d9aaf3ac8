"""The cross-entropy sampler: it keeps to its budget and the space, replays the same samples
for the same seed and scores, and finds more failing samples than random at equal budget on an
objective whose failures sit in a small corner."""

from __future__ import annotations

import numpy as np
import pytest

from falsify.errors import ConfigError
from falsify.sampler import make_sampler
from falsify.world.space import parse_space
from tests.conftest import scored

DIMS = {"car_model": {"values": ["sedan", "suv"]}, "x": {"min": -5, "max": 4, "step": 1},
        "y": {"min": 5, "max": 19, "step": 1}, "background": {"values": [0, 1, 2, 3, 4, 5]}}


def space():
    return parse_space({"seed": 0, "threshold": 0.65, "dims": DIMS}, builtin_cars=("sedan", "suv"))


def corner(s) -> float:
    """Falls off towards far right and on street 4, like IoU with distance: below 0.65 only in a
    corner of the space (about 3 % of it)."""
    street = 0.12 if s["background"] == 4 else 0.0
    return 0.95 - 0.012 * (s["y"] - 5) - 0.012 * (s["x"] + 5) - street



def test_keeps_budget_space_and_replays():
    sp = space()
    ev, calls = scored(corner)
    a = make_sampler("cross-entropy").run(sp, ev, 95, seed=7)
    assert a.evaluations == 95 and sum(calls) == 95 and max(calls) <= 20
    for s in a.samples:
        assert -5 <= s["x"] <= 4 and 5 <= s["y"] <= 19 and s["background"] in range(6)
        assert s["car_model"] in ("sedan", "suv")
    b = make_sampler("cross-entropy").run(sp, scored(corner)[0], 95, seed=7)
    assert a.samples == b.samples and a.curve == b.curve
    c = make_sampler("cross-entropy").run(sp, scored(corner)[0], 95, seed=8)
    assert c.samples != a.samples


def test_finds_more_failures_than_random_at_equal_budget():
    sp = space()
    ce, rnd = [], []
    for seed in range(5):
        for name, out in (("cross-entropy", ce), ("random", rnd)):
            res = make_sampler(name).run(sp, scored(corner)[0], 200, seed=seed)
            out.append(sum(1 for v in res.curve if v is not None and v < sp.threshold))
    assert np.mean(ce) > 3 * np.mean(rnd), (ce, rnd)
    assert min(ce) > max(rnd), (ce, rnd)


def test_invalid_scores_are_skipped():
    sp = space()
    res = make_sampler("cross-entropy").run(sp, scored(lambda s: None)[0], 40, seed=0)
    assert res.evaluations == 40 and res.best is None


@pytest.mark.parametrize("options", [{"buckets": 0}, {"elite": 0.0}, {"smoothing": 1.5},
                                     {"batch_size": 0}, {"floor": -1}])
def test_bad_options_are_named(options):
    with pytest.raises(ConfigError, match=next(iter(options))):
        make_sampler("cross-entropy", **options)


def test_search_command_runs_it(tmp_path, capsys, monkeypatch):
    """Through the CLI on the smoke config: rows are stored, and a resume recomputes nothing."""
    from pathlib import Path

    from falsify.cli import main
    monkeypatch.chdir(Path(__file__).resolve().parents[2])
    out = tmp_path / "ce"
    argv = ["search", "configs/smoke.toml", "--algorithm", "cross-entropy", "--budget", "12",
            "--out", str(out), "--quiet", "--json"]
    assert main(argv) == 0
    capsys.readouterr()
    assert main([*argv, "--resume"]) == 0
    import json
    doc = json.loads(capsys.readouterr().out)
    assert doc["samples"] == 12 and doc["computed_this_time"] == 0
