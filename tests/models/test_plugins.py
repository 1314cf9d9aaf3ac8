"""Python plug-ins (module:factory), points-in models, devices and SemanticKITTI class names in
model specs."""

from __future__ import annotations

import json
import re
import sqlite3
import textwrap
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from falsify.cli import main
from falsify.errors import FalsifyError
from falsify.models.plausible import plausible_scans
from falsify.models.plugin import is_plugin
from falsify.models.runners import BUNDLED_ONNX, PluginSegmenter, load_segmenter
from falsify.models.spec import SPEC_CLASSES, four_class_of, load_spec, spec_path_for, train_id_of
from falsify.results.metrics import class_scores, confusion
from falsify.results.replay import row_sample
from falsify.results.samples import sample_seed
from falsify.semantic import TRAIN_CLASSES
from falsify.sensor.lidar import load_sensor
from falsify.sensor.simulator import Simulator
from falsify.world.space import load_space

torch = pytest.importorskip("torch")

ROOT = Path(__file__).resolve().parents[2]
SMOKE = ROOT / "configs" / "smoke.toml"
POINTNET = "falsify.models.pointnet:factory"
NO_CUDA = "needs a CUDA GPU (torch.cuda.is_available() is False here)"

# A points plug-in in plain numpy: car by height above the road, road below, else unknown; its
# outputs are SemanticKITTI names (unknown, car, road), its answers (N, 3) float logits.
RULES = '''
import numpy as np

SPEC = {"name": "rules", "input_kind": "points", "num_classes": 3,
        "classes": {"unknown": 0, "car": 1, "road": 2}}


class Rules:
    spec = SPEC

    def __init__(self, device):
        self.device = device
        self.calls = []

    def predict(self, batch):
        self.calls.append(len(batch))
        out = []
        for p in batch:
            z = p[:, 2]
            car = 1.0 - np.abs(z + 1.0) * 2.0 - np.abs(p[:, 1]) / 8.0
            road = -(z + 1.6) * 10.0
            out.append(np.stack([np.zeros_like(z), car, road], axis=1).astype(np.float32))
        return out


def factory(device="cpu"):
    return Rules(device)
'''


@pytest.fixture
def rules(tmp_path: Path) -> Path:
    path = tmp_path / "plug" / "rules.py"
    path.parent.mkdir()
    path.write_text(RULES)
    return path


def _scans(space, samples) -> list[np.ndarray]:
    """The samples' scans as a run casts them (the sample's own seed)."""
    sim = Simulator(load_sensor(space.sensor), space.user_cars)
    return [sim.scan(s, rng=np.random.default_rng(sample_seed(space, s))).image
            for s in samples]


def _rows(run: Path) -> pd.DataFrame:
    with sqlite3.connect(run / "results.sqlite") as db:
        return pd.read_sql_query("SELECT * FROM samples ORDER BY eval_index", db)


def _meta(run: Path) -> dict:
    with sqlite3.connect(run / "results.sqlite") as db:
        return {k: json.loads(v) for k, v in db.execute("SELECT key, value FROM run")}


def test_a_file_plugin_runs_a_grid_and_its_rows_equal_direct_calls(rules, tmp_path,
                                                                  monkeypatch):
    monkeypatch.chdir(ROOT)
    ref = f"{rules}:factory"
    run = tmp_path / "run"
    assert main(["grid", "configs/smoke.toml", "--model", ref, "--out", str(run), "--workers",
                 "2", "--quiet", "--no-report"]) == 0
    meta = _meta(run)
    assert meta["backend"] == "python" and meta["model_path"] == ref
    assert meta["model_hash"] == load_segmenter(ref).model_hash
    assert "device" not in meta["sessions"][0]        # the CPU: nothing new stored

    space = load_space(SMOKE)
    rows = _rows(run)
    assert len(rows) == len(space.grid())
    samples = [row_sample(space, row) for _, row in rows.iterrows()]
    assert sorted(map(str, samples)) == sorted(map(str, space.grid()))
    assert rows["seed"].tolist() == [sample_seed(space, s) for s in samples]
    scans = _scans(space, samples)
    mod: dict = {}
    exec(compile(RULES, str(rules), "exec"), mod)
    plugin = mod["factory"]()
    for scan, (_, row) in zip(scans, rows.iterrows(), strict=True):
        valid = scan[..., 4] > 0
        points = np.ascontiguousarray(scan[valid][:, :4], np.float32)
        (logits,) = plugin.predict([points])
        pred = np.zeros(valid.shape, np.uint8)
        pred[valid] = np.where(logits.argmax(1) == 1, 1, 0)   # car; road and unknown: ours 0
        label = scan[..., 5].astype(np.uint8)
        car = class_scores(confusion(pred, label, 4))[1]
        assert car.iou is not None and car.tp > 0          # the rule finds the car
        assert row["car_iou"] == pytest.approx(car.iou, abs=1e-12)
        assert (row["car_tp"], row["car_fp"], row["car_fn"]) == (car.tp, car.fp, car.fn)
        assert row["car_points"] == int((pred == 1).sum())


def test_plugin_predictions_fold_semantickitti_names_and_keep_train_ids(rules):
    seg = load_segmenter(f"{rules}:factory")
    assert isinstance(seg, PluginSegmenter) and seg.spec.input_kind == "points"
    scans = plausible_scans(2, seed=3)
    pred = seg.predict(scans)
    valid = scans[..., 4] > 0
    assert pred.classes.shape == pred.train_ids.shape == scans.shape[:3]
    assert set(np.unique(pred.train_ids)) <= {0, 1, 9}       # unlabeled, car, road
    assert ((pred.train_ids == 1) == (pred.classes == 1)).all()
    assert (pred.train_ids[~valid] == 0).all() and (pred.classes[~valid] == 0).all()
    assert (pred.train_ids[valid] == 9).any()              # road: a train class, not ours
    np.testing.assert_allclose(pred.probabilities.sum(-1), 1.0, atol=1e-5)
    assert seg.plugin.calls == [2]                          # one call for the batch


def test_plugin_hash_covers_source_factory_and_files(rules, tmp_path, monkeypatch):
    ref = f"{rules}:factory"
    first = load_segmenter(ref).model_hash
    assert load_segmenter(ref).model_hash == first and len(first) == 64
    monkeypatch.chdir(rules.parent)
    assert load_segmenter("rules.py:factory").model_hash == first   # paths are not hashed
    weights = tmp_path / "w.bin"
    weights.write_bytes(b"1")
    rules.write_text(RULES + f"\nFILES = [{str(weights)!r}]\n\ndef with_files(device='cpu'):\n"
                     "    r = Rules(device)\n    r.files = FILES\n    return r\n")
    edited = load_segmenter(ref).model_hash
    assert edited != first                                           # the source
    a = load_segmenter(f"{rules}:with_files").model_hash
    assert a != edited                                               # the factory name
    weights.write_bytes(b"2")
    assert load_segmenter(f"{rules}:with_files").model_hash != a     # the weights' bytes


def test_a_range_plugin_gets_scans_without_labels(tmp_path):
    (tmp_path / "ranged.py").write_text(textwrap.dedent('''
        import numpy as np

        class Ranged:
            spec = {"name": "ranged", "height": 64, "width": 512, "output_kind": "logits",
                    "num_classes": 2, "classes": {"unknown": 0, "car": 1}}
            seen = []

            def predict(self, batch):
                self.seen.extend(batch)
                return np.stack([(s[..., 4] > 20).astype(np.int64) for s in batch])

        def make():
            return Ranged()
    '''))
    seg = load_segmenter(f"{tmp_path / 'ranged.py'}:make")
    scans = plausible_scans(2, seed=4)
    scans[..., 5] = 1
    pred = seg.predict(scans)
    assert [s.shape for s in seg.plugin.seen] == [(64, 512, 6)] * 2
    assert all((s[..., 5] == 0).all() for s in seg.plugin.seen)     # the label is hidden
    want = (scans[..., 4] > 20).astype(np.uint8)
    assert (pred.classes == want).all() and (pred.train_ids == want).all()
    with pytest.raises(FalsifyError, match="takes no 'device' keyword"):
        load_segmenter(f"{tmp_path / 'ranged.py'}:make", device="cuda")


@pytest.mark.parametrize("text, match", [
    ("def factory():\n    return 3\n", "lacks a `spec` or a `predict"),
    ("def factory():\n    raise ValueError('no')\n", "the factory failed: ValueError: no"),
    ("import no_such_module_here\n", "loading .* failed: ModuleNotFoundError"),
    ("class P:\n    spec = {'name': 'p', 'input_kind': 'points', 'num_classes': 2,\n"
     "            'classes': {'lorry': 1}}\n    def predict(self, b):\n        return b\n"
     "def factory():\n    return P()\n", "unknown class 'lorry'; allowed"),
])
def test_bad_plugins_are_clear_errors(tmp_path, text, match):
    (tmp_path / "bad.py").write_text(text)
    with pytest.raises(FalsifyError, match=match):
        load_segmenter(f"{tmp_path / 'bad.py'}:factory")


def test_bad_plugin_answers_are_clear_errors(tmp_path):
    (tmp_path / "short.py").write_text(
        "import numpy as np\n"
        "class P:\n    spec = {'name': 'p', 'input_kind': 'points', 'num_classes': 2,\n"
        "            'classes': {'car': 1}}\n"
        "    def predict(self, b):\n        return [np.zeros(3, np.int64) for _ in b]\n"
        "def factory():\n    return P()\n")
    seg = load_segmenter(f"{tmp_path / 'short.py'}:factory")
    with pytest.raises(FalsifyError, match=r"classes of shape \(3,\) for a scan, expected"):
        seg.predict(plausible_scans(1))


@pytest.mark.parametrize("answer, match", [
    ("np.full((len(p), 2), np.nan, np.float32)", "NaN or inf scores"),
    ("np.array(['car'] * len(p))", r"dtype <U3; allowed: integer output indices or float"),
    ("1 / 0", "predict failed: ZeroDivisionError"),
])
def test_plugin_answers_that_cannot_be_scored_are_exit_2(tmp_path, capsys, answer, match):
    """NaN scores, text answers and a predict that raises: one line naming the plug-in, exit 2,
    no run folder left (before: NaN scored as IoU 0, a raise a traceback)."""
    (tmp_path / "odd.py").write_text(
        "import numpy as np\n"
        "class P:\n    spec = {'name': 'p', 'input_kind': 'points', 'num_classes': 2,\n"
        "            'classes': {'car': 1}}\n"
        f"    def predict(self, b):\n        return [{answer} for p in b]\n"
        "def factory():\n    return P()\n")
    out = tmp_path / "run"
    assert main(["grid", str(SMOKE), "--out", str(out), "--model",
                 f"{tmp_path / 'odd.py'}:factory", "--quiet", "--no-report"]) == 2
    err = capsys.readouterr().err
    assert re.search(match, err) and "odd.py:factory" in err and "Traceback" not in err
    assert not out.exists()


@pytest.mark.parametrize("command", [["grid"], ["search", "--algorithm", "random",
                                                  "--budget", "2"]])
def test_a_backend_a_plugin_cannot_run_on_is_refused(rules, tmp_path, capsys, command):
    """grid and search --backend torch with a plug-in: refused as predict refuses it (before:
    silently run on python)."""
    out = tmp_path / "run"
    assert main([*command[:1], str(SMOKE), *command[1:], "--out", str(out), "--model",
                 f"{rules}:factory", "--backend", "torch", "--quiet"]) == 2
    assert "--backend torch: the plug-in model" in capsys.readouterr().err
    assert not out.exists()


def test_model_strings_name_plugins(tmp_path, monkeypatch):
    assert is_plugin("falsify.models.pointnet:factory")
    assert is_plugin("nets/mine.py:build") and is_plugin(r"C:\nets\mine.py:build")
    assert not is_plugin(r"C:\models\net.onnx") and not is_plugin("C:/models/net.onnx")
    assert not is_plugin("squeezeseg-drive") and not is_plugin(None)
    monkeypatch.chdir(tmp_path)
    Path("odd:name.onnx").write_bytes(b"")
    assert not is_plugin("odd:name.onnx")                            # an existing file
    with pytest.raises(FalsifyError, match="plug-in file nope.py not found"):
        load_segmenter("nope.py:factory")
    with pytest.raises(FalsifyError, match="cannot import no_such_pkg"):
        load_segmenter("no_such_pkg.mod:factory")
    with pytest.raises(FalsifyError, match="backend 'python' runs a plug-in"):
        load_segmenter(BUNDLED_ONNX, backend="python")


def test_pointnet_runs_through_load_segmenter(tmp_path):
    from falsify.models.pointnet import PointNetSeg, build, factory

    seg = load_segmenter(POINTNET, threads=1)
    assert isinstance(seg, PluginSegmenter)
    assert seg.spec.input_kind == "points" and seg.spec.num_classes == len(TRAIN_CLASSES)
    assert set(seg.spec.classes) == set(TRAIN_CLASSES[1:])
    scans = plausible_scans(2, seed=5)
    pred = seg.predict(scans)
    assert pred.classes.shape == pred.train_ids.shape == (2, 64, 512)
    assert pred.train_ids.max() < len(TRAIN_CLASSES)
    assert (pred.train_ids[scans[..., 4] <= 0] == 0).all()
    again = load_segmenter(POINTNET)
    assert again.model_hash == seg.model_hash
    assert (again.predict(scans).train_ids == pred.train_ids).all()   # seeded
    # a weights file loads, and the hash covers it
    other = PointNetSeg()
    torch.save(other.state_dict(), tmp_path / "pn.pt")
    loaded = factory(tmp_path / "pn.pt")
    assert loaded.files == (str(tmp_path / "pn.pt"),)
    x = torch.rand(1, 50, 4)
    with torch.no_grad():
        assert torch.equal(loaded.model(x), other.eval()(x))
        assert not torch.equal(loaded.model(x), build()(x))
    (tmp_path / "trained.py").write_text(
        "from falsify.models.pointnet import factory as pointnet\n"
        f"def factory(device='cpu'):\n    return pointnet({str(tmp_path / 'pn.pt')!r}, device)\n")
    assert load_segmenter(f"{tmp_path / 'trained.py'}:factory").model_hash != seg.model_hash
    (tmp_path / "bad.pt").write_bytes(b"not weights")
    with pytest.raises(FalsifyError, match="cannot load PointNet weights"):
        factory(tmp_path / "bad.pt")


def test_points_onnx_equals_the_torch_plugin(tmp_path):
    from falsify.models.pointnet import export_onnx, factory

    path, _ = export_onnx(factory().model, tmp_path / "pointnet.onnx")
    spec = load_spec(spec_path_for(path))
    assert spec.input_kind == "points" and spec.height == 0
    onnx = load_segmenter(path)
    plugin = load_segmenter(POINTNET)
    space = load_space(SMOKE)
    scans = np.stack(_scans(space, space.grid()[:3]))
    a, b = onnx.run_raw(scans), plugin.run_raw(scans)
    assert a.shape == (3, len(TRAIN_CLASSES), 64, 512)
    np.testing.assert_allclose(a, b, atol=1e-4)
    pa, pb = onnx.predict(scans), plugin.predict(scans)
    assert (pa.classes == pb.classes).all() and (pa.train_ids == pb.train_ids).all()
    # the graph is checked against its spec at load
    d = json.loads(spec_path_for(path).read_text())
    d["num_classes"] = 25
    spec_path_for(path).write_text(json.dumps(d))
    with pytest.raises(FalsifyError, match=r"expected \(1, N, 25\)"):
        load_segmenter(path)
    d["input_kind"] = "range"
    spec_path_for(path).write_text(json.dumps(d))
    with pytest.raises(FalsifyError, match="key 'height' must be > 0"):
        load_segmenter(path)


def test_the_bundled_model_predicts_train_ids_of_its_classes():
    seg = load_segmenter()
    pred = seg.predict(plausible_scans(2, seed=6))
    assert (pred.train_ids == np.array([0, 1, 6, 7], np.uint8)[pred.classes]).all()


# -- spec class names ----------------------------------------------------------------------------
def _spec_file(tmp_path: Path, **changes) -> Path:
    d = json.loads(spec_path_for(BUNDLED_ONNX).read_text())
    d.update(changes)
    p = tmp_path / "m.json"
    p.write_text(json.dumps(d))
    return p


def test_specs_take_semantickitti_names(tmp_path):
    spec = load_spec(_spec_file(tmp_path, classes={"unknown": 0, "car": 1, "person": 2,
                                                   "bicyclist": 3}))
    assert spec.four_class_outputs() == [[0], [1], [2], [3]]
    assert spec.train_id_table().tolist() == [0, 1, 6, 7]
    spec = load_spec(_spec_file(tmp_path, classes={"road": 0, "truck": 1, "motorcyclist": 2,
                                                   "traffic-sign": 3}))
    assert spec.four_class_outputs() == [[0, 1, 3], [], [], [2]]   # motorcyclists: cyclists
    assert spec.train_id_table().tolist() == [9, 4, 8, 19]
    assert [four_class_of(n) for n in ("pedestrian", "person", "cyclist", "bicycle")] == [
        2, 2, 3, 0]
    assert train_id_of("pedestrian") == train_id_of("person") == 6
    assert SPEC_CLASSES[:4] == ("unknown", "car", "pedestrian", "cyclist")
    assert set(SPEC_CLASSES[4:]) == set(TRAIN_CLASSES[1:]) - {"car"}


@pytest.mark.parametrize("classes, match", [
    ({"car": 1, "lorry": 2}, r"unknown class 'lorry'; allowed \['unknown', 'car', "
                             r"'pedestrian', 'cyclist', 'bicycle'.*'traffic-sign'\]"),
    ({"unlabeled": 0, "car": 1}, "unknown class 'unlabeled'"),
    ({"unknown": 0}, "at least one class besides 'unknown'"),
    ({}, "at least one class besides 'unknown'"),
    ({"car": 1, "person": 1}, "one output index to two classes"),
])
def test_bad_class_names_are_refused_with_the_allowed_ones(tmp_path, classes, match):
    with pytest.raises(FalsifyError, match=f"m.json: key 'classes' .*{match}"):
        load_spec(_spec_file(tmp_path, classes=classes))


def test_a_spec_without_car_loads(tmp_path):
    spec = load_spec(_spec_file(tmp_path, classes={"unknown": 0, "road": 1}))
    assert spec.four_class_outputs() == [[0, 1], [], [], []]


def test_existing_specs_load_unchanged():
    """Every shipped spec reads back to its own bytes: no input_kind is written for range
    models, so their files and model hashes stay as they were."""
    specs = sorted((ROOT / "models" / "weights").glob("*.json"))
    assert len(specs) >= 2   # the default and its int8 copy at least
    for p in specs:
        spec = load_spec(p)
        assert spec.input_kind == "range"
        assert spec.to_json() == p.read_text(), p.name
        assert "input_kind" not in p.read_text()


def test_points_specs_check_their_kind(tmp_path):
    base = {"name": "p", "input_kind": "points", "num_classes": 2, "classes": {"car": 1}}
    p = tmp_path / "p.json"
    p.write_text(json.dumps(base))
    spec = load_spec(p)
    assert spec.channels == ("x", "y", "z", "intensity") and spec.mean == (0.0,) * 4
    assert json.loads(spec.to_json())["input_kind"] == "points"
    for changes, key in (({"input_kind": "voxels"}, "input_kind"),
                         ({"channels": ["x", "y", "z", "range"]}, "channels"),
                         ({"height": -1}, "height")):
        p.write_text(json.dumps({**base, **changes}))
        with pytest.raises(FalsifyError, match=f"p.json: key '{key}'"):
            load_spec(p)


# -- devices -------------------------------------------------------------------------------------
def _has_cuda_provider() -> bool:
    import onnxruntime as ort
    return "CUDAExecutionProvider" in ort.get_available_providers()


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has CUDA: no error to see")
@pytest.mark.parametrize("extra, match", [
    ([], "pip install onnxruntime-gpu"),
    (["--backend", "torch"], r"torch.cuda.is_available\(\) is False"),
    (["--model", POINTNET], r"torch.cuda.is_available\(\) is False"),
])
def test_device_cuda_without_cuda_is_a_clear_error(tmp_path, capsys, monkeypatch, extra, match):
    if not extra and _has_cuda_provider():
        pytest.skip("onnxruntime here has the CUDAExecutionProvider")
    monkeypatch.chdir(ROOT)
    out = tmp_path / "run"
    assert main(["grid", "configs/smoke.toml", "--out", str(out), "--device", "cuda",
                 "--quiet", *extra]) == 2
    err = capsys.readouterr().err
    assert "--device cuda" in err and len(err.strip().splitlines()) == 1
    assert re.search(match, err)
    assert not out.exists()


def test_an_unknown_device_is_refused(capsys):
    with pytest.raises(FalsifyError, match="--device 'tpu'; allowed: cpu, cuda"):
        load_segmenter(device="tpu")
    with pytest.raises(SystemExit) as exc:
        main(["grid", "configs/smoke.toml", "--out", "x", "--device", "tpu"])
    assert exc.value.code == 2 and "--device" in capsys.readouterr().err


def test_predict_and_report_take_plugins_and_devices(tmp_path, monkeypatch, capsys):
    scans = plausible_scans(2, seed=9)
    for i, s in enumerate(scans):
        np.save(tmp_path / f"{i:06d}.npy", s)
    out = tmp_path / "pred"
    assert main(["predict", str(tmp_path / "000000.npy"), str(tmp_path / "000001.npy"),
                 "--model", POINTNET, "--device", "cpu", "--out", str(out), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["backend"] == "python"
    want = load_segmenter(POINTNET).predict(scans).classes
    assert (np.load(out / "000000.pred.npy") == want[0]).all()
    monkeypatch.chdir(ROOT)
    run = tmp_path / "run"
    assert main(["grid", "configs/smoke.toml", "--model", POINTNET, "--out", str(run),
                 "--quiet", "--no-report"]) == 0
    assert main(["report", str(run), "--device", "cpu", "--out", str(tmp_path / "r.html"),
                 "--json"]) == 0
    assert "Model not loaded" not in (tmp_path / "r.html").read_text()


# -- on a CUDA GPU (skipped here; run on a machine with one) -------------------------------------
@pytest.mark.skipif(not torch.cuda.is_available(), reason=NO_CUDA)
def test_a_cuda_run_equals_the_cpu_run(tmp_path, monkeypatch):
    monkeypatch.chdir(ROOT)
    runs = {}
    for device in ("cpu", "cuda"):
        runs[device] = tmp_path / device
        assert main(["grid", "configs/smoke.toml", "--model", POINTNET, "--device", device,
                     "--out", str(runs[device]), "--quiet", "--no-report"]) == 0
    assert _meta(runs["cuda"])["sessions"][0]["device"] == "cuda"
    assert _meta(runs["cuda"])["model_hash"] == _meta(runs["cpu"])["model_hash"]
    cpu, cuda = _rows(runs["cpu"]), _rows(runs["cuda"])
    assert len(cpu) == len(cuda) == 8
    assert (cpu["status"] == cuda["status"]).all()
    np.testing.assert_allclose(cuda["car_iou"].astype(float), cpu["car_iou"].astype(float),
                               atol=0.01)
    np.testing.assert_allclose(cuda["car_points"], cpu["car_points"], rtol=0.01, atol=5)
    # the logits themselves, on the same scans
    space = load_space(SMOKE)
    scans = np.stack(_scans(space, space.grid()[:2]))
    a = load_segmenter(POINTNET, device="cpu").run_raw(scans)
    b = load_segmenter(POINTNET, device="cuda").run_raw(scans)
    np.testing.assert_allclose(b, a, atol=1e-3, rtol=1e-3)


@pytest.mark.skipif(not torch.cuda.is_available(), reason=NO_CUDA)
def test_the_torch_backend_on_cuda_equals_the_cpu():
    scans = plausible_scans(2, seed=10)
    a = load_segmenter(backend="torch").run_raw(scans)
    b = load_segmenter(backend="torch", device="cuda").run_raw(scans)
    np.testing.assert_allclose(b, a, atol=1e-3, rtol=1e-3)


@pytest.mark.skipif(not torch.cuda.is_available(), reason=NO_CUDA)
def test_onnx_without_its_gpu_provider_points_to_the_torch_backend(tmp_path, capsys,
                                                                  monkeypatch):
    """A PyTorch GPU machine often has the CPU build of onnxruntime: the error says that torch
    runs the bundled network there, and `--backend torch` does."""
    if _has_cuda_provider():
        pytest.skip("onnxruntime here has the CUDAExecutionProvider: no error to see")
    monkeypatch.chdir(ROOT)
    out = tmp_path / "run"
    assert main(["grid", "configs/smoke.toml", "--out", str(out), "--device", "cuda",
                 "--quiet"]) == 2
    assert "--backend torch for a model with its .pt" in capsys.readouterr().err
    assert not out.exists()
    assert main(["grid", "configs/smoke.toml", "--out", str(out), "--device", "cuda",
                 "--backend", "torch", "--quiet", "--no-report"]) == 0


@pytest.mark.skipif(not torch.cuda.is_available(), reason=NO_CUDA)
def test_onnx_on_cuda_equals_the_cpu(tmp_path):
    if not _has_cuda_provider():
        pytest.skip("onnxruntime here has no CUDAExecutionProvider (pip install "
                    "onnxruntime-gpu)")
    from falsify.models.pointnet import export_onnx, factory

    scans = plausible_scans(2, seed=11)
    a = load_segmenter(device="cpu").run_raw(scans)
    b = load_segmenter(device="cuda").run_raw(scans)
    np.testing.assert_allclose(b, a, atol=1e-3, rtol=1e-3)
    path, _ = export_onnx(factory().model, tmp_path / "pointnet.onnx")
    np.testing.assert_allclose(load_segmenter(path, device="cuda").run_raw(scans),
                               load_segmenter(path).run_raw(scans), atol=1e-3, rtol=1e-3)


def test_ray_ships_no_model_for_a_plugin_and_names_its_file_absolutely(rules, monkeypatch):
    from falsify.executors.evaluator import EvalSettings
    from falsify.executors.ray import Shipment

    monkeypatch.chdir(rules.parent)
    shipment = Shipment.of(EvalSettings(space=load_space(SMOKE), model="rules.py:factory",
                                        backend="python"))
    assert shipment.model is None and shipment.spec is None
    local = shipment.local_settings()
    assert local.model == f"{rules}:factory" and local.backend == "python"
    assert shipment.driver_names("boom") == "boom"
