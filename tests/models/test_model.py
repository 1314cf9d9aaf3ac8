"""SqueezeSeg network and recurrent CRF: architecture, padding, CRF maths against a reference."""

from __future__ import annotations

import math

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from falsify.models.crf import ANGULAR_COEF, BILATERAL_COEF, THETA_A, THETA_R, RecurrentCRF  # noqa: E402
from falsify.models.squeezeseg import (  # noqa: E402
    Conv,
    Pool,
    SqueezeSeg,
    _same_pad_w,
    bilinear_kernel,
    count_parameters,
)


def test_parameter_count_matches_paper():
    n = count_parameters(SqueezeSeg())
    assert abs(n - 0.91e6) / 0.91e6 < 0.05, n
    # full input (x, y, z, intensity, range + mask) adds only 64 * 9 + 64 weights
    assert count_parameters(SqueezeSeg(("x", "y", "z", "intensity", "range"))) == n + 64 * 10


@pytest.mark.parametrize("W", [512, 64, 100])
def test_output_shape_equals_input_shape(W):
    m = SqueezeSeg(crf_iterations=1).eval()
    x = torch.randn(2, 5, 8, W)
    with torch.no_grad():
        y = m(x, torch.randn(2, 3, 8, W), torch.ones(2, 1, 8, W))
    assert y.shape == (2, 4, 8, W)


def test_stride2_conv_pads_like_tensorflow_same():
    # TF SAME, kernel 3, stride 2, even width: 0 columns left, 1 right; output j sees 2j..2j+2
    conv = Conv(1, 1, 3, stride=(1, 2), relu=False)
    with torch.no_grad():
        conv.conv.weight.zero_()
        conv.conv.weight[0, 0, 1, 0] = 1.0  # picks the left column of each window
        conv.conv.bias.zero_()
    x = torch.arange(8.0).view(1, 1, 1, 8)
    y = conv(x)
    assert y.shape[-1] == 4
    assert y.flatten().tolist() == [0.0, 2.0, 4.0, 6.0]


@pytest.mark.parametrize("W", [512, 256, 129, 64, 7, 2])
def test_pool_equals_explicit_tensorflow_same_padding(W):
    # the pool pads inside itself (ceil_mode for the one right column); same values as F.pad
    x = torch.rand(2, 3, 5, W)
    left, right = _same_pad_w(W, 3, 2)
    ref = torch.nn.functional.max_pool2d(
        torch.nn.functional.pad(x, (left, right, 1, 1)), 3, stride=(1, 2))
    assert torch.equal(Pool()(x), ref)


def test_unstrided_conv_pads_inside_like_tensorflow_same():
    conv = Conv(2, 3, 3, relu=False)
    x = torch.randn(1, 2, 6, 9)
    ref = torch.nn.functional.conv2d(torch.nn.functional.pad(x, (1, 1, 1, 1)),
                                     conv.conv.weight, conv.conv.bias)
    torch.testing.assert_close(conv(x), ref)


def test_exported_graph_keeps_the_blocked_layout(tmp_path):
    # Speed guard without a timer: a Pad or a Softmax on axis 1 between layers makes ONNX
    # Runtime reorder the blocked layout around it. Only conv1's input pad may remain.
    onnx = pytest.importorskip("onnx")
    from falsify.models.export import export_onnx

    path, _ = export_onnx(SqueezeSeg(crf_iterations=3).eval(), tmp_path / "m.onnx")
    ops = [n.op_type for n in onnx.load(str(path)).graph.node]
    assert ops.count("Pad") == 1 and "Softmax" not in ops
    assert ops.count("MaxPool") == 3


def test_deconv_is_bilinear_and_doubles_width():
    k = bilinear_kernel(2)
    assert torch.allclose(k[0, 0, 0], torch.tensor([0.25, 0.75, 0.75, 0.25]))
    assert k[0, 1].abs().sum() == 0
    m = SqueezeSeg()
    d = m.fire_deconv13.deconv
    y = d(torch.ones(1, 16, 1, 10))
    assert y.shape[-1] == 20
    # interior of a constant input stays constant (bilinear upsampling)
    assert torch.allclose(y[0, 0, 0, 1:-1], torch.ones(18))


def test_no_batch_norm_and_dropout_before_conv14():
    m = SqueezeSeg()
    assert not any(isinstance(x, torch.nn.BatchNorm2d) for x in m.modules())
    assert m.drop.p == 0.5
    assert all(c.conv.bias is not None for c in m.modules() if isinstance(c, Conv))


def test_crf_compatibility_initialisation():
    crf = RecurrentCRF(3)
    off = 1 - torch.eye(4)
    assert torch.allclose(crf.bilateral_compat.weight[..., 0, 0], off * BILATERAL_COEF)
    assert torch.allclose(crf.angular_compat.weight[..., 0, 0], off * ANGULAR_COEF)
    assert sum(p.numel() for p in crf.parameters()) == 32


def _reference_crf(logits, xyz, mask, iters, ang_c, bi_c, theta_a=THETA_A, theta_r=THETA_R):
    """Plain-loop numpy version of the CRF (one image) to check the vectorised one."""
    C, H, W = logits.shape
    e = logits.astype(np.float64)
    for _ in range(iters):
        q = np.exp(e - e.max(0)) / np.exp(e - e.max(0)).sum(0)
        ang = np.zeros_like(q)
        bi = np.zeros_like(q)
        for r in range(H):
            for c in range(W):
                for dr in (-1, 0, 1):
                    for dc in (-2, -1, 0, 1, 2):
                        rr, cc = r + dr, c + dc
                        if (dr, dc) == (0, 0) or not (0 <= rr < H and 0 <= cc < W):
                            continue
                        if not mask[rr, cc]:
                            continue
                        d2 = np.sum((xyz[:, r, c] - xyz[:, rr, cc]) ** 2)
                        for k in range(C):
                            g = math.exp(-(dr * dr + dc * dc) / 2 / theta_a[k] ** 2)
                            ang[k, r, c] += g * q[k, rr, cc]
                            if mask[r, c]:
                                b = math.exp(-d2 / 2 / theta_r[k] ** 2)
                                bi[k, r, c] += g * b * q[k, rr, cc]
        e = (logits - np.einsum("ij,jhw->ihw", ang_c, ang)
             - np.einsum("ij,jhw->ihw", bi_c, bi))  # mean field: unary = logits
    return e


@pytest.mark.parametrize("theta_a, theta_r", [
    (THETA_A, THETA_R),                                   # two groups of two classes: broadcast
    ((0.9, 0.8, 0.7, 0.6), (0.015, 0.02, 0.01, 0.012)),   # four groups
    ((0.9, 0.6, 0.9, 0.6), (0.015, 0.01, 0.015, 0.01)),   # groups not side by side
])
def test_crf_matches_loop_reference_and_ignores_invalid_pixels(theta_a, theta_r):
    rng = np.random.default_rng(0)
    H, W = 4, 7
    logits = rng.normal(size=(4, H, W)).astype(np.float32)
    xyz = (rng.normal(size=(3, H, W)) * 0.01).astype(np.float32)  # close points: bilateral on
    mask = rng.random((H, W)) > 0.25
    crf = RecurrentCRF(2, theta_a=theta_a, theta_r=theta_r)
    assert crf.groups == len(set(zip(theta_a, theta_r, strict=True)))
    with torch.no_grad():
        crf.angular_compat.weight.normal_()
        crf.bilateral_compat.weight.normal_()
        got = crf(torch.from_numpy(logits)[None], torch.from_numpy(xyz)[None],
                  torch.from_numpy(mask.astype(np.float32))[None, None])[0].numpy()
    ang_c = crf.angular_compat.weight[..., 0, 0].detach().numpy()
    bi_c = crf.bilateral_compat.weight[..., 0, 0].detach().numpy()
    ref = _reference_crf(logits, xyz, mask, 2, ang_c, bi_c, theta_a, theta_r)
    np.testing.assert_allclose(got, ref, atol=1e-5)
    # changing an invalid pixel's logits and xyz changes nothing at the valid pixels
    r, c = np.argwhere(~mask)[0]
    logits2, xyz2 = logits.copy(), xyz.copy()
    logits2[:, r, c] += 5.0
    xyz2[:, r, c] += 1.0
    with torch.no_grad():
        got2 = crf(torch.from_numpy(logits2)[None], torch.from_numpy(xyz2)[None],
                   torch.from_numpy(mask.astype(np.float32))[None, None])[0].numpy()
    np.testing.assert_allclose(got2[:, mask], got[:, mask], atol=1e-6)


def test_crf_zero_iterations_is_identity():
    x = torch.randn(1, 4, 3, 5)
    assert torch.equal(RecurrentCRF(0)(x, torch.zeros(1, 3, 3, 5), torch.ones(1, 1, 3, 5)), x)
    with pytest.raises(ValueError):
        RecurrentCRF(4)


def test_crf_with_its_initialisation_smooths_an_isolated_pixel():
    """A pixel narrowly voting car inside a surface of close 'unknown' points is pulled back to
    its neighbours' class; a confident car region is left alone."""
    H, W = 5, 9
    logits = np.zeros((4, H, W), np.float32)
    logits[0] = 2.0                     # unknown everywhere ...
    logits[1, 2, 4] = 2.1               # ... one pixel narrowly car
    logits[1, :, 6:] = 6.0              # a confident car region on the right
    xs, ys = np.meshgrid(np.arange(W) * 0.005, np.arange(H) * 0.005)
    xyz = np.stack([np.full((H, W), 10.0), xs, ys]).astype(np.float32)
    mask = np.ones((1, 1, H, W), np.float32)
    crf = RecurrentCRF(3)
    with torch.no_grad():
        out = crf(torch.from_numpy(logits)[None], torch.from_numpy(xyz)[None],
                  torch.from_numpy(mask))[0].argmax(0).numpy()
    assert logits.argmax(0)[2, 4] == 1 and out[2, 4] == 0
    assert (out[:, 7:] == 1).all()
