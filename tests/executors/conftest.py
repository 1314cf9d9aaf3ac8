"""The local Ray instance the Ray executor's tests share within a module."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="module")
def ray():
    ray = pytest.importorskip("ray", reason='ray is not installed (pip install "falsify[ray]")')
    # "local": a Ray instance of its own, never a cluster running on the machine (another
    # module's, or a user's), which ray.init would join and refuse num_cpus for
    ray.init(address="local", num_cpus=2, include_dashboard=False, _node_ip_address="127.0.0.1",
             log_to_driver=False, logging_level="ERROR")
    yield ray
    ray.shutdown()
