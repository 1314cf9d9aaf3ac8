"""The exported graph's equivalent layers (`models.inference`) against the training layers."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from falsify.models.inference import PhaseDeconv, TapConv, for_export  # noqa: E402
from falsify.models.squeezeseg import SqueezeSeg  # noqa: E402


@pytest.mark.parametrize("shape", [(1, 64, 64, 512), (2, 5, 3, 7), (1, 3, 1, 1)])
@pytest.mark.parametrize("kernel", [(3, 3), (3, 5), (1, 1)])
def test_tap_conv_equals_the_conv(shape, kernel):
    torch.manual_seed(0)
    conv = torch.nn.Conv2d(shape[1], 4, kernel, padding=(kernel[0] // 2, kernel[1] // 2))
    x = torch.randn(*shape)
    with torch.no_grad():
        torch.testing.assert_close(TapConv(conv)(x), conv(x), atol=2e-5, rtol=1e-5)


def test_tap_conv_refuses_what_it_cannot_express():
    with pytest.raises(ValueError, match="stride-1"):
        TapConv(torch.nn.Conv2d(2, 2, 3, stride=2, padding=1))
    with pytest.raises(ValueError):
        TapConv(torch.nn.Conv2d(2, 2, 2))


@pytest.mark.parametrize("width", [1, 2, 7, 32, 256])
def test_phase_deconv_equals_the_transposed_conv(width):
    torch.manual_seed(1)
    ct = torch.nn.ConvTranspose2d(6, 6, (1, 4), stride=(1, 2), padding=(0, 1))
    x = torch.randn(2, 6, 3, width)
    with torch.no_grad():
        want = ct(x)
        got = PhaseDeconv(ct)(x)
    assert got.shape == want.shape == (2, 6, 3, 2 * width)
    torch.testing.assert_close(got, want, atol=1e-5, rtol=1e-5)
    with pytest.raises(ValueError):
        PhaseDeconv(torch.nn.ConvTranspose2d(6, 6, (1, 3), stride=(1, 2)))


def test_export_copy_equals_the_network_and_leaves_it_alone():
    torch.manual_seed(2)
    m = SqueezeSeg(crf_iterations=3).eval()
    with torch.no_grad():  # trained-like weights, not the bilinear init
        for p in m.parameters():
            p.add_(torch.randn_like(p) * 0.05)
    x = torch.randn(1, 5, 64, 512)
    xyz = torch.randn(1, 3, 64, 512) * 10
    mask = (torch.rand(1, 1, 64, 512) > 0.1).float()
    fast = for_export(m)
    with torch.no_grad():
        want, got = m(x, xyz, mask), fast(x, xyz, mask)
    torch.testing.assert_close(got, want, atol=1e-4, rtol=1e-4)
    assert np.mean((got.argmax(1) == want.argmax(1)).numpy()) == 1.0
    assert isinstance(m.conv14.conv, torch.nn.Conv2d)  # the original keeps its layers
    assert isinstance(m.fire_deconv10.deconv, torch.nn.ConvTranspose2d)


def test_int8_graph_folds_relus_and_concats_copy(tmp_path):
    """Speed guard without a timer: after ONNX Runtime's optimisation the int8 graph keeps its
    activations quantised from conv to conv; a dequantise-requantise pair after each conv
    (the ReLU left out of quantisation) cost 4 ms/frame of 29."""
    onnx = pytest.importorskip("onnx")
    ort = pytest.importorskip("onnxruntime")
    from falsify.models.export import export_onnx, quantize_int8
    from falsify.models.plausible import plausible_scans

    torch.manual_seed(3)
    m = SqueezeSeg(crf_iterations=1).eval()
    with torch.no_grad():  # distinct weights, as trained ones are (the init repeats some)
        for p in m.parameters():
            p.add_(torch.randn_like(p) * 0.05)
    path, _ = export_onnx(m, tmp_path / "m.onnx")
    q = quantize_int8(path, tmp_path / "q.onnx", scans=plausible_scans(2, seed=0))
    opts = ort.SessionOptions()
    opts.optimized_model_filepath = str(tmp_path / "opt.onnx")
    opts.log_severity_level = 3
    ort.InferenceSession(str(q), opts, providers=["CPUExecutionProvider"])
    nodes = onnx.load(str(tmp_path / "opt.onnx")).graph.node
    ops = [n.op_type for n in nodes]
    # conv1 and its skip, 8 fires x 3, 4 decoder fires x 4 (the deconv as a conv), conv14 taps
    assert ops.count("QLinearConv") == 2 + 8 * 3 + 4 * 4 + 1 and "ConvTranspose" not in ops
    quantised_by = {i: n for n in nodes if n.op_type == "QuantizeLinear" for i in n.input}
    requantised = [n.name for n in nodes if n.op_type == "DequantizeLinear"
                   and any(o in quantised_by for o in n.output)]
    assert requantised == [], requantised
    # each concat copies bytes: its inputs carry its output's scale and zero point
    consts = {i.name: onnx.numpy_helper.to_array(i) for i in
              onnx.load(str(tmp_path / "opt.onnx")).graph.initializer}
    concats = [n for n in nodes if n.op_type == "QLinearConcat"]
    assert len(concats) == 12
    for n in concats:
        out = (consts[n.input[0]], consts[n.input[1]])
        for k in range(2, len(n.input), 3):
            assert (consts[n.input[k + 1]], consts[n.input[k + 2]]) == out, n.name


def test_padding_the_input_channels_keeps_the_output(tmp_path):
    onnx = pytest.importorskip("onnx")
    ort = pytest.importorskip("onnxruntime")
    from falsify.models.export import export_onnx, pad_input_channels

    torch.manual_seed(4)
    path, spec = export_onnx(SqueezeSeg(crf_iterations=1).eval(), tmp_path / "m.onnx")
    model = onnx.load(str(path))
    assert pad_input_channels(model, spec.input_name)
    onnx.checker.check_model(model)
    convs = [n for n in model.graph.node if n.op_type == "Conv"]
    wide = {i.name: i.dims for i in model.graph.initializer}
    assert sum(wide.get(c.input[1], [0, 0])[1] == 8 for c in convs) == 2   # conv1, its skip
    rng = np.random.default_rng(0)
    feeds = {spec.input_name: rng.normal(size=(1, 5, 64, 512)).astype(np.float32),
             spec.xyz_input: rng.normal(size=(1, 3, 64, 512)).astype(np.float32),
             spec.mask_input: np.ones((1, 1, 64, 512), np.float32)}
    run = [ort.InferenceSession(m, providers=["CPUExecutionProvider"]).run(None, feeds)[0]
           for m in (str(path), model.SerializeToString())]
    np.testing.assert_allclose(run[1], run[0], atol=1e-4)
    assert not pad_input_channels(model, spec.input_name)   # 8 already: nothing to do
    assert not pad_input_channels(onnx.load(str(path)), "no-such-input")
