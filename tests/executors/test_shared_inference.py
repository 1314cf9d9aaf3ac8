"""--inference shared: CPU workers cast scans and one inference process runs the network for all
of them; the rows equal those of the network in each worker, a failing network is a clear
error, and no process outlives the run. The GPU path's tests skip without CUDA."""

from __future__ import annotations

import multiprocessing as mp
import sys
import textwrap
from pathlib import Path

import pytest

from falsify.cli import main
from falsify.errors import FalsifyError
from falsify.jobs.run import RunRequest, execute
from falsify.results.store import TIMING_COLUMNS, read_frame

ROOT = Path(__file__).resolve().parents[2]
SMALL = ROOT / "tests" / "data" / "small-grid.toml"   # 24 samples on 2 streets


def _rows(run: Path):
    return read_frame(run).drop(columns=list(TIMING_COLUMNS))


def _cuda() -> bool:
    try:
        import torch
    except ImportError:
        return False
    return bool(torch.cuda.is_available())


NO_CUDA = "needs a CUDA GPU (torch is missing or torch.cuda.is_available() is False here)"


def test_shared_inference_gives_the_rows_of_inference_in_each_worker(tmp_path):
    runs = {}
    for mode in ("worker", "shared"):
        runs[mode] = tmp_path / mode
        execute(RunRequest(config=SMALL, out=runs[mode], command="grid", workers=2,
                           report=False, inference=mode))
    assert _rows(runs["shared"]).equals(_rows(runs["worker"]))
    assert not [p for p in mp.active_children() if p.name == "falsify-inference"]


def test_a_network_that_fails_in_the_inference_process_is_named(tmp_path):
    plugin = tmp_path / "broken.py"
    plugin.write_text(textwrap.dedent('''
        class Broken:
            spec = {"name": "broken", "height": 64, "width": 512, "output_kind": "logits",
                    "num_classes": 2, "classes": {"unknown": 0, "car": 1}}

            def predict(self, batch):
                raise ValueError("out of device memory")

        def make():
            return Broken()
    '''))
    with pytest.raises(FalsifyError, match="inference process failed: .*out of device memory"):
        execute(RunRequest(config=SMALL, out=tmp_path / "run", command="grid", workers=2,
                           report=False, inference="shared", model=f"{plugin}:make",
                           backend="python"))
    assert not [p for p in mp.active_children() if p.name == "falsify-inference"]


@pytest.mark.parametrize("ray_hidden", [False, True])
def test_shared_inference_is_refused_on_ray(tmp_path, capsys, monkeypatch, ray_hidden):
    """The two options conflict whether or not ray is installed, and that is what is said."""
    if ray_hidden:
        monkeypatch.setitem(sys.modules, "ray", None)   # `import ray` fails, as without it
    code = main(["grid", str(SMALL), "--out", str(tmp_path / "r"), "--workers", "2",
                 "--executor", "ray", "--inference", "shared", "--quiet"])
    assert code == 2 and "--inference shared" in capsys.readouterr().err
    assert not (tmp_path / "r" / "results.sqlite").exists()


@pytest.mark.skipif(not _cuda(), reason=NO_CUDA)
def test_the_network_on_the_gpu_gives_the_same_rows_twice(tmp_path):
    runs = []
    for k in range(2):
        out = tmp_path / f"gpu{k}"
        execute(RunRequest(config=SMALL, out=out, command="grid", workers=2, report=False,
                           device="cuda", backend="torch"))
        runs.append(_rows(out))
    assert runs[0].equals(runs[1])


@pytest.mark.skipif(not _cuda(), reason=NO_CUDA)
def test_bench_pipeline_on_the_gpu_reports_both_ceilings():
    """On torch: a PyTorch GPU machine's onnxruntime is often the CPU build."""
    from falsify.bench.shared import bench_shared
    r = bench_shared(ROOT / "configs" / "bench.toml", samples=48, device="cuda",
                     backend="torch")
    assert r["backend"] == "torch"
    assert r["e2e_samples_per_s"] > 0 and r["network_alone_frames_per_s"] > 0
    assert r["e2e_over_lower_ceiling"] > 0
