"""--executor ray: the same rows as local processes, also when an actor is killed mid-run; bad
--address values exit 2 with one line and nothing written. One local Ray instance (loopback,
2 CPUs) serves the module; the tests that need it skip where ray is not installed."""

from __future__ import annotations

import json
import sys
import threading
from pathlib import Path

import pandas as pd
import pytest
from falsify.sampler.base import make_sampler

from falsify.cli import main
from falsify.cluster import RayExecutor, import_ray
from falsify.errors import FalsifyError
from falsify.pipeline import Driver, EvalSettings, Progress
from falsify.runs import RunRequest, execute
from falsify.space import load_space
from falsify.store import STORE_NAME, TIMING_COLUMNS, Store, read_frame, sample_key

CI = Path(__file__).resolve().parent.parent / "configs" / "ci.toml"


@pytest.fixture(scope="module")
def ray():
    ray = pytest.importorskip("ray", reason='ray is not installed (pip install "falsify[ray]")')
    ray.init(num_cpus=2, include_dashboard=False, _node_ip_address="127.0.0.1",
             log_to_driver=False, logging_level="ERROR")
    yield ray
    ray.shutdown()


@pytest.fixture(scope="module")
def process_rows(tmp_path_factory):
    """configs/ci.toml on two local worker processes: the reference rows."""
    out = tmp_path_factory.mktemp("process") / "run"
    execute(RunRequest(config=CI, out=out, command="grid", workers=2, report=False))
    return rows(out / STORE_NAME)


def rows(path: Path):
    """Every stored column but the timings, in evaluation order."""
    return read_frame(path).drop(columns=list(TIMING_COLUMNS))


def test_ray_rows_equal_process_rows(ray, process_rows, tmp_path):
    out = tmp_path / "run"
    assert main(["grid", str(CI), "--out", str(out), "--executor", "ray", "--workers", "2",
                 "--no-report", "--quiet", "--json"]) == 0
    got = rows(out / STORE_NAME)
    assert len(got) == 75
    assert got.equals(process_rows)


def test_killed_actor_gives_the_identical_rows(ray, process_rows, tmp_path):
    space = load_space(CI)
    store = Store(tmp_path / STORE_NAME, space)
    killed: list = []

    def kill_one(progress, final):   # after the first chunk, kill an actor holding a chunk
        if not killed and not final and driver.ray.in_flight:
            chunk, actor = next(iter(driver.ray.in_flight.values()))
            ray.kill(actor)
            killed.append(chunk)

    with Driver(EvalSettings(space=space), store, workers=2, executor="ray",
                progress=Progress(None, kill_one)) as driver:
        make_sampler("grid").run(space, driver.evaluate, None, space.seed)
        reruns, replaced = driver.ray.reruns, driver.ray.replaced
    store.close()
    assert killed and reruns >= 1 and replaced == 1
    assert rows(tmp_path / STORE_NAME).equals(process_rows)


def test_map_serves_concurrent_callers_in_their_own_order(ray, process_rows):
    """Two threads map chunks at once on two actors: each gets its own results in its order."""
    space = load_space(CI)
    grid = space.grid()
    asks = [[grid[i:i + 2] for i in range(k, 40, 8)] for k in (0, 4)]
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
    """NLopt runs the three backgrounds two at a time on two actors: the rows and the curve of
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
    assert main(["bench", "pipeline", "--config", str(CI.with_name("smoke.toml")), "--samples",
                 "24", "--workers", "2", "--executor", "ray", "--json"]) == 0
    r = json.loads(capsys.readouterr().out)
    assert r["ray"]["actors"] == 2 and r["ray"]["samples_per_s"] > 0
    assert r["ray"]["against_processes"] > 0 and r["ray"]["tasks_timed"] == 200
    assert 0 < r["ray"]["task_round_trip_ms"] and 0 < r["ray"]["driver_ms_per_task"]
    assert r["driver_store_rows_per_s"] > 0 and r["2_workers"]["samples_per_s"] > 0
