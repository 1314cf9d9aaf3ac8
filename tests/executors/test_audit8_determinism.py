"""Same config, seed and model give the same bytes on any machine: the network's logits must not
depend on how many cores the machine has or how many workers share the inference process.

ONNX Runtime sums SqueezeSeg's CRF messages one way up to 4 intra-op threads and another from 5
on (last-bit differences in the logits), so sessions not told a thread count, and the shared
inference process of many workers, stay at 4 or fewer.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from falsify.executors.evaluator import EvalSettings, Evaluator
from falsify.executors.inference import server_threads
from falsify.models.runners import (
    BUNDLED_ONNX,
    MAX_DEFAULT_THREADS,
    OnnxSegmenter,
    default_threads,
)
from falsify.world.space import load_space

ROOT = Path(__file__).resolve().parents[2]
SMOKE = ROOT / "configs" / "smoke.toml"   # 2 x 2 positions on 2 streets


@pytest.fixture(scope="module")
def scans() -> np.ndarray:
    """The smoke grid's scans, as a grid run casts them."""
    space = load_space(SMOKE)
    ev = Evaluator(EvalSettings(space=space, threads=1))
    return np.stack([ev.scan(s).image for s in space.grid()]).astype(np.float32)


def test_shared_inference_of_many_workers_computes_a_workers_logits(scans):
    """--workers 8 --inference shared on the CPU: the inference process's network gives the
    logits a worker's 1-thread network gives (8 threads changed some in their last bits)."""
    settings = EvalSettings(space=load_space(SMOKE), threads=1)
    threads = server_threads(settings, 8)
    one = OnnxSegmenter(BUNDLED_ONNX, threads=1).run_raw(scans)
    shared = OnnxSegmenter(BUNDLED_ONNX, threads=threads).run_raw(scans)
    assert shared.tobytes() == one.tobytes()
    assert 1 <= threads <= MAX_DEFAULT_THREADS
    assert server_threads(settings, 2) == 2   # a few workers keep a thread each


def test_a_session_not_told_its_threads_takes_a_bounded_count_not_every_core(scans):
    """`falsify predict` and the report open the network without a thread count: it runs on
    the usable cores up to MAX_DEFAULT_THREADS, set on the session (ONNX Runtime's own default
    is every core, whose logits differ on machines of 5 or more), and scores as 1 thread does."""
    seg = OnnxSegmenter(BUNDLED_ONNX, threads=None)
    opts = seg.session.get_session_options()
    assert opts.intra_op_num_threads == default_threads()
    assert 1 <= default_threads() <= MAX_DEFAULT_THREADS
    assert seg.run_raw(scans).tobytes() == OnnxSegmenter(BUNDLED_ONNX, threads=1).run_raw(
        scans).tobytes()


ONE_VAN = """name = "one"
sensor = "kitti-hdl64e-front"
[dims.car_model]
values = ["van"]
[dims.x]
values = [-6.0]
[dims.y]
values = [6.0]
[dims.yaw]
values = [45.0]
[dims.background]
values = [0]
"""


def test_torch_rows_do_not_depend_on_workers(tmp_path: Path) -> None:
    """torch's oneDNN convolutions sum in another order on 1 and 2 threads: with a worker's
    threads set by --workers, this van's scan had a pixel flip between unknown and pedestrian
    (pedestrian IoU 0.0877 on 1 worker, 0.0875 on 2, on a 2-core AVX-512 EPYC)."""
    pytest.importorskip("torch")
    import pandas as pd

    from falsify.cli import main
    from falsify.jobs.run import inference_threads

    assert {inference_threads(b, "cpu", w) for b in ("torch", "python") for w in (1, 2, 8)} == {1}
    config = tmp_path / "one.toml"
    config.write_text(ONE_VAN)
    rows = []
    for workers in (1, 2):
        out = tmp_path / f"w{workers}"
        assert main(["grid", str(config), "--backend", "torch", "--workers", str(workers),
                     "--out", str(out), "--quiet", "--no-report"]) == 0
        frame = pd.read_csv(out / "results.csv")
        rows.append(frame[[c for c in frame.columns if not c.startswith("t_")]])
    pd.testing.assert_frame_equal(rows[0], rows[1])
