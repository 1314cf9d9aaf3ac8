"""Shared fixtures: repo paths, the real KITTI data folder (skipped with a message if absent) and a
headless Chromium with the check that a page it loaded made no network request."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
CONFIGS = ROOT / "configs"
# The project's real test data: ../shared/data/kitti beside the checkout, or FALSIFY_TEST_KITTI.
KITTI = Path(os.environ.get("FALSIFY_TEST_KITTI", ROOT.parent / "shared" / "data" / "kitti"))
KITTI_DIR = KITTI
MINI = KITTI / "semantickitti-mini"
# semantickitti-mini's split (its README), the project's and not the product's: evaluation
# sequences are only reported on; HOLDOUT holds them (and squeezeseg/, semantickitti/) out by
# content, and every test and subprocess sees it through FALSIFY_HOLDOUT.
EVALUATION_SEQUENCES = ("00", "03", "06", "08")
FIT_SEQUENCES = ("01", "02", "04", "05", "07", "09", "10")
HOLDOUT = ROOT / "tests" / "data" / "kitti-holdout.toml"
os.environ.setdefault("FALSIFY_HOLDOUT", str(HOLDOUT))
if MINI.is_dir():   # what configs/paper-real.toml reads
    os.environ.setdefault("SEMANTICKITTI", str(MINI))


# Modules that start a Ray instance: a bare `ray.init()` joins the newest cluster started on the
# machine (Ray's docs), so under pytest-xdist they run in one worker, one after the other.
RAY_MODULES = ("tests/executors/test_ray.py", "tests/executors/test_ray_cluster.py")
# A child script's first lines: torch cannot be imported, as on a machine without it.
NO_TORCH = ("import importlib.abc, sys\n"
            "class NoTorch(importlib.abc.MetaPathFinder):\n"
            "    def find_spec(self, name, path=None, target=None):\n"
            "        if name.split('.')[0] == 'torch':\n"
            "            raise ImportError(\"No module named 'torch'\")\n"
            "sys.meta_path.insert(0, NoTorch())\n")


@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Under `--dist loadgroup`, a module's tests share one worker (its module fixtures are built
    once) and the Ray modules share one between them."""
    for item in items:
        if item.get_closest_marker("xdist_group") is None:
            module = item.nodeid.split("::", 1)[0]
            group = "ray" if module in RAY_MODULES else module
            item.add_marker(pytest.mark.xdist_group(group))


@pytest.fixture
def kitti_dir() -> Path:
    if not (KITTI / "squeezeseg").is_dir():
        pytest.skip(f"real KITTI scans not found at {KITTI} (shared/data/ is beside the repo)")
    return KITTI


def one_car_config(tmp_path: Path, background: str) -> Path:
    """A config of one sedan at (0, 8) m over the `[dims.background]` table's lines given."""
    cfg = tmp_path / "c.toml"
    cfg.write_text('name = "c"\nsensor = "kitti-hdl64e-front"\n[dims.car_model]\nvalues = '
                   '["sedan"]\n[dims.x]\nvalues = [0.0]\n[dims.y]\nvalues = [8.0]\n'
                   '[dims.background]\n' + background)
    return cfg


CHROMIUM = Path("/usr/bin/chromium")
CHROMEDRIVER = Path("/usr/bin/chromedriver")


@pytest.fixture
def browser(tmp_path: Path):
    """Headless Chromium logging its network and console (skipped when it is not installed)."""
    if not CHROMIUM.exists() or not CHROMEDRIVER.exists():
        pytest.skip(f"headless browser test needs {CHROMIUM} and {CHROMEDRIVER}")
    webdriver = pytest.importorskip("selenium.webdriver")
    from selenium.webdriver.chrome.service import Service

    opts = webdriver.ChromeOptions()
    opts.binary_location = str(CHROMIUM)
    for arg in ("--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
                "--no-first-run", "--disable-component-update", "--disable-sync",
                f"--user-data-dir={tmp_path / 'profile'}", "--window-size=1300,1000"):
        opts.add_argument(arg)
    opts.set_capability("goog:loggingPrefs", {"performance": "ALL", "browser": "ALL"})
    driver = webdriver.Chrome(options=opts, service=Service(str(CHROMEDRIVER)))
    try:
        yield driver
    finally:
        driver.quit()


def assert_offline(browser) -> None:
    """The loaded page fetched nothing but data: URIs and its own file, and logged no error."""
    resources = browser.execute_script(
        "return performance.getEntriesByType('resource').map(e => e.name)")
    assert all(r.startswith("data:") for r in resources), resources
    requested = []
    for entry in browser.get_log("performance"):
        msg = json.loads(entry["message"])["message"]
        if msg.get("method") == "Network.requestWillBeSent":
            requested.append(msg["params"]["request"]["url"])
    assert any(u.startswith("file:") for u in requested)     # the log works: it saw the page
    assert not [u for u in requested if u.startswith(("http:", "https:", "ws:", "wss:"))]
    errors = [e for e in browser.get_log("browser") if e["level"] == "SEVERE"]
    assert not errors, errors


class Scorer:
    """An evaluate callback: scores with `fn`, keeps every sample and each batch's size."""

    def __init__(self, fn=lambda s: 0.5):
        self.fn = fn
        self.samples: list = []
        self.batches: list[int] = []

    def __call__(self, batch):
        self.batches.append(len(batch))
        self.samples.extend(batch)
        return [self.fn(s) for s in batch]

    @property
    def scores(self) -> list:
        return [self.fn(s) for s in self.samples]


def scored(fn):
    """An evaluate callback scoring each sample with `fn`, and the batch sizes it was called
    with (what a sampler test reads)."""
    calls: list[int] = []

    def evaluate(batch):
        calls.append(len(batch))
        return [fn(s) for s in batch]
    return evaluate, calls
