"""--executor ray on a multi-node cluster: a local Ray cluster of one head and two worker nodes
(separate raylets and object stores on loopback); a whole worker node is removed mid-run, its
actors and object store with it, and a new node joins. The rows equal those of local processes.
Skipped where ray is not installed."""

from __future__ import annotations

import os
import threading
from dataclasses import replace
from pathlib import Path

import pytest

from falsify.executors.driver import Driver, Progress
from falsify.executors.evaluator import EvalSettings
from falsify.jobs.run import RunRequest, execute
from falsify.results.samples import CAR_SCORING
from falsify.results.store import STORE_NAME, TIMING_COLUMNS, Store, read_frame
from falsify.sampler import make_sampler
from falsify.world.space import load_space

pytestmark = pytest.mark.slow   # the heavy tier: real multi-node Ray clusters

ROOT = Path(__file__).resolve().parents[2]
CI = ROOT / "tests" / "data" / "small-grid.toml"  # 24 samples on 2 streets


def rows(path: Path):
    return read_frame(path).drop(columns=list(TIMING_COLUMNS))


@pytest.fixture(scope="module")
def cluster():
    """Head with no CPU (it schedules, it does not score) and two 1-CPU worker nodes."""
    pytest.importorskip("ray", reason='ray is not installed (pip install "falsify[ray]")')
    from ray.cluster_utils import Cluster

    c = Cluster(initialize_head=True, head_node_args={
        "num_cpus": 0, "include_dashboard": False, "node_ip_address": "127.0.0.1"})
    nodes = [c.add_node(num_cpus=1, node_ip_address="127.0.0.1") for _ in range(2)]
    c.wait_for_nodes()
    import ray
    from ray._private import services
    # Ray rewrites a loopback address into the machine's own interface address before it
    # dials; where only loopback is open (this sandbox, CI) that never answers. Keep loopback
    # for this test's driver; the executor then uses this connection.
    services.node_ip_address_from_perspective = lambda *a, **k: "127.0.0.1"
    ray.init(address=c.address, _node_ip_address="127.0.0.1", log_to_driver=False,
             logging_level="ERROR")
    yield c, nodes
    ray.shutdown()
    c.shutdown()


def test_without_address_a_run_starts_its_own_ray_beside_a_running_cluster(cluster, tmp_path):
    """A cluster started on the machine (`ray start`, here the fixture's) is the one Ray's
    default joins; without --address falsify starts its own local instance, as documented (it
    joined the cluster and failed: "num_cpus and num_gpus must not be provided")."""
    import subprocess
    import sys

    out = tmp_path / "own"
    env = {k: v for k, v in os.environ.items() if k != "RAY_ADDRESS"}
    done = subprocess.run([sys.executable, "-m", "falsify", "grid", str(CI), "--out", str(out),
                           "--quiet", "--no-report", "--workers", "1", "--executor", "ray"],
                          capture_output=True, text=True, timeout=600, env=env)
    assert done.returncode == 0, done.stderr[-2000:]
    assert len(read_frame(out)) == 24


def test_a_removed_node_and_a_joining_one_give_the_process_rows(cluster, tmp_path):
    c, nodes = cluster
    process = tmp_path / "process"
    execute(RunRequest(config=CI, out=process, command="grid", workers=2, report=False))

    space = load_space(CI)
    scoring = replace(CAR_SCORING, parts=True)   # what the grid run scores: the placed car apart
    store = Store(tmp_path / STORE_NAME, space, scoring)
    events: list[str] = []
    lock = threading.Lock()

    def lose_a_node(progress, final):
        """After the first chunks: a whole node goes, then a fresh one joins. Chunks of 2 leave
        nine for after the loss, so both actors take work again and the dead one is met
        whichever node held it (with three chunks of 8 the live one could take the last)."""
        with lock:
            if events or final or progress.done < 6:
                return
            events.append("removed")
        c.remove_node(nodes[0], allow_graceful=False)
        c.add_node(num_cpus=1, node_ip_address="127.0.0.1")
        events.append("added")

    settings = EvalSettings(space=space, scoring=scoring)
    with Driver(settings, store, workers=2, batch=2, executor="ray", address=c.address,
                progress=Progress(None, lose_a_node)) as driver:
        make_sampler("grid").run(space, driver.evaluate, None, space.seed)
        replaced = driver.executor.replaced
    store.close()
    assert events == ["removed", "added"]
    assert replaced >= 1, "the removed node's actor was not replaced"
    got, want = rows(tmp_path / STORE_NAME), rows(process / STORE_NAME)
    assert len(got) == len(space.grid()) and got.equals(want)
