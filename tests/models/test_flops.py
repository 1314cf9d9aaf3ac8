"""The FLOP counter: a tiny graph counted by hand; the bundled network counted the same twice."""

from __future__ import annotations

import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper, numpy_helper

from falsify.models.flops import count_flops, static_shapes
from tests.conftest import ROOT

BUNDLED = ROOT / "models" / "weights" / "squeezeseg.onnx"


def _const(name: str, values) -> onnx.NodeProto:
    arr = np.asarray(values, np.int64)
    return helper.make_node("Constant", [], [name], value=numpy_helper.from_array(arr, name))


def _weight(name: str, shape: tuple[int, ...]) -> onnx.TensorProto:
    return numpy_helper.from_array(np.ones(shape, np.float32), name)


def tiny_model() -> onnx.ModelProto:
    """X (batch, 4, 8, 10) padded by computed pads (as torch exports F.pad), a grouped strided
    Conv, a ConvTranspose, a grouped Conv named like the CRF's, a Reshape to a shape computed
    from Shape, a batched MatMul and a Gemm with transA."""
    nodes = [
        _const("p_a", [0, 0, 1, 1]), _const("p_b", [0, 0, 1, 1]),
        helper.make_node("Concat", ["p_a", "p_b"], ["pads"], axis=0),
        helper.make_node("Pad", ["X", "pads"], ["xp"]),                     # (1, 4, 10, 12)
        # (1, 6, 8, 5): 6 * 8 * 5 outputs x 2 * 3 * 3 MACs
        helper.make_node("Conv", ["xp", "w1"], ["c1"], name="/enc/conv", group=2,
                         kernel_shape=[3, 3], strides=[1, 2]),
        # (1, 3, 8, 10): 6 * 8 * 5 inputs x 3 * 1 * 2 MACs
        helper.make_node("ConvTranspose", ["c1", "w2"], ["up"], name="/dec/up",
                         kernel_shape=[1, 2], strides=[1, 2]),
        # (1, 3, 8, 10): 3 * 8 * 10 outputs x 1 * 3 * 3 MACs
        helper.make_node("Conv", ["up", "w3"], ["crf"], name="/crf/Conv", group=3,
                         kernel_shape=[3, 3], pads=[1, 1, 1, 1]),
        helper.make_node("Shape", ["crf"], ["s"]),
        _const("s0", [0]), _const("s2", [2]), _const("minus1", [-1]),
        helper.make_node("Slice", ["s", "s0", "s2"], ["s01"]),
        helper.make_node("Concat", ["s01", "minus1"], ["flat_shape"], axis=0),
        helper.make_node("Reshape", ["crf", "flat_shape"], ["flat"]),       # (1, 3, 80)
        helper.make_node("MatMul", ["flat", "w4"], ["mm"], name="mm"),      # (1, 3, 7): K = 80
        _const("rows", [-1, 21]),
        helper.make_node("Reshape", ["mm", "rows"], ["r"]),                 # (1, 21)
        helper.make_node("Transpose", ["r"], ["a"], perm=[1, 0]),           # (21, 1)
        helper.make_node("Gemm", ["a", "w5"], ["Y"], name="gemm", transA=1),  # (1, 5): K = 21
    ]
    inits = [_weight("w1", (6, 2, 3, 3)), _weight("w2", (6, 3, 1, 2)),
             _weight("w3", (3, 1, 3, 3)), _weight("w4", (80, 7)), _weight("w5", (21, 5))]
    graph = helper.make_graph(
        nodes, "tiny", [helper.make_tensor_value_info("X", TensorProto.FLOAT,
                                                      ["batch", 4, 8, 10])],
        [helper.make_tensor_value_info("Y", TensorProto.FLOAT, ["batch", 5])], inits)
    return helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])


CONV = 2 * (6 * 8 * 5) * (2 * 3 * 3)          # 8640
DECONV = 2 * (6 * 8 * 5) * (3 * 1 * 2)        # 2880
CRF = 2 * (3 * 8 * 10) * (1 * 3 * 3)          # 4320
MATMUL = 2 * (3 * 7) * 80                     # 3360
GEMM = 2 * (1 * 5) * 21                       # 210


def test_tiny_graph_counts_as_by_hand():
    m = tiny_model()
    onnx.checker.check_model(m)
    shapes = static_shapes(m)
    assert shapes["xp"] == (1, 4, 10, 12) and shapes["c1"] == (1, 6, 8, 5)
    assert shapes["flat"] == (1, 3, 80) and shapes["Y"] == (1, 5)
    c = count_flops(m)
    assert c.by_op_type == {"Conv": CONV + CRF, "ConvTranspose": DECONV, "MatMul": MATMUL,
                            "Gemm": GEMM}
    assert c.total == CONV + DECONV + CRF + MATMUL + GEMM == 19410
    assert c.crf == CRF and c.crf_share == pytest.approx(CRF / 19410)
    assert c.counted_nodes == 5 and c.unknown == ()
    assert count_flops(m, batch=4).total == c.total      # per frame, whatever the batch


def test_tiny_graph_runs_with_the_shapes_counted():
    """The hand-built graph is a real one: ONNX Runtime gives the shapes the counter used."""
    ort = pytest.importorskip("onnxruntime")
    m = tiny_model()
    sess = ort.InferenceSession(m.SerializeToString(), providers=["CPUExecutionProvider"])
    y = sess.run(None, {"X": np.ones((1, 4, 8, 10), np.float32)})[0]
    assert y.shape == static_shapes(m)["Y"]


def test_no_crf_nodes_means_no_crf_figure():
    m = tiny_model()
    for n in m.graph.node:
        n.name = n.name.replace("crf", "head")
    assert count_flops(m).crf is None


@pytest.mark.skipif(not BUNDLED.exists(), reason="bundled model not trained yet")
def test_bundled_network_count_is_positive_and_stable():
    a, b = count_flops(BUNDLED), count_flops(BUNDLED, batch=2)
    assert a.total > 1e9 and a == b            # the same per frame, counted again at batch 2
    assert a.unknown == () and sum(a.by_op_type.values()) == a.total
    assert a.crf is not None and 0 < a.crf_share < 0.5
