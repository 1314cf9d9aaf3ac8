"""--executor ray: the same rows as local processes, also when an actor is killed mid-run; bad
--address values and actors that cannot start exit 2 with one line and nothing written, a crash
is told apart. One local Ray instance (loopback, 2 CPUs) serves the module; the tests that need
it skip where ray is not installed."""

from __future__ import annotations

import json
import os
import shutil
import sqlite3
import subprocess
import sys
import threading
import time
from dataclasses import replace
from pathlib import Path

import pandas as pd
import pytest

from falsify.cli import main
from falsify.errors import FalsifyError
from falsify.executors.driver import Driver, Progress
from falsify.executors.evaluator import EvalSettings, Evaluator
from falsify.executors.ray import ActorCrash, EvalActor, RayExecutor, Shipment, import_ray
from falsify.jobs.run import RunRequest, execute, executors_of
from falsify.models.runners import load_segmenter
from falsify.models.spec import spec_path_for
from falsify.results.samples import CAR_SCORING, sample_key
from falsify.results.store import STORE_NAME, TIMING_COLUMNS, Store, read_frame, read_meta
from falsify.sampler import make_sampler
from falsify.world.space import load_space
from tests.bench.test_bench import check_pipeline_figures
from tests.cli.test_bad_input import snapshot

pytestmark = pytest.mark.slow   # the heavy tier: Ray: a local instance per module, whole grids
RUN_SCORING = replace(CAR_SCORING, parts=True)   # what a grid run scores: the placed car apart too

ROOT = Path(__file__).resolve().parents[2]
CI = ROOT / "tests" / "data" / "small-grid.toml"  # 24 samples on 2 streets


@pytest.fixture(scope="module")
def process_run(tmp_path_factory) -> Path:
    """The small grid on two local worker processes: the reference run."""
    out = tmp_path_factory.mktemp("process") / "run"
    execute(RunRequest(config=CI, out=out, command="grid", workers=2, report=False))
    return out


@pytest.fixture(scope="module")
def process_rows(process_run):
    """The reference run's rows."""
    return rows(process_run / STORE_NAME)


def wait_for_free_cpus(ray, cpus: float = 2.0, timeout: float = 60.0) -> None:
    """Every CPU of the module's Ray instance free again (no actor left holding one)."""
    deadline = time.time() + timeout
    while ray.available_resources().get("CPU", 0.0) < cpus:
        assert time.time() < deadline, f"actors left behind: {ray.available_resources()}"
        time.sleep(0.2)


def rows(path: Path):
    """Every stored column but the timings, in evaluation order."""
    return read_frame(path).drop(columns=list(TIMING_COLUMNS))


def test_ray_rows_equal_process_rows(ray, process_rows, tmp_path):
    out = tmp_path / "run"
    assert main(["grid", str(CI), "--out", str(out), "--executor", "ray", "--workers", "2",
                 "--no-report", "--quiet", "--json"]) == 0
    got = rows(out / STORE_NAME)
    assert len(got) == 24
    assert got.equals(process_rows)


def test_killed_actor_gives_the_identical_rows(ray, process_rows, tmp_path):
    space = load_space(CI)
    store = Store(tmp_path / STORE_NAME, space, RUN_SCORING)
    killed: list = []

    def kill_one(progress, final):   # after the first chunk, kill an actor holding a chunk
        if not killed and not final and driver.executor.in_flight:
            chunk, actor = next(iter(driver.executor.in_flight.values()))
            ray.kill(actor)
            killed.append(chunk)

    with Driver(EvalSettings(space=space, scoring=RUN_SCORING), store, workers=2, executor="ray",
                progress=Progress(None, kill_one)) as driver:
        make_sampler("grid").run(space, driver.evaluate, None, space.seed)
        reruns, replaced = driver.executor.reruns, driver.executor.replaced
    store.close()
    # The killed actor's chunk may already have finished (its result is kept), so a re-run is
    # not certain; the replacement and the identical rows are.
    assert killed and replaced == 1 and reruns <= 1
    assert rows(tmp_path / STORE_NAME).equals(process_rows)


def test_map_serves_concurrent_callers_in_their_own_order(ray, process_rows):
    """Two threads map chunks at once on two actors: each gets its own results in its order."""
    space = load_space(CI)
    grid = space.grid()
    asks = [[grid[i:i + 2] for i in range(k, 24, 8)] for k in (0, 4)]
    got: dict[int, list] = {}
    with RayExecutor(EvalSettings(space=space), 2) as ex:
        threads = [threading.Thread(target=lambda k=k: got.__setitem__(k, list(ex.map(asks[k]))))
                   for k in (0, 1)]
        for t in threads:
            t.start()
        for t in threads:
            t.join(120)
        assert not ex.in_flight and len(ex.actors) == 2
    want = process_rows.set_index("sample_key")["car_iou"]
    for k in (0, 1):
        assert [[r.sample for r in chunk] for chunk in got[k]] == asks[k]
        for chunk in got[k]:
            for r in chunk:
                v = want[sample_key(r.sample)]
                assert (r.score is None and v != v) or r.score == pytest.approx(v, abs=1e-6)


def test_concurrent_search_on_ray_gives_the_rows_of_one_process(ray, tmp_path):
    """NLopt runs the two backgrounds at once on two actors: the rows and the curve of
    the sequential loop on one local process."""
    runs = {}
    for name, executor, workers in (("one", "process", 1), ("ray", "ray", 2)):
        runs[name] = execute(RunRequest(config=CI, out=tmp_path / name, command="search",
                                        algorithm="GN_CRS2_LM", budget=12, workers=workers,
                                        executor=executor, report=False))
    assert runs["one"].search == runs["ray"].search
    pd.testing.assert_frame_equal(rows(tmp_path / "one" / STORE_NAME),
                                  rows(tmp_path / "ray" / STORE_NAME),
                                  check_exact=False, atol=1e-6)


@pytest.mark.parametrize("address, says", [
    ("127.0.0.1:1", "--address 127.0.0.1:1: no Ray head answers there"),
    ("nohost", "--address 'nohost': expected HOST:PORT"),
    ("10.0.0.1:99999", "expected HOST:PORT"),
])
def test_bad_address_exits_2_and_writes_nothing(address, says, tmp_path, capsys):
    out = tmp_path / "run"
    code = main(["grid", str(CI), "--out", str(out), "--executor", "ray", "--address", address,
                 "--quiet"])
    err = capsys.readouterr().err
    assert code == 2 and says in err and err.count("\n") == 1
    assert not out.exists()


def test_address_needs_the_ray_executor(tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["grid", str(CI), "--out", str(out), "--address", "127.0.0.1:6379"]) == 2
    assert "only with --executor ray" in capsys.readouterr().err
    assert not out.exists()


def test_missing_ray_is_one_clear_error(monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)
    with pytest.raises(FalsifyError, match=r'ray is not installed; pip install "falsify\[ray\]"'):
        import_ray()


def test_bench_pipeline_measures_ray_beside_processes(ray, capsys):
    assert main(["bench", "pipeline", "--config", str(CI), "--samples",
                 "24", "--workers", "2", "--executor", "ray", "--json"]) == 0
    r = json.loads(capsys.readouterr().out)
    assert r["ray"]["actors"] == 2 and r["ray"]["samples_per_s"] > 0
    assert r["ray"]["against_processes"] > 0 and r["ray"]["tasks_timed"] == 200
    assert 0 < r["ray"]["task_round_trip_ms"] and 0 < r["ray"]["driver_ms_per_task"]
    check_pipeline_figures(r, CI)   # the process paths' figures, from the same run


class CrashingActor(EvalActor):
    """An actor whose Evaluator fails as a bug in falsify would (not the user's input)."""

    def build(self, shipment: Shipment) -> Evaluator:
        return {}["lod"]


class DyingActor(EvalActor):
    """An actor whose process dies while it starts, as one killed by its node would."""

    def build(self, shipment: Shipment) -> Evaluator:
        os._exit(3)


class FailsOnceMarked(EvalActor):
    """Starts as usual until the file `marker` exists, then fails as an unreadable input would."""

    marker = Path("/nonexistent")

    def build(self, shipment: Shipment) -> Evaluator:
        if self.marker.exists():
            raise FalsifyError(f"user car mesh {self.marker}: cannot be read on this node")
        return super().build(shipment)


def test_replacement_that_cannot_start_stops_the_run(ray, tmp_path):
    """Actors die mid-run and their replacements fail to start: the failure's own line, not
    chunks re-run on actors that never start."""
    ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])
    marker = tmp_path / "marker"
    actor = type("Marked", (FailsOnceMarked,), {"marker": marker})
    space = load_space(CI)
    chunks = [[s] for s in space.grid()[:6]]
    with pytest.raises(FalsifyError, match=r"could not start: user car mesh .*marker: cannot"):
        with RayExecutor(EvalSettings(space=space), 2, actor=actor) as ex:
            results = ex.map(chunks)
            next(results)
            marker.touch()
            for a in list(ex.actors):   # the next chunk goes to a dead actor, whatever finished
                ray.kill(a)
            list(results)
    assert ex.replaced >= 1 and not ex.actors
    wait_for_free_cpus(ray)


def test_actor_that_cannot_load_the_model_stops_with_one_line(ray, tmp_path):
    """The model file changed on disk after the driver opened it: every actor fails to load it,
    which is the user's input (FalsifyError naming the user's file, not the node's copy)."""
    corrupt = tmp_path / "corrupt.onnx"
    corrupt.write_bytes(b"not an onnx graph" * 64)
    shutil.copy(spec_path_for(load_segmenter().path), spec_path_for(corrupt))
    space = load_space(CI)
    store = Store(tmp_path / STORE_NAME, space)
    with pytest.raises(FalsifyError) as err:
        with Driver(EvalSettings(space=space, model=str(corrupt)), store, workers=2,
                    executor="ray", model=load_segmenter()):
            pytest.fail("the driver started with actors that cannot load the model")
    store.close()
    message = str(err.value)
    assert "an actor on" in message and "could not start: cannot load ONNX model" in message
    assert str(corrupt) in message and "falsify-blobs" not in message
    assert "\n" not in message
    wait_for_free_cpus(ray)


@pytest.mark.parametrize("actor, says", [
    (CrashingActor, "crashed while starting: KeyError: 'lod'"),
    (DyingActor, "an actor died while starting"),
])
def test_actor_crash_is_not_an_input_error(ray, actor, says):
    ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])   # workers need no tests/
    with pytest.raises(ActorCrash) as err:
        with RayExecutor(EvalSettings(space=load_space(CI)), 2, actor=actor):
            pytest.fail("the executor started with actors that crashed")
    assert not isinstance(err.value, FalsifyError)
    assert says in str(err.value).splitlines()[0]
    wait_for_free_cpus(ray)


def test_actor_start_failure_exits_2_and_leaves_no_run(tmp_path):
    """Actors whose node cannot write the shipped files (FALSIFY_CACHE): one line naming it,
    exit 2, Ray shut down, and no run directory that --resume would then misread."""
    pytest.importorskip("ray", reason='ray is not installed (pip install "falsify[ray]")')
    before = snapshot(tmp_path)
    env = {**os.environ, "FALSIFY_CACHE": "/proc/falsify-cache"}
    r = subprocess.run([sys.executable, "-m", "falsify", "grid",
                        str(ROOT / "configs" / "smoke.toml"), "--out", "run", "--executor", "ray",
                        "--workers", "1", "--quiet"], cwd=tmp_path, env=env,
                       capture_output=True, text=True, timeout=300)
    lines = [line for line in r.stderr.splitlines() if line.strip()]
    assert r.returncode == 2 and len(lines) == 1, r.stderr[-3000:]
    assert "could not start: FALSIFY_CACHE: cannot write" in lines[0]
    assert "/proc/falsify-cache" in lines[0]
    assert snapshot(tmp_path) == before, "the failed run left files behind"


def test_resume_on_another_executor_is_allowed_and_recorded(ray, process_run, process_rows,
                                                            tmp_path, capsys):
    """A run killed after 18 of 24 samples on two processes, resumed on one Ray actor: the rows
    equal the uninterrupted run's (they do not depend on the executor or --workers), the meta
    keeps both sessions and the summary names both executors."""
    run = tmp_path / "run"
    shutil.copytree(process_run, run)
    with sqlite3.connect(run / STORE_NAME) as db:
        db.execute("DELETE FROM samples WHERE eval_index >= 18")
    assert main(["grid", str(CI), "--out", str(run), "--resume", "--executor", "ray",
                 "--workers", "1", "--no-report", "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "6 computed now" in out and "computed on executors process, then ray" in out
    assert rows(run / STORE_NAME).equals(process_rows)
    sessions = read_meta(run)["sessions"]
    assert [(s["executor"], s["workers"]) for s in sessions] == [("process", 2), ("ray", 1)]
    assert json.loads((run / "summary.json").read_text())["executors"] == ["process", "ray"]


def test_runs_from_before_sessions_count_their_first_executor():
    assert executors_of({"executor": "ray", "workers": 2, "started": "2025"}) == ["ray"]
    assert executors_of({"workers": 1}) == ["process"]    # made before --executor existed
    assert executors_of({}) == []
    assert executors_of({"sessions": [{"executor": "process"}, {"executor": "ray"},
                                      {"executor": "process"}]}) == ["process", "ray"]


def test_shipped_model_is_loaded_with_its_own_spec(tmp_path, monkeypatch):
    """The same network shipped twice with an edited spec: the node's copy is opened with the
    spec shipped this time, not the one left beside it by the first run (same model hash as
    the driver's)."""
    monkeypatch.setenv("FALSIFY_CACHE", str(tmp_path / "cache"))
    space = load_space(CI)
    bundled = load_segmenter().path
    for name, shift in (("a", 0.0), ("b", 1.0)):
        model = tmp_path / name / "net.onnx"
        model.parent.mkdir()
        shutil.copy(bundled, model)
        spec = json.loads(spec_path_for(bundled).read_text())
        spec["mean"] = [m + shift for m in spec["mean"]]
        spec_path_for(model).write_text(json.dumps(spec))
        local = Shipment.of(EvalSettings(space=space, model=str(model))).local_settings()
        assert load_segmenter(local.model).model_hash == load_segmenter(str(model)).model_hash
