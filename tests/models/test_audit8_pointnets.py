"""Point and voxel networks brought as Python plug-ins: what `falsify predict --score points`
feeds them on real SemanticKITTI scans, how their answers come back, and the --device cuda error
of a plug-in that asks torch for a GPU."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from falsify.cli import main
from falsify.data.scansets import load_sets, pixel_classes, point_rows
from falsify.data.velodyne import kitti_rows, read_kitti, read_kitti_points
from falsify.semantic import train_ids
from falsify.sensor.lidar import load_sensor
from falsify.sensor.scan import point_pixels
from tests.conftest import FIT_SEQUENCES, MINI

SENSOR = "semantickitti-hdl64e"   # 360 degrees: every point of a scan has a pixel

# A points plug-in: road (train id 9) below z = -1.2 m, building (13) above, from each point's
# own height; it saves every batch it is fed under SAVE.
RECORDER = '''
import numpy as np

NAMES = ["car", "bicycle", "motorcycle", "truck", "other-vehicle", "person", "bicyclist",
         "motorcyclist", "road", "parking", "sidewalk", "other-ground", "building", "fence",
         "vegetation", "trunk", "terrain", "pole", "traffic-sign"]
SAVE = {save!r}


class Recorder:
    spec = {{"name": "recorder", "input_kind": "points", "num_classes": 20,
             "classes": {{n: i + 1 for i, n in enumerate(NAMES)}}}}

    def __init__(self):
        self.calls = 0

    def predict(self, batch):
        for k, p in enumerate(batch):
            np.save(f"{{SAVE}}/{{self.calls:03d}}-{{k:03d}}.npy", p)
        self.calls += 1
        return [np.where(p[:, 2] < -1.2, 9, 13).astype(np.int64) for p in batch]


def factory():
    return Recorder()
'''


def _rule(z: np.ndarray) -> np.ndarray:
    return np.where(z < -1.2, 9, 13)


@pytest.fixture
def fit_sequence() -> Path:
    seq = next((MINI / "sequences" / s for s in FIT_SEQUENCES
                if (MINI / "sequences" / s / "velodyne").is_dir()), None)
    if seq is None:
        pytest.skip(f"SemanticKITTI mini fit scans not found under {MINI}")
    return seq


def test_score_points_feeds_a_points_plugin_every_point_and_scores_its_own_answer(
        fit_sequence, tmp_path, capsys):
    """Before: the plug-in got one point per range-image pixel (about 100,000 of a scan's
    127,000) and each of the other points was scored with the answer of the nearer point that
    won its pixel."""
    save = tmp_path / "fed"
    save.mkdir()
    plugin = tmp_path / "recorder.py"
    plugin.write_text(RECORDER.format(save=str(save)))
    out = tmp_path / "out"
    assert main(["predict", str(fit_sequence), "--sensor", SENSOR, "--score", "points",
                 "--model", f"{plugin}:factory", "--out", str(out), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    fed = [np.load(f) for f in sorted(save.glob("*.npy"))]
    sensor = load_sensor(SENSOR)
    bins = sorted((fit_sequence / "velodyne").glob("*.bin"))
    assert len(fed) == len(bins)
    tp = fp = fn = 0
    for got, b in zip(fed, bins, strict=True):
        label = fit_sequence / "labels" / f"{b.stem}.label"
        r = read_kitti_points(b, label)
        inside = point_pixels(sensor, r.xyz, kitti_rows(sensor, r.xyz))[2]
        assert inside.all()                                  # the whole scan, in the file's order
        want = np.column_stack([r.xyz, r.remission]).astype(np.float32)
        assert got.dtype == np.float32 and np.array_equal(got, want)
        lab = train_ids(r.semantic)
        pred = _rule(r.xyz[:, 2])
        scored = lab != 0
        tp += int(((pred == 9) & (lab == 9))[scored].sum())
        fp += int(((pred == 9) & (lab != 9))[scored].sum())
        fn += int(((pred != 9) & (lab == 9))[scored].sum())
        # the picture's classes: each pixel the answer of the point it holds
        image = read_kitti(b, label, sensor).image
        on_pixels = np.where(image[..., 4] > 0, _rule(image[..., 2]), 0)
        assert np.array_equal(np.load(out / f"{b.stem}.pred.npy"), on_pixels)
    road = summary["pooled"]["road"]
    assert (road["tp"], road["fp"], road["fn"]) == (tp, fp, fn)
    assert summary["points_outside_image"] == 0


def test_point_rows_keep_each_scan_apart_and_pixels_hold_their_nearest_point(fit_sequence):
    """Scans of different lengths padded into one array: each row holds exactly its scan's
    points, and `pixel_classes` puts back on each pixel the point the range image kept."""
    s = load_sets([str(fit_sequence)], load_sensor("kitti-hdl64e-front"), points=True)[0]
    rows = point_rows(s)
    counts = [len(p.pixel) for p in s.points]
    assert len(set(counts)) > 1 and rows.images.shape == (len(s), 1, max(counts), 6)
    for k, p in enumerate(s.points):
        valid = rows.images[k, 0, :, 4] > 0
        assert int(valid.sum()) == counts[k] and valid[:counts[k]].all()
        assert np.array_equal(rows.images[k, 0, :counts[k], :4], p.xyzi)
        assert np.array_equal(rows.points[k].pixel, np.arange(counts[k]))
        held = pixel_classes(p, np.arange(counts[k]), s.images.shape[1:3])
        image = s.images[k]
        on = image[..., 4] > 0
        assert np.array_equal(p.xyzi[held[on], :3], image[on, :3])   # the same point
        assert np.array_equal(p.range[held[on]], image[on, 4])


CUDA_PLUGIN = '''
import numpy as np
import torch


class P:
    spec = {{"name": "p", "input_kind": "points", "num_classes": 2, "classes": {{"car": 1}}}}

    def __init__(self, device):
        self.device = device
        {factory_line}

    def predict(self, batch):
        return [torch.zeros(len(p), dtype=torch.long, device=self.device) for p in batch]


def factory(device="cpu"):
    return P(device)
'''


@pytest.mark.parametrize("factory_line, where", [
    ("torch.zeros(1, device=device)", "the factory failed"),
    ("pass", "predict failed"),
])
def test_a_plugin_asking_torch_for_cuda_without_one_says_so(tmp_path, capsys, factory_line,
                                                            where):
    """Before: `AssertionError: Torch not compiled with CUDA enabled`, nothing on the cause."""
    torch = pytest.importorskip("torch")
    if torch.cuda.is_available():
        pytest.skip("a CUDA GPU is present: nothing to refuse")
    plugin = tmp_path / "gpu.py"
    plugin.write_text(CUDA_PLUGIN.format(factory_line=factory_line))
    out = tmp_path / "run"
    assert main(["grid", str(Path(__file__).resolve().parents[2] / "configs" / "smoke.toml"),
                 "--model", f"{plugin}:factory", "--device", "cuda", "--out", str(out),
                 "--quiet", "--no-report"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "gpu.py:factory" in err and where in err
    assert "finds no CUDA GPU; run with --device cpu" in err
    assert not out.exists()
