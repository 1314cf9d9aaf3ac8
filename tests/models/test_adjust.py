"""Logit adjustment: the offsets are folded into conv14 exactly, alpha is chosen by car IoU on
validation scans, and bad input exits 2 with nothing written."""

from __future__ import annotations

import json

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from falsify.cli import main as falsify_main  # noqa: E402
from falsify.models.adjust import adjust_state, choose_alpha, logit_offsets  # noqa: E402
from falsify.models.spec import DEFAULT_CHANNELS  # noqa: E402
from falsify.models.squeezeseg import SqueezeSeg  # noqa: E402
from falsify.models.train import CLASS_WEIGHTS, batch_tensors  # noqa: E402
from tests.models.conftest import write_crops  # noqa: E402


@pytest.fixture(scope="module")
def val(tmp_path_factory):
    return write_crops(tmp_path_factory.mktemp("val"), 3, seed=5, name="{i:06d}.npy")


@pytest.fixture(scope="module")
def state():
    torch.manual_seed(0)
    return SqueezeSeg(DEFAULT_CHANNELS, crf_iterations=1).state_dict()


def main(argv: list[str]) -> int:
    """`falsify adjust ARGV`."""
    return falsify_main(["adjust", *argv])


def _model(state, crf=1):
    m = SqueezeSeg(DEFAULT_CHANNELS, crf_iterations=crf)
    m.load_state_dict(state)
    return m.eval()


def test_offsets_are_minus_alpha_log_weight_ratio():
    assert np.all(logit_offsets(0.0) == 0)
    w = np.asarray(CLASS_WEIGHTS)
    np.testing.assert_allclose(logit_offsets(0.75), -0.75 * np.log(w / w[0]))
    assert logit_offsets(1.0)[0] == 0 and logit_offsets(1.0)[1] == pytest.approx(-np.log(15))


def test_adjusted_weights_shift_the_logits_by_the_offsets_and_nothing_else(val, state):
    scans = np.stack([np.load(p) for p in sorted(val.glob("*.npy"))])
    x, _, _, _ = batch_tensors(scans, DEFAULT_CHANNELS)
    adjusted = adjust_state(state, 0.6)
    assert adjusted.keys() == state.keys()
    assert all(torch.equal(adjusted[k], state[k]) for k in state if k != "conv14.conv.bias")
    with torch.inference_mode():
        before = _model(state).backbone(x)
        after = _model(adjusted).backbone(x)
    off = torch.tensor(logit_offsets(0.6), dtype=before.dtype).view(1, -1, 1, 1)
    torch.testing.assert_close(after, before + off, rtol=0, atol=1e-5)


def test_choose_alpha_scores_like_the_full_model_and_picks_the_best(val, state):
    res = choose_alpha(state, val, [0.5, 0.0, 0.5, 1.0], crf_iterations=1)
    assert [s.alpha for s in res.scores] == [0.0, 0.5, 1.0] and res.scans == 3
    best = max(s.car_iou for s in res.scores)
    chosen = next(s for s in res.scores if s.alpha == res.chosen)
    assert chosen.car_iou == best
    assert all(s.alpha >= res.chosen for s in res.scores if s.car_iou == best)
    # alpha 0 equals the plain model with its CRF, scored by hand
    scans = np.stack([np.load(p) for p in sorted(val.glob("*.npy"))])
    x, xyz, mask, labels = batch_tensors(scans, DEFAULT_CHANNELS)
    with torch.inference_mode():
        pred = _model(state)(x, xyz, mask).argmax(1).numpy()
    pred[scans[..., 4] <= 0] = 0
    lab = labels.numpy()
    tp, fp, fn = [int(v.sum()) for v in ((pred == 1) & (lab == 1), (pred == 1) & (lab != 1),
                                         (pred != 1) & (lab == 1))]
    assert res.scores[0].car_iou == pytest.approx(tp / (tp + fp + fn))


def test_cli_writes_the_chosen_adjustment(val, state, tmp_path, capsys):
    src, out = tmp_path / "w.pt", tmp_path / "adj.pt"
    torch.save(SqueezeSeg(DEFAULT_CHANNELS).state_dict(), src)
    assert main([str(src), "--val", str(val), "--out", str(out), "--alphas", "0,1",
                 "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    got = torch.load(out, weights_only=True)
    base = torch.load(src, weights_only=True)
    off = torch.tensor(logit_offsets(res["chosen"]), dtype=torch.float32)
    torch.testing.assert_close(got["conv14.conv.bias"], base["conv14.conv.bias"] + off)


@pytest.mark.parametrize("args,needle", [
    (["--alphas", "a,b"], "--alphas"),
    (["--alphas", "3"], "--alphas"),
    (["--out-name", "x.onnx"], "--out"),
    (["--val-empty"], "no *.npy scans"),
    (["--weights-bad"], "cannot load weights"),
    (["--val-no-car"], "no car points"),
    (["--val-semantickitti-index"], "semantickitti labels"),
    (["--val-semantickitti-ids"], "label id 19"),
])
def test_bad_input_exits_2_naming_it_and_writes_nothing(val, tmp_path, capsys, args, needle):
    src = tmp_path / "w.pt"
    torch.save(SqueezeSeg(DEFAULT_CHANNELS).state_dict(), src)
    out = tmp_path / "adj.pt"
    v = val
    if args == ["--out-name", "x.onnx"]:
        out, args = tmp_path / "x.onnx", []
    elif args == ["--val-empty"]:
        v, args = tmp_path / "empty", []
        v.mkdir()
    elif args == ["--weights-bad"]:
        src.write_bytes(b"not weights")
        args = []
    elif args == ["--val-no-car"]:
        v, args = tmp_path / "nocar", []
        v.mkdir()
        scan = np.load(next(val.glob("*.npy")))
        scan[..., 5] = np.where(scan[..., 5] == 1, 0, scan[..., 5])
        np.save(v / "000000.npy", scan)
    elif args in (["--val-semantickitti-index"], ["--val-semantickitti-ids"]):
        v = tmp_path / "sk"
        v.mkdir()
        scan = np.load(next(val.glob("*.npy")))
        scan[..., 5] = np.where(scan[..., 5] == 1, 19, scan[..., 5])   # SemanticKITTI's ids
        np.save(v / "000000.npy", scan)
        if args == ["--val-semantickitti-index"]:
            (v / "index.json").write_text(json.dumps({"scans": 1, "labels": "semantickitti"}))
        args = []
    assert main([str(src), "--val", str(v), "--out", str(out), *args]) == 2
    assert needle in capsys.readouterr().err
    assert not out.exists()


@pytest.mark.parametrize("args, needle", [
    (["--height", "0"], "--height"),
    (["--width", "-3"], "--width"),
    (["--out-name", "m"], "must end in .onnx"),
    (["--out-name", "afile"], "must end in .onnx"),
])
def test_export_bad_input_exits_2_and_writes_nothing(tmp_path, capsys, args, needle):
    src = tmp_path / "w.pt"
    torch.save(SqueezeSeg(DEFAULT_CHANNELS).state_dict(), src)
    (tmp_path / "afile").write_text("mine\n")
    out = tmp_path / "d" / "m.onnx"
    if args[0] == "--out-name":
        out, args = tmp_path / args[1], []
    before = sorted(p.name for p in tmp_path.rglob("*"))
    assert falsify_main(["export", str(src), "--out", str(out), *args]) == 2
    err = capsys.readouterr().err
    assert needle in err and "Traceback" not in err
    assert sorted(p.name for p in tmp_path.rglob("*")) == before
    assert (tmp_path / "afile").read_text() == "mine\n"
