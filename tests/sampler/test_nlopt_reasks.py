"""NLopt asks again for points it has scored (simplex methods re-evaluate a vertex, restarts
land on old points): the driver answers each from the store, neither casting and predicting it
again nor storing a second row, and the re-ask counts as one of the budget's evaluations (the
curve holds it); a search stopped in the middle and resumed ends with the same files."""

from __future__ import annotations

import json
from collections import Counter
from pathlib import Path

import pandas as pd
import pytest

from falsify.executors.evaluator import Evaluator
from falsify.jobs.run import RunRequest, execute
from falsify.results.samples import sample_key
from falsify.results.store import read_frame, read_meta
from tests.cli.test_pipeline import BUNDLED, exported, rows

pytestmark = pytest.mark.skipif(not BUNDLED.exists(), reason="bundled model not trained yet")

# One street, a car from beside the ego car to 12 m ahead: LN_SBPLX re-asks points here.
CONFIG = """name = "reasks"
sensor = "kitti-hdl64e-front"
seed = 0
[dims.car_model]
values = ["sedan"]
[dims.x]
min = -2.0
max = 2.0
step = 1.0
[dims.y]
min = 0.0
max = 12.0
step = 1.0
[dims.background]
values = [0]
"""
ALGORITHM, BUDGET = "LN_SBPLX", 12


@pytest.fixture
def scored(monkeypatch) -> Counter:
    """How often the evaluator (ray-cast and network) scored each sample, by key."""
    counts: Counter = Counter()
    real = Evaluator.score_batch

    def counting(self, samples):
        counts.update(sample_key(s) for s in samples)
        return real(self, samples)

    monkeypatch.setattr(Evaluator, "score_batch", counting)
    return counts


def _search(config: Path, out: Path, **kw):
    return RunRequest(config=config, out=out, command="search", algorithm=ALGORITHM,
                      budget=BUDGET, seed=0, workers=1, report=False, **kw)


def test_a_reasked_point_is_read_back_not_scored_or_stored_again(tmp_path, scored):
    config = tmp_path / "reasks.toml"
    config.write_text(CONFIG)
    summary = execute(_search(config, tmp_path / "run"))
    asked = [sample_key(s) for s in summary.search.samples]
    distinct = set(asked)
    assert len(asked) == BUDGET == len(read_meta(tmp_path / "run")["curve"])
    assert len(distinct) < len(asked), "the search must re-ask a point for this test to check"
    frame = read_frame(tmp_path / "run")
    assert sorted(frame["sample_key"]) == sorted(distinct)
    assert summary.samples == summary.computed_this_time == len(distinct)
    assert set(scored) == distinct and set(scored.values()) == {1}


@pytest.mark.slow
def test_a_stopped_nlopt_search_resumes_to_the_files_of_an_unbroken_one(tmp_path, scored):
    """Stopped once it has scored the points before its first re-ask, resumed: each point
    scored once over both invocations, and the same rows and files (timings apart) as one run."""
    config = tmp_path / "reasks.toml"
    config.write_text(CONFIG)
    whole = execute(_search(config, tmp_path / "whole"))
    asked = [sample_key(s) for s in whole.search.samples]
    first_repeat = next(i for i, k in enumerate(asked) if k in asked[:i])
    before = len(set(asked[:first_repeat]))
    scored.clear()

    def stop(progress, final):
        if progress.computed >= before:
            raise KeyboardInterrupt

    cut = tmp_path / "cut"
    with pytest.raises(KeyboardInterrupt):
        execute(_search(config, cut), on_progress=stop)
    assert len(read_frame(cut)) == before
    again = execute(_search(config, cut, resume=True))
    assert again.computed_this_time == len(set(asked)) - before
    assert set(scored) == set(asked) and set(scored.values()) == {1}
    assert again.search == whole.search
    pd.testing.assert_frame_equal(rows(tmp_path / "whole"), rows(cut))
    assert read_meta(cut)["curve"] == read_meta(tmp_path / "whole")["curve"]
    assert _files(cut) == _files(tmp_path / "whole")


def _files(run: Path) -> dict[str, str]:
    """`exported` files of a run, its summary without what differs between invocations."""
    files = exported(run)
    summary = json.loads(files["summary.json"])
    del summary["computed_this_time"]
    return {**files, "summary.json": json.dumps(summary)}
