"""Runners: ONNX Runtime vs torch parity, spec checks, input checks, hashing, no-torch import."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from falsify.errors import FalsifyError
from falsify.models.plausible import plausible_scans
from falsify.models.runners import (
    BUNDLED_ONNX,
    WEIGHTS_DIR,
    load_segmenter,
    resolve_model,
    to_prediction,
)
from falsify.models.spec import load_spec, model_hash, spec_path_for
from tests.conftest import KITTI_DIR

KITTI = KITTI_DIR / "squeezeseg"
ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    """A seeded random SqueezeSeg with a 3-iteration CRF, exported to .onnx + .pt + .json."""
    torch = pytest.importorskip("torch")
    from falsify.models.export import export_onnx
    from falsify.models.squeezeseg import SqueezeSeg

    torch.manual_seed(1234)
    model = SqueezeSeg(crf_iterations=3).eval()
    d = tmp_path_factory.mktemp("model")
    onnx_path, _ = export_onnx(model, d / "seg.onnx")
    torch.save(model.state_dict(), d / "seg.pt")
    return onnx_path


def _kitti_scans() -> np.ndarray:
    files = sorted(KITTI.glob("*.npy"))
    if not files:
        pytest.skip(f"real KITTI scans not found in {KITTI} (shared data folder absent)")
    return np.stack([np.load(f) for f in files])


def _parity(onnx_path: Path, scans: np.ndarray) -> None:
    ort_seg = load_segmenter(onnx_path, "onnx", threads=2)
    torch_seg = load_segmenter(onnx_path.with_suffix(".pt"), "torch", threads=2)
    a, b = ort_seg.run_raw(scans), torch_seg.run_raw(scans)
    assert np.abs(a - b).max() < 1e-4
    assert (a.argmax(1) == b.argmax(1)).mean() >= 0.9999
    valid = scans[..., 4] > 0
    pa, pb = to_prediction(a, ort_seg.spec, valid), to_prediction(b, torch_seg.spec, valid)
    assert pa.classes.dtype == np.uint8 and pa.classes.shape == scans.shape[:3]
    assert pa.probabilities.shape == (*scans.shape[:3], 4)
    assert (pa.classes == pb.classes).mean() >= 0.9999
    assert (pa.classes[scans[..., 4] <= 0] == 0).all()  # invalid pixels are always unknown
    np.testing.assert_allclose(pa.probabilities.sum(-1), 1.0, atol=1e-5)


def test_parity_on_real_kitti(exported):
    _parity(exported, _kitti_scans())


def test_parity_on_synthetic_scan(exported):
    _parity(exported, plausible_scans(2, seed=7))


def test_single_scan_and_hash(exported):
    seg = load_segmenter(exported)
    p = seg.predict(plausible_scans(1, seed=1)[0])
    assert p.classes.shape == (1, 64, 512)
    assert seg.model_hash == model_hash(exported) and len(seg.model_hash) == 64
    assert seg.spec.crf_iterations == 3 and seg.spec.xyz_input == "xyz"


def test_export_is_deterministic(exported, tmp_path):
    import torch

    from falsify.models.export import export_onnx
    from falsify.models.squeezeseg import SqueezeSeg

    model = SqueezeSeg(crf_iterations=3)
    model.load_state_dict(torch.load(exported.with_suffix(".pt"), weights_only=True))
    again, _ = export_onnx(model, tmp_path / "seg.onnx")
    assert again.read_bytes() == exported.read_bytes()
    assert model_hash(again) == model_hash(exported)


def test_nan_and_shape_errors(exported):
    seg = load_segmenter(exported)
    scan = plausible_scans(1, seed=2)
    scan[0, 10, 20, 0] = np.nan
    with pytest.raises(FalsifyError, match="NaN"):
        seg.predict(scan)
    scan[0, 10, 20, 0] = np.inf
    with pytest.raises(FalsifyError, match="NaN or inf"):
        seg.predict(scan)
    with pytest.raises(FalsifyError, match="seg.onnx expects scans of shape"):
        seg.predict(np.zeros((1, 32, 512, 6), np.float32))


@pytest.mark.parametrize("backend", ["onnx", "torch"])
def test_a_network_answering_nan_is_refused_not_scored(tmp_path, backend):
    """A network whose scores are NaN is an error naming it: argmax read NaN as class 0 and the
    scan was scored as if the network had answered."""
    torch = pytest.importorskip("torch")
    from falsify.models.export import export_onnx
    from falsify.models.squeezeseg import SqueezeSeg

    torch.manual_seed(1234)
    model = SqueezeSeg(crf_iterations=0).eval()
    with torch.no_grad():
        model.conv14.conv.bias.fill_(float("nan"))   # the last layer: every score NaN
    onnx_path, _ = export_onnx(model, tmp_path / "nan.onnx")
    torch.save(model.state_dict(), tmp_path / "nan.pt")
    seg = load_segmenter(onnx_path, backend=backend)
    with pytest.raises(FalsifyError, match=r"nan\.(onnx|pt).*NaN or inf scores on [\d,]+ valid"):
        seg.predict(plausible_scans(1, seed=2))


def test_missing_and_corrupt_files(exported, tmp_path):
    with pytest.raises(FalsifyError, match="nope.onnx not found"):
        load_segmenter(tmp_path / "nope.onnx")
    bad = tmp_path / "bad.onnx"
    bad.write_bytes(b"not an onnx file")
    spec_path_for(bad).write_text(spec_path_for(exported).read_text())
    with pytest.raises(FalsifyError, match="bad.onnx"):
        load_segmenter(bad)
    lone = tmp_path / "lone.onnx"
    lone.write_bytes(exported.read_bytes())
    with pytest.raises(FalsifyError, match="lone.json not found"):
        load_segmenter(lone)
    with pytest.raises(FalsifyError, match="backend"):
        load_segmenter(exported, backend="tf")


def test_torch_without_a_pt_beside_the_onnx_says_where_it_looked(exported, tmp_path):
    """--backend torch with net.onnx reads net.pt: its absence names both files."""
    lone = tmp_path / "lone.onnx"
    lone.write_bytes(exported.read_bytes())
    spec_path_for(lone).write_text(spec_path_for(exported).read_text())
    with pytest.raises(FalsifyError, match=r"reads the state dict beside .*lone\.onnx: "
                       r".*lone\.pt not found"):
        load_segmenter(lone, backend="torch")


def test_torch_weights_that_do_not_fit_the_spec_are_one_line(exported, tmp_path):
    """--backend torch with a .pt of another class count, or not a state dict: one line naming
    the file, the spec's classes and torch's first complaint (before: torch's whole listing, or
    its advice to load untrusted pickles)."""
    pytest.importorskip("torch")
    d = json.loads(spec_path_for(exported).read_text())
    d.update(num_classes=20, classes={"car": 1}, crf_iterations=0, xyz_input=None,
             mask_input=None)
    net = tmp_path / "net.onnx"
    net.write_bytes(exported.read_bytes())
    spec_path_for(net).write_text(json.dumps(d))
    net.with_suffix(".pt").write_bytes(exported.with_suffix(".pt").read_bytes())   # 4 classes
    with pytest.raises(FalsifyError) as exc:
        load_segmenter(net, backend="torch")
    msg = str(exc.value)
    assert "\n" not in msg and "net.pt into the SqueezeSeg" in msg and "20 classes" in msg
    assert "size mismatch for conv14" in msg and "more)" in msg
    net.with_suffix(".pt").write_bytes(b"not a state dict")
    with pytest.raises(FalsifyError) as exc:
        load_segmenter(net, backend="torch")
    assert "\n" not in str(exc.value) and "not a state dict" in str(exc.value)
    assert "weights_only` set to `False`" not in str(exc.value)


def _with_spec(exported: Path, tmp_path: Path, **changes) -> Path:
    d = json.loads(spec_path_for(exported).read_text())
    d.update(changes)
    p = tmp_path / "m.onnx"
    p.write_bytes(exported.read_bytes())
    spec_path_for(p).write_text(json.dumps(d))
    return p


@pytest.mark.parametrize("changes, match", [
    ({"height": 32}, "height"),
    ({"width": 1024}, "width"),
    ({"num_classes": 5}, "4 classes, spec says 5"),
    ({"input_name": "points"}, "inputs"),
    ({"output_name": "prob"}, "output 'prob'"),
    ({"xyz_input": None, "mask_input": None}, "inputs"),
    ({"channels": ["x", "y", "z", "intensity", "range", "mask"],
      "mean": [0.0] * 6, "std": [1.0] * 6}, "5 channels, spec says 6"),
])
def test_spec_mismatch_is_caught_at_load(exported, tmp_path, changes, match):
    p = _with_spec(exported, tmp_path, **changes)
    with pytest.raises(FalsifyError, match=match) as e:
        load_segmenter(p)
    assert "m.onnx" in str(e.value)


@pytest.mark.parametrize("changes, key", [
    ({"channels": ["x", "q"]}, "channels"),
    ({"mean": [0.0]}, "mean"),
    ({"output_kind": "scores"}, "output_kind"),
    ({"classes": {"car": 9}}, "classes"),
    ({"height": "64"}, "height"),
    ({"layout": "NHWC"}, "layout"),
])
def test_invalid_spec_names_file_and_key(exported, tmp_path, changes, key):
    p = _with_spec(exported, tmp_path, **changes)
    with pytest.raises(FalsifyError, match=f"m.json: key '{key}'"):
        load_spec(spec_path_for(p))
    d = json.loads(spec_path_for(exported).read_text())
    del d["output_name"]
    spec_path_for(p).write_text(json.dumps(d))
    with pytest.raises(FalsifyError, match="m.json: missing key 'output_name'"):
        load_spec(spec_path_for(p))


def test_a_misspelt_spec_key_is_named_with_the_allowed_ones(exported, tmp_path):
    """num_class for num_classes, or a key of the user's own outside 'extra', is an error."""
    p = _with_spec(exported, tmp_path, colour="x")
    with pytest.raises(FalsifyError, match="m.json: unknown key 'colour'; allowed: .*num_classes"):
        load_spec(spec_path_for(p))
    load_spec(spec_path_for(_with_spec(exported, tmp_path, extra={"colour": "x"})))


def test_class_mapping_folds_outputs(exported, tmp_path):
    # a model whose output 0 is car and 1 unknown reads back with the classes swapped
    p = _with_spec(exported, tmp_path, classes={"unknown": 1, "car": 0, "pedestrian": 2,
                                                "cyclist": 3})
    a = load_segmenter(exported).predict(plausible_scans(1, seed=3))
    b = load_segmenter(p).predict(plausible_scans(1, seed=3))
    np.testing.assert_allclose(a.probabilities[..., 2:], b.probabilities[..., 2:])
    valid = plausible_scans(1, seed=3)[..., 4] > 0
    np.testing.assert_allclose(a.probabilities[..., 0][valid], b.probabilities[..., 1][valid])


def test_network_batch_size_does_not_change_predictions(exported):
    from falsify.models.runners import OnnxSegmenter

    scans = plausible_scans(5, seed=8)
    one = OnnxSegmenter(exported, threads=1, batch=1).run_raw(scans)
    three = OnnxSegmenter(exported, threads=1, batch=3).run_raw(scans)
    np.testing.assert_allclose(one, three, atol=1e-5)


def test_classes_from_logits_equal_classes_from_probabilities(exported, tmp_path):
    # one output per class: argmax of the raw logits; several outputs per class (here car and
    # cyclist folded into car): argmax of the summed probabilities. Both match the probabilities.
    scans = plausible_scans(2, seed=4)
    valid = scans[..., 4] > 0
    for spec_path in (spec_path_for(exported), spec_path_for(_with_spec(
            exported, tmp_path, classes={"unknown": 0, "car": [1, 3], "pedestrian": 2}))):
        spec = load_spec(spec_path)
        raw = load_segmenter(exported).run_raw(scans)
        pred = to_prediction(raw, spec, valid)
        assert (pred.classes == pred.probabilities.argmax(-1)).mean() > 0.9999
        assert (pred.classes[~valid] == 0).all()


def test_runner_imports_and_runs_without_torch(exported):
    code = (
        "import sys; sys.modules['torch'] = None\n"
        "import numpy as np\n"
        "from falsify.models.runners import load_segmenter\n"
        "from falsify.models.plausible import plausible_scans\n"
        f"seg = load_segmenter({str(exported)!r}, threads=1)\n"
        "p = seg.predict(plausible_scans(1))\n"
        "assert 'torch' not in sys.modules or sys.modules['torch'] is None\n"
        "print(p.classes.shape, seg.model_hash[:12])\n"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT,
                       timeout=120)
    assert r.returncode == 0, r.stderr
    assert "(1, 64, 512)" in r.stdout


def test_export_cli_writes_model_and_int8_copy(exported, tmp_path, capsys):
    pytest.importorskip("torch")
    from falsify.cli import main

    def export_main(argv):
        return main(["export", *argv])

    out, q = tmp_path / "net.onnx", tmp_path / "int8" / "net-int8.onnx"   # folder made
    assert export_main([str(exported.with_suffix(".pt")), "--out", str(out), "--int8", str(q),
                        "--calibration-scans", "2", "--note", "data=test"]) == 0
    written = json.loads(capsys.readouterr().out)
    assert written["int8"] == str(q) and load_spec(spec_path_for(q)).extra == {"data": "test"}
    scans = plausible_scans(1, seed=2)
    a, b = load_segmenter(out).predict(scans), load_segmenter(q).predict(scans)
    assert (a.classes == b.classes).mean() > 0.9


def test_export_cli_rejects_bad_input_before_writing(exported, tmp_path, capsys):
    torch = pytest.importorskip("torch")
    from falsify.cli import main

    def export_main(argv):
        return main(["export", *argv])

    out = tmp_path / "net.onnx"
    args = [str(exported.with_suffix(".pt")), "--out", str(out)]
    assert export_main([*args, "--int8", str(tmp_path / "q.onnx"), "--height", "32"]) == 2
    assert "64 x 512 only" in capsys.readouterr().err
    assert export_main([*args, "--note", "epochs"]) == 2
    assert "--note 'epochs': write KEY=VALUE" in capsys.readouterr().err
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"not a checkpoint")
    assert export_main([str(bad), "--out", str(out)]) == 2
    assert "cannot load weights" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exc:   # argparse: exit 2, naming the option
        export_main([*args, "--int8", str(tmp_path / "q.onnx"), "--calibration-scans", "0"])
    assert exc.value.code == 2
    assert "--calibration-scans: 0: allowed 1..1024" in capsys.readouterr().err
    assert not out.exists() and not (tmp_path / "q.onnx").exists()
    tensor = tmp_path / "tensor.pt"
    torch.save(torch.zeros(3), tensor)
    assert export_main([str(tensor), "--out", str(out)]) == 2
    assert "not a state dict" in capsys.readouterr().err
    assert sorted(tmp_path.iterdir()) == [bad, tensor]


def test_a_bundled_model_can_be_named(tmp_path, monkeypatch):
    """`--model squeezeseg-drive` means models/weights/squeezeseg-drive.onnx for every command
    (grid, search, predict, retrain and the Ray executor resolve through one function)."""
    from falsify.cli import main

    drive = WEIGHTS_DIR / "squeezeseg-drive.onnx"
    assert resolve_model("squeezeseg-drive") == drive
    assert resolve_model("squeezeseg-drive", "torch") == drive.with_suffix(".pt")
    assert resolve_model(None) == BUNDLED_ONNX
    for name in ("squeezeseg-drive", "squeezeseg-drive-retrained"):   # every shipped drive net
        spec = load_segmenter(name).spec
        assert spec.name == name and spec.crf_iterations == 3, name
    assert load_segmenter("squeezeseg-drive").model_hash == load_segmenter(drive).model_hash
    with pytest.raises(FalsifyError, match="no-such-model: no such file, and not a bundled "
                       "network; bundled: squeezeseg, squeezeseg-drive"):
        load_segmenter("no-such-model")
    with pytest.raises(FalsifyError, match="a plug-in; run it as --model "
                       "falsify.models.pointnet:reference"):
        load_segmenter("pointnet20")
    monkeypatch.chdir(ROOT)
    out = tmp_path / "run"
    assert main(["grid", "configs/smoke.toml", "--model", "squeezeseg-drive", "--out", str(out),
                 "--quiet"]) == 0
    run = json.loads((out / "summary.json").read_text())
    assert run["model_hash"] == load_segmenter(drive).model_hash


def test_flushing_subnormals_leaves_the_bundled_outputs_unchanged(tmp_path):
    """The runners' sessions flush subnormals to zero (a speed matter on Intel cores); on the
    bundled network that changes no output bit. Both run in fresh processes: this one may
    have opened its first session, which sets the flags, on another test's thread."""
    import subprocess
    import sys


    scans = plausible_scans(2, seed=5)
    np.save(tmp_path / "scans.npy", scans)
    code = (
        "import numpy as np, onnxruntime as ort\n"
        "from falsify.models.runners import feeds, BUNDLED_ONNX\n"
        "from falsify.models.spec import load_spec, spec_path_for\n"
        "spec = load_spec(spec_path_for(BUNDLED_ONNX))\n"
        "s = ort.InferenceSession(str(BUNDLED_ONNX), providers=['CPUExecutionProvider'])\n"
        f"x = np.load({str(tmp_path / 'scans.npy')!r})\n"
        "out = np.concatenate([s.run(None, feeds(spec, x[i:i + 1]))[0] for i in range(2)])\n"
        f"np.save({str(tmp_path / 'plain.npy')!r}, out)\n")
    subprocess.run([sys.executable, "-c", code], check=True)
    # ours in a fresh process too: ONNX Runtime sets the flags on the thread that opens the
    # process's first session, which in this one may have been another test's worker thread
    mine = (
        "import numpy as np\n"
        "from falsify.models.runners import BUNDLED_ONNX, feeds, load_segmenter\n"
        "seg = load_segmenter(BUNDLED_ONNX)\n"
        f"x = np.load({str(tmp_path / 'scans.npy')!r})\n"
        "out = np.concatenate([seg.session.run(None, feeds(seg.spec, x[i:i + 1]))[0]\n"
        "                      for i in range(2)])\n"
        f"np.save({str(tmp_path / 'ours.npy')!r}, out)\n"
        "print(np.float32(1e-39) * np.float32(1.0) == 0.0)\n")   # the flags on in its thread
    done = subprocess.run([sys.executable, "-c", mine], check=True, capture_output=True,
                          text=True)
    assert done.stdout.split() == ["True"]
    assert np.array_equal(np.load(tmp_path / "ours.npy"), np.load(tmp_path / "plain.npy"))
