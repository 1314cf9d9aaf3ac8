"""--executor ray records the environments of its actors (their nodes' versions, ray's too), and
tells actors set up differently apart. Heavy tier; it shares the Ray modules' xdist worker."""

from __future__ import annotations

import os
import sqlite3
from pathlib import Path

import pytest

from falsify.cli import main
from falsify.executors.environment import session_changes
from falsify.executors.evaluator import EvalSettings
from falsify.executors.ray import EvalActor, RayExecutor
from falsify.jobs.run import RunRequest, execute
from falsify.results.store import STORE_NAME, read_meta
from falsify.world.space import load_space

pytestmark = [pytest.mark.slow, pytest.mark.xdist_group("ray")]

ROOT = Path(__file__).resolve().parents[2]
SMALL = ROOT / "tests" / "data" / "small-grid.toml"   # 24 samples on 2 streets


def test_a_run_resumed_on_ray_records_the_actors_environment(ray, tmp_path, capsys):
    """A process run cut after 16 rows, resumed on one Ray actor: the new session holds the
    actor's environment with ray's version; ray computes no number and the actor's one session
    of 2 threads gives the bytes of two workers' 1, so nothing is said to have changed."""
    run = tmp_path / "run"
    execute(RunRequest(config=SMALL, out=run, command="grid", workers=2, report=False))
    with sqlite3.connect(run / STORE_NAME) as db:
        db.execute("DELETE FROM samples WHERE eval_index >= 16")
    assert main(["grid", str(SMALL), "--out", str(run), "--resume", "--executor", "ray",
                 "--workers", "1", "--no-report", "--quiet"]) == 0
    assert "warning" not in capsys.readouterr().err
    first, second = read_meta(run)["sessions"]
    [local], [actor] = first["environments"], second["environments"]
    assert "ray" not in local and actor["ray"] == ray.__version__
    assert actor["inference_threads"] == 2 and local["inference_threads"] == 1
    assert {k: v for k, v in actor.items() if k not in ("ray", "inference_threads")} == \
        {k: v for k, v in local.items() if k != "inference_threads"}
    assert "changed" not in second


class OtherNumpyActor(EvalActor):
    """An actor whose node has another numpy, as on a cluster set up unevenly."""

    def environment(self) -> dict:
        env = super().environment()
        return env | {"numpy": f"{env['numpy']}+node{os.getpid()}"}


def test_actors_of_unlike_nodes_are_each_recorded(ray):
    """Two actors that report different numpy versions: both environments are kept, and what
    differs is named."""
    settings = EvalSettings(space=load_space(SMALL))
    with RayExecutor(settings, 2, actor=OtherNumpyActor) as ex:
        envs = ex.environments()
    assert len(envs) == 2 and envs[0]["numpy"] != envs[1]["numpy"]
    assert session_changes([], envs) == [f"numpy {envs[0]['numpy']} -> {envs[1]['numpy']}"]
