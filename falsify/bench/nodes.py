"""`falsify bench nodes`: samples/s through Ray on local clusters of 1, 2, ... N one-CPU nodes
(each node its own raylet and object store on loopback, as `ray.cluster_utils.Cluster` starts
them), every count against one node in the same run: the scale-out model measured, not derived.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from pathlib import Path

from falsify.bench.machine import machine
from falsify.bench.scan import possible
from falsify.checks import MAX_SAMPLES
from falsify.data.real_backgrounds import scanner_for
from falsify.errors import FalsifyError
from falsify.world.space import load_space


@dataclass(frozen=True)
class NodeRate:
    """The driver's rate over a local cluster of `nodes` one-CPU worker nodes."""

    nodes: int
    samples: int          # timed: all but the first chunk of each node's actor
    seconds: float
    start_s: float        # the cluster's start and every actor warm, before the clock

    @property
    def samples_per_s(self) -> float:
        return self.samples / self.seconds


@dataclass(frozen=True)
class NodesBench:
    config: str
    batch: int
    machine: dict
    rates: tuple[NodeRate, ...]

    def to_json(self) -> dict:
        one = self.rates[0].samples_per_s
        cores = os.cpu_count() or 1
        return {
            "benchmark": "nodes", "config": self.config, "samples_per_task": self.batch,
            "machine": self.machine, "node_cpus": 1, "head_cpus": 0,
            "nodes": [{"nodes": r.nodes, "samples_timed": r.samples,
                       "samples_per_s": round(r.samples_per_s, 2),
                       "over_1_node": round(r.samples_per_s / one, 3),
                       "ideal_on_this_machine": min(r.nodes, cores),
                       "cluster_start_s": round(r.start_s, 1)} for r in self.rates],
            "note": f"every node runs on this machine's {cores} cores: past {cores} nodes they "
                    "share cores, so the ideal stops growing there",
        }


def bench_nodes(config: str | Path, nodes: int = 2, samples: int = 120, batch: int = 8,
                model: str | None = None, on_progress=None) -> NodesBench:
    """For n = 1..`nodes`: a fresh local cluster (a head that only schedules, n worker nodes of
    one CPU), one actor a node, the same samples through the driver and a store, timed after
    each actor's first chunk."""
    import tempfile

    from falsify.executors.driver import Driver, Progress
    from falsify.executors.evaluator import EvalSettings
    from falsify.executors.ray import import_ray
    from falsify.models.runners import backend_for
    from falsify.results.store import Store

    space = load_space(config)
    space.check_size(MAX_SAMPLES, "the benchmark's limit")
    grid = possible(scanner_for(space), space.grid())
    if samples <= nodes * batch:
        raise FalsifyError(f"--samples: {samples} must be more than the first chunk of each "
                           f"node ({nodes} x {batch}), which warms it up")
    if samples > len(grid):
        raise FalsifyError(f"--samples: {samples} is more than the {len(grid)} samples of "
                           f"{config}")
    picked = grid[:samples]
    ray = import_ray()
    from ray._private import services
    from ray.cluster_utils import Cluster

    settings = EvalSettings(space=space, model=model, backend=backend_for(model, "onnx"),
                            threads=1,
                            warm_backgrounds=tuple(sorted({s.background for s in picked})))
    # Ray dials a node by the machine's interface address even for a loopback cluster; where
    # only loopback is open (sandboxes, CI) that never answers, so keep loopback throughout.
    dial = services.node_ip_address_from_perspective
    services.node_ip_address_from_perspective = lambda *a, **k: "127.0.0.1"
    rates = []
    try:
        with tempfile.TemporaryDirectory() as tmp:
            for n in range(1, nodes + 1):
                if on_progress is not None:
                    on_progress(f"bench nodes: {n} node(s), {samples} samples")
                t_start = time.perf_counter()
                cluster = Cluster(initialize_head=True, head_node_args={
                    "num_cpus": 0, "include_dashboard": False, "node_ip_address": "127.0.0.1"})
                try:
                    for _ in range(n):
                        cluster.add_node(num_cpus=1, node_ip_address="127.0.0.1")
                    cluster.wait_for_nodes()
                    ray.init(address=cluster.address, _node_ip_address="127.0.0.1",
                             log_to_driver=False, logging_level="ERROR")
                    store = Store(Path(tmp) / f"nodes-{n}.sqlite", space)
                    with Driver(settings, store, workers=n, batch=batch,
                                progress=Progress(None), executor="ray",
                                address=cluster.address) as driver:
                        driver.evaluate(picked[:n * batch])     # actors warm, streets built
                        t0 = time.perf_counter()
                        driver.evaluate(picked[n * batch:])
                        t1 = time.perf_counter()
                    store.close()
                finally:
                    ray.shutdown()
                    cluster.shutdown()
                rates.append(NodeRate(n, len(picked) - n * batch, t1 - t0, t0 - t_start))
    finally:
        services.node_ip_address_from_perspective = dial
    return NodesBench(str(config), batch, machine(), tuple(rates))
