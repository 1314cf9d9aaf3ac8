"""FLOPs per frame of an ONNX network, counted from its graph (reads ONNX only: no torch, no
runtime), so that a measured time per frame can be read as GFLOP/s against the machine's.

Conv, ConvTranspose, MatMul and Gemm count 2 FLOPs per multiply-add (bias adds and every other
op are left out of the total; their output elements are listed per op type beside it). Shapes
come from ONNX's own per-node shape inference, walked in graph order with the small
shape-computing tensors (Shape, Slice, Concat, ... of constants) evaluated on the way, so that
Pad and Reshape nodes fed by computed shapes (as torch exports them) still get static shapes.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

COUNTED = ("Conv", "ConvTranspose", "MatMul", "Gemm")
# Tensors up to this many elements are evaluated while walking the graph (shape arithmetic and
# small constants); larger ones, such as weights, are never computed.
_EVAL_LIMIT = 1 << 16

Shape = tuple[int | None, ...]


@dataclass(frozen=True)
class FlopCount:
    """FLOPs of one frame (batch 1): the total, by op type, the CRF's part where the graph names
    its CRF nodes, and what could not be counted."""

    total: int                                   # 2 x multiply-adds of the COUNTED ops
    by_op_type: dict[str, int]
    crf: int | None                              # nodes named "...crf..." (None: no such node)
    counted_nodes: int
    other_elements: dict[str, int] = field(default_factory=dict)  # per other op: output
    # elements of its non-constant outputs (shape arithmetic left out)
    unknown: tuple[str, ...] = ()                # COUNTED nodes whose shapes stayed unknown

    @property
    def crf_share(self) -> float | None:
        return None if self.crf is None or not self.total else self.crf / self.total

    def to_json(self) -> dict:
        return {"gflop_per_frame": round(self.total / 1e9, 4), "flops_per_frame": self.total,
                "by_op_type": dict(sorted(self.by_op_type.items())),
                "crf_gflop": None if self.crf is None else round(self.crf / 1e9, 4),
                "crf_share": None if self.crf_share is None else round(self.crf_share, 4),
                "counted_nodes": self.counted_nodes,
                "other_ops_output_elements": dict(sorted(self.other_elements.items())),
                "unknown_nodes": list(self.unknown)}


def _tensor_type(elem_type: int, shape: Shape):
    from onnx import helper
    return helper.make_tensor_type_proto(elem_type, list(shape))


def _dims(tp) -> Shape | None:
    """A TypeProto's static dims (None for a symbolic one); None when the rank is unknown."""
    t = tp.tensor_type
    if not t.HasField("shape"):
        return None
    return tuple(d.dim_value if d.HasField("dim_value") else None for d in t.shape.dim)


def _evaluate(node, values: dict[str, np.ndarray], opsets: dict[str, int]) -> list | None:
    """The node's outputs when all its inputs are small known tensors (or it has none)."""
    from onnx.reference import ReferenceEvaluator

    ins = [i for i in node.input if i]
    if not all(i in values for i in ins) or sum(values[i].size for i in ins) > _EVAL_LIMIT:
        return None
    try:
        outs = ReferenceEvaluator(node, opsets=opsets).run(None, {i: values[i] for i in ins})
    except Exception:   # an op the reference evaluator lacks: fall back to shape inference
        return None
    outs = [np.asarray(o) for o in outs]
    return None if any(o.size > _EVAL_LIMIT for o in outs) else outs


def static_shapes(model, batch: int = 1) -> dict[str, Shape]:
    """Every tensor's shape with each input's symbolic first dim set to `batch` (None where a dim
    stays unknown)."""
    return _walk(model, batch)[0]


def _walk(model, batch: int) -> tuple[dict[str, Shape], set[str]]:
    """Shapes of every tensor, and the names of those computed as constants on the way."""
    import onnx
    from onnx import numpy_helper

    graph = model.graph
    opsets = {o.domain or "": o.version for o in model.opset_import}
    types: dict[str, onnx.TypeProto] = {}
    values: dict[str, np.ndarray] = {}
    for init in graph.initializer:
        arr = numpy_helper.to_array(init)
        types[init.name] = _tensor_type(init.data_type, arr.shape)
        if arr.size <= _EVAL_LIMIT:
            values[init.name] = arr
    for inp in graph.input:
        if inp.name in types:
            continue
        dims = _dims(inp.type) or ()
        fixed = tuple(batch if (d is None and k == 0) else d for k, d in enumerate(dims))
        types[inp.name] = _tensor_type(inp.type.tensor_type.elem_type, fixed)
    for node in graph.node:
        shape_of = types.get(node.input[0]) if node.input else None
        if node.op_type == "Shape" and shape_of is not None:
            dims = _dims(shape_of)
            if dims is not None and None not in dims:   # Shape of a static tensor: a constant
                attrs = {a.name: a.i for a in node.attribute}
                start, end = attrs.get("start", 0), attrs.get("end", len(dims))
                values[node.output[0]] = np.array(dims[start:end], np.int64)
        outs = None if node.output[0] in values else _evaluate(node, values, opsets)
        if outs is not None:
            for name, arr in zip(node.output, outs, strict=False):
                values[name] = arr
        for name in node.output:
            if name in values:
                arr = values[name]
                types[name] = _tensor_type(numpy_helper.from_array(arr).data_type, arr.shape)
        if all(o in types for o in node.output if o):
            continue
        try:
            schema = onnx.defs.get_schema(node.op_type, opsets.get(node.domain or "", 1),
                                          node.domain or "")
            inferred = onnx.shape_inference.infer_node_outputs(
                schema, node, {i: types[i] for i in node.input if i in types},
                input_data={i: numpy_helper.from_array(values[i]) for i in node.input
                            if i in values})
        except Exception:   # unknown op or domain, or inference refused: leave unknown
            continue
        for name, tp in inferred.items():
            types.setdefault(name, tp)
    shapes = {name: dims for name, tp in types.items() if (dims := _dims(tp)) is not None}
    return shapes, set(values)


def _size(shape: Shape | None) -> int | None:
    if shape is None or any(d is None for d in shape):
        return None
    return int(np.prod(shape, dtype=np.int64))


def node_flops(node, shapes: dict[str, Shape]) -> int | None:
    """2 x multiply-adds of one Conv, ConvTranspose, MatMul or Gemm node; None if a shape it
    needs is unknown."""
    x, w = (shapes.get(node.input[k]) if len(node.input) > k else None for k in (0, 1))
    y = shapes.get(node.output[0])
    if node.op_type == "Conv":       # W: (Cout, Cin/groups, k...): each output element
        out, per = _size(y), _size(w[1:] if w else None)   # takes Cin/groups * prod(k) MACs
        return None if out is None or per is None else 2 * out * per
    if node.op_type == "ConvTranspose":   # W: (Cin, Cout/groups, k...): each input element
        inp, per = _size(x), _size(w[1:] if w else None)   # spreads to Cout/groups * prod(k)
        return None if inp is None or per is None else 2 * inp * per
    if node.op_type == "MatMul":     # (..., M, K) @ (..., K, N): K MACs per output element
        out = _size(y)
        return None if out is None or not x or x[-1] is None else 2 * out * x[-1]
    if node.op_type == "Gemm":       # A (M, K) or its transpose
        trans_a = next((a.i for a in node.attribute if a.name == "transA"), 0)
        out = _size(y)
        k = None if not x or len(x) != 2 else x[0 if trans_a else 1]
        return None if out is None or k is None else 2 * out * k
    return None


def count_flops(model: str | Path | object, batch: int = 1) -> FlopCount:
    """FLOPs of one frame of an ONNX model (a path or a loaded ModelProto), counted at `batch`
    frames and divided by it."""
    import onnx

    if isinstance(model, str | Path):
        model = onnx.load(str(model))
    shapes, constants = _walk(model, batch)
    by_op: dict[str, int] = {}
    other: dict[str, int] = {}
    crf, has_crf, counted, unknown = 0, False, 0, []
    for node in model.graph.node:
        if node.op_type not in COUNTED:
            out = node.output[0] if node.output else ""
            n = None if out in constants else _size(shapes.get(out))
            if n is not None:
                other[node.op_type] = other.get(node.op_type, 0) + n // batch
            continue
        f = node_flops(node, shapes)
        if f is None:
            unknown.append(node.name or node.output[0])
            continue
        f //= batch
        counted += 1
        by_op[node.op_type] = by_op.get(node.op_type, 0) + f
        if "crf" in node.name.lower():
            crf += f
            has_crf = True
    has_crf = has_crf or any("crf" in n.name.lower() for n in model.graph.node)
    return FlopCount(sum(by_op.values()), by_op, crf if has_crf else None, counted, other,
                     tuple(unknown))
