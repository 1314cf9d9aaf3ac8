"""The stored icospheres equal trimesh's own, and a worker that scores samples on built-in cars
never imports trimesh (with scipy, some 65 MB of every worker's memory)."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
import trimesh

from falsify.world.shapes import _unit_icosphere


@pytest.mark.parametrize("subdivisions", [0, 1, 2, 3])
def test_stored_icospheres_are_trimeshs(subdivisions: int) -> None:
    want = trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0)
    v, f = _unit_icosphere(subdivisions)
    assert v.tobytes() == np.asarray(want.vertices, np.float64).tobytes()
    assert f.tobytes() == np.asarray(want.faces, np.int64).tobytes()


def test_unstored_subdivisions_are_refused() -> None:
    with pytest.raises(ValueError, match="stored are 0-3"):
        _unit_icosphere(4)


def test_a_worker_scores_without_trimesh() -> None:
    code = """
import sys
from falsify.executors.evaluator import EvalSettings, Evaluator
from falsify.paths import CONFIGS
from falsify.world.space import load_space
space = load_space(CONFIGS / "paper.toml")
middle = [s for s in space.grid() if s["x"] == 0.0]   # on the road of every street
samples = middle[:3] + middle[-3:]
scores = Evaluator(EvalSettings(space=space, threads=1)).score_batch(samples)
assert all(r.score is not None for r in scores), scores
print(sorted(m for m in ("trimesh", "scipy", "pandas") if m in sys.modules))
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout
    assert out.strip() == "[]", out
