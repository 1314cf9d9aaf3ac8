"""A clean install: the wheel puts sampler, models, reports and configs under falsify/ (no
generic top-level package), ships the default network, sensor presets, world profiles and
bundled configs and no other network, and works from a directory outside the checkout.
Slow: it builds a wheel and a venv."""

from __future__ import annotations

import importlib.util
import json
import os
import shutil
import subprocess
import sys
import sysconfig
import venv
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
GENERIC = ("models", "reports", "sampler", "configs")
# The wheel ships the default network and its int8 variants, not the other networks (each has a
# card, shipped, that says how to make it).
LEFT_OUT = ("squeezeseg-v1", "squeezeseg-v2", "squeezeseg-v3", "squeezeseg-v4", "squeezeseg-drive",
            "squeezeseg-drive-retrained", "squeezeseg20", "pointnet20")
MAX_WHEEL_MB = 16

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("dist")
    # Built from a copy of the sources: setuptools' build/ in the checkout keeps files of earlier
    # builds (weights since left out), and a second build there at the same time collides.
    src = tmp_path_factory.mktemp("src")
    for name in ("pyproject.toml", "README.md", "LICENSE"):
        shutil.copy2(ROOT / name, src / name)
    for folder in ("falsify", *GENERIC):
        shutil.copytree(ROOT / folder, src / folder,
                        ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    r = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation",
                        "-v", "-w", str(out), str(src)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    # A deprecated pyproject key is a dated future build failure (setuptools names the date).
    assert "SetuptoolsDeprecationWarning" not in r.stdout + r.stderr, r.stdout + r.stderr
    (found,) = out.glob("falsify-*.whl")
    return found


def test_wheel_holds_only_the_falsify_package_and_its_data(wheel):
    names = zipfile.ZipFile(wheel).namelist()
    tops = {n.split("/")[0] for n in names}
    assert not tops & set(GENERIC), sorted(tops)
    assert {t for t in tops if not t.endswith(".dist-info")} == {"falsify"}
    # BSD-2-Clause asks that its text go with every binary redistribution
    assert any(n.endswith(".dist-info/licenses/LICENSE") for n in names), names
    weights = "falsify/models/weights/"
    for need in (weights + "squeezeseg.onnx", weights + "squeezeseg.json",
                 weights + "squeezeseg-int8.onnx", weights + "squeezeseg.pt",
                 "falsify/configs/sensors/kitti-hdl64e-front.toml", "falsify/configs/ci.toml",
                 "falsify/configs/paper.toml",
                 "falsify/sampler/nlopt.py", "falsify/reports/run/report.py",
                 "falsify/reports/assets/run.css", "falsify/reports/assets/run.js",
                 "falsify/configs/worlds/semantickitti-fit-parked.json",
                 "falsify/configs/worlds/semantickitti-fit.json",
                 "falsify/configs/worlds/semantickitti-places.json",
                 "falsify/models/cards/squeezeseg-drive.md"):
        assert need in names, need
    weights = {n.rsplit("/", 1)[1].split(".")[0] for n in names if n.startswith(weights)}
    assert weights == {"squeezeseg", "squeezeseg-int8", "squeezeseg-int8-crf0",
                       "squeezeseg-int8-crf1"}, sorted(weights)
    assert wheel.stat().st_size < MAX_WHEEL_MB * 2**20, wheel.stat().st_size
    # Every source module is in the wheel: a subpackage missing from pyproject's list fails here.
    sources = [f.relative_to(ROOT).as_posix() for f in (ROOT / "falsify").rglob("*.py")]
    for top in ("models", "reports", "sampler"):
        sources += [f"falsify/{f.relative_to(ROOT).as_posix()}" for f in (ROOT / top).rglob("*.py")]
    missing = sorted(n for n in sources if "__pycache__" not in n and n not in names)
    assert not missing, missing


@pytest.fixture(scope="module")
def installed(wheel, tmp_path_factory) -> Path:
    """A venv holding the wheel (its folder)."""
    env_dir = tmp_path_factory.mktemp("venv")
    # The running interpreter's packages (numpy, onnxruntime, ...) without a download: its
    # system site-packages, and, when the tests run inside a venv, that venv's site-packages by a
    # .pth line (which adds the folder but runs none of its .pth files, so the checkout's editable
    # install stays out). The wheel goes into the new venv itself, first on sys.path (checked).
    venv.EnvBuilder(system_site_packages=True, with_pip=False).create(env_dir)
    py = env_dir / "bin" / "python"
    site = site_packages(env_dir)
    parent = {sysconfig.get_paths()[k] for k in ("purelib", "platlib")}
    (site / "_falsify_test_parent.pth").write_text("".join(f"{p}\n" for p in sorted(parent)))
    r = subprocess.run([str(py), "-m", "pip", "install", "-q", "--no-deps", "--no-index",
                        "--force-reinstall", str(wheel)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    return env_dir


def site_packages(env_dir: Path) -> Path:
    return env_dir / "lib" / f"python{sys.version_info.major}.{sys.version_info.minor}" / \
        "site-packages"


def clean_env() -> dict[str, str]:
    """The environment without variables that would import falsify from elsewhere."""
    return {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME")}


def test_installed_wheel_runs_outside_the_checkout(installed, tmp_path):
    env_dir = installed
    py = env_dir / "bin" / "python"
    site = site_packages(env_dir)
    work = tmp_path / "elsewhere"
    work.mkdir()
    env = clean_env()

    def run(*args: str) -> subprocess.CompletedProcess:
        return subprocess.run([str(py), *args], cwd=work, env=env, capture_output=True,
                              text=True, timeout=600)

    where = run("-c", "import json, falsify, falsify.models, falsify.sampler, falsify.reports; "
                "print(json.dumps([m.__file__ for m in (falsify, falsify.models, "
                "falsify.sampler, falsify.reports)]))")
    assert where.returncode == 0, where.stderr
    for f in json.loads(where.stdout):
        assert Path(f).is_relative_to(site), f"{f} is not the installed wheel"
    assert not [g for g in GENERIC if (site / g).exists()]
    module = run("-m", "falsify", "--help")
    assert module.returncode == 0 and "grid" in module.stdout, module.stderr
    falsify_cmd = str(env_dir / "bin" / "falsify")
    scan = subprocess.run([falsify_cmd, "scan", "configs/smoke.toml", "--out", "scan", "--json"],
                          cwd=work, env=env, capture_output=True, text=True, timeout=600)
    assert scan.returncode == 0, scan.stderr
    assert json.loads(scan.stdout)["car_points"] > 0 and (work / "scan" / "scan.png").exists()
    # the paper's streets stand for real places: their world profile ships in the wheel (x = 0:
    # the first x, -5 m, stands in a parked bicycle beside street 0's narrow road)
    paper = subprocess.run([falsify_cmd, "scan", "configs/paper.toml", "--out", "paper",
                            "--set", "x=0", "--json"], cwd=work, env=env, capture_output=True,
                           text=True, timeout=600)
    assert paper.returncode == 0, paper.stderr
    grid = subprocess.run([falsify_cmd, "grid", "configs/ci.toml", "--out", "run", "--workers",
                           "2", "--quiet", "--json"], cwd=work, env=env, capture_output=True,
                          text=True, timeout=600)
    assert grid.returncode == 0, grid.stderr
    summary = json.loads(grid.stdout)
    assert summary["samples"] == 75 and summary["ok"] == 75, summary
    assert (work / "run" / "report.html").stat().st_size > 10_000
    assert (work / "run" / "maps" / "miou_x_y.csv").exists()
    # the world profiles ship: by their path in the checkout, and by name
    for world in ("configs/worlds/semantickitti-fit-parked.json", "semantickitti-fit"):
        data = subprocess.run([falsify_cmd, "dataset", "configs/smoke.toml", "--scans", "2",
                               "--world", world, "--out", f"data-{Path(world).stem}", "--json"],
                              cwd=work, env=env, capture_output=True, text=True, timeout=600)
        assert data.returncode == 0, data.stderr
        assert len(list((work / f"data-{Path(world).stem}").glob("*.npy"))) == 2
    # a network left out of the wheel is named, with where to get it
    left = subprocess.run([falsify_cmd, "grid", "configs/smoke.toml", "--out", "r2", "--model",
                           "squeezeseg-drive"], cwd=work, env=env, capture_output=True,
                          text=True, timeout=600)
    assert left.returncode == 2 and "--model squeezeseg-drive: not installed" in left.stderr
    assert "squeezeseg-drive.md" in left.stderr and not (work / "r2").exists()


def test_every_network_left_out_of_the_wheel_is_named_not_installed(installed, tmp_path):
    """Each bundled name the wheel leaves out, and the PointNet plug-in's own entry point (its
    weights left out too), exits 2 saying so and naming its shipped card, before any output."""
    falsify_cmd = str(installed / "bin" / "falsify")
    # the plug-in's module imports torch: without it, that is what the error says
    plugin = ("falsify.models.pointnet:reference",) if importlib.util.find_spec("torch") else ()
    for name in (*LEFT_OUT, *plugin):
        out = tmp_path / "run"
        r = subprocess.run([falsify_cmd, "grid", "smoke", "--out", str(out), "--model", name],
                           cwd=tmp_path, env=clean_env(), capture_output=True, text=True,
                           timeout=600)
        assert r.returncode == 2 and f"--model {name}: not installed" in r.stderr, (name, r.stderr)
        card = "pointnet20" if "pointnet" in name else name
        assert f"cards/{card}.md" in r.stderr and r.stderr.count("\n") == 1, r.stderr
        assert (site_packages(installed) / "falsify" / "models" / "cards" / f"{card}.md").is_file()
        assert not out.exists(), name
