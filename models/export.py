"""ONNX export of SqueezeSeg (+ its spec JSON) and int8 / fp16 variants for ONNX Runtime."""

from __future__ import annotations

import copy
import logging
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from falsify.models.spec import (
    ModelSpec,
    default_spec,
    load_spec,
    normalise,
    save_spec,
    spec_path_for,
)

from falsify.errors import FalsifyError

if TYPE_CHECKING:
    from falsify.models.squeezeseg import SqueezeSeg

OPSET = 17


def export_onnx(model: SqueezeSeg, path: str | Path, H: int = 64, W: int = 512,
                name: str | None = None, **extra: Any) -> tuple[Path, ModelSpec]:
    """Export ``model`` (eval mode, batch dynamic) to ``path`` and write ``<path>.json``.

    Uses the legacy TorchScript exporter (opset 17): same weights give the same bytes.
    """
    import torch

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    m = copy.deepcopy(model).float().to(memory_format=torch.contiguous_format).eval()
    spec = default_spec(name or path.stem, m.channels, H, W, m.crf_iterations, **extra)
    c = len(spec.channels)
    args: tuple[torch.Tensor, ...] = (torch.zeros(1, c, H, W),)
    names = [spec.input_name]
    if m.crf_iterations:
        args += (torch.zeros(1, 3, H, W), torch.ones(1, 1, H, W))
        names += [spec.xyz_input, spec.mask_input]
    dyn = {n: {0: "batch"} for n in [*names, spec.output_name]}
    with warnings.catch_warnings(), torch.no_grad():
        warnings.simplefilter("ignore")
        torch.onnx.export(m, args, str(path), dynamo=False, opset_version=OPSET,
                          input_names=names, output_names=[spec.output_name],
                          dynamic_axes=dyn, do_constant_folding=True)
    save_spec(spec, spec_path_for(path))
    return path, spec


class _ScanReader:
    """Calibration data reader for static quantisation: one scan per call."""

    def __init__(self, spec: ModelSpec, scans: np.ndarray) -> None:
        self.feeds = []
        for i in range(len(scans)):
            x, xyz, mask = normalise(scans[i : i + 1], spec.channels, spec.mean, spec.std)
            feed = {spec.input_name: x}
            if spec.xyz_input:
                feed[spec.xyz_input] = xyz
            if spec.mask_input:
                feed[spec.mask_input] = mask
            self.feeds.append(feed)
        self.it = iter(self.feeds)

    def get_next(self) -> dict[str, np.ndarray] | None:
        return next(self.it, None)

    def rewind(self) -> None:
        self.it = iter(self.feeds)


def _crf_nodes(onnx_path: Path) -> list[str]:
    """Names of the graph nodes that belong to the CRF (kept in fp32 when quantising)."""
    import onnx

    g = onnx.load(str(onnx_path)).graph
    return [n.name for n in g.node if "crf" in n.name.lower()
            or any("crf" in i for i in n.input)]


def quantize_int8(onnx_in: str | Path, onnx_out: str | Path, scans: np.ndarray | None = None,
                  method: str = "static") -> Path:
    """Write an int8 model (+ a copy of the spec). ``static``: QDQ, calibrated on ``scans``
    (default: a few synthetic plausible scans); ``dynamic``: weights-only ConvInteger.

    The CRF stays fp32. Measured on the 2-core EPYC: see models/README.md.
    """
    from onnxruntime.quantization import (
        CalibrationMethod,
        QuantFormat,
        QuantType,
        quantize_dynamic,
        quantize_static,
    )

    onnx_in, onnx_out = Path(onnx_in), Path(onnx_out)
    spec = load_spec(spec_path_for(onnx_in))
    if not onnx_in.is_file():
        raise FalsifyError(f"model file {onnx_in} not found")
    exclude = _crf_nodes(onnx_in)
    root = logging.getLogger()
    level = root.level
    root.setLevel(logging.ERROR)  # its 'consider pre-processing' advice, on every call
    try:
        if method == "dynamic":
            quantize_dynamic(str(onnx_in), str(onnx_out), weight_type=QuantType.QInt8,
                             nodes_to_exclude=exclude, op_types_to_quantize=["Conv"])
        elif method == "static":
            if scans is None:
                from falsify.models.variants import plausible_scans

                scans = plausible_scans(8, spec.height, spec.width, seed=123)
            quantize_static(str(onnx_in), str(onnx_out), _ScanReader(spec, scans),
                            quant_format=QuantFormat.QDQ, activation_type=QuantType.QUInt8,
                            weight_type=QuantType.QInt8, per_channel=True,
                            calibrate_method=CalibrationMethod.MinMax,
                            nodes_to_exclude=exclude, op_types_to_quantize=["Conv", "MaxPool",
                                                                           "Concat", "Add"])
        else:
            raise FalsifyError(f"quantisation method must be 'static' or 'dynamic', got {method!r}")
    finally:
        root.setLevel(level)

    save_spec(spec, spec_path_for(onnx_out))
    return onnx_out


def convert_fp16(onnx_in: str | Path, onnx_out: str | Path,
                 keep_fp32: Sequence[str] = ()) -> Path:
    """fp16 weights and activations with fp32 inputs/outputs (keep_io_types); spec copied.

    No speedup on this CPU (ORT has few fp16 CPU kernels); kept for agreement checks.
    """
    import onnx
    from onnxruntime.transformers.float16 import convert_float_to_float16

    onnx_in, onnx_out = Path(onnx_in), Path(onnx_out)
    model = onnx.load(str(onnx_in))
    m16 = convert_float_to_float16(model, keep_io_types=True,
                                   node_block_list=list(keep_fp32) or None)
    onnx.save(m16, str(onnx_out))
    save_spec(load_spec(spec_path_for(onnx_in)), spec_path_for(onnx_out))
    return onnx_out


def main(argv: Sequence[str] | None = None) -> int:
    """`python -m falsify.models.export WEIGHTS.pt --out MODEL.onnx`: export trained weights
    with their spec."""
    import argparse
    import json
    import sys

    p = argparse.ArgumentParser(prog="python -m falsify.models.export", description=main.__doc__)
    p.add_argument("weights", help="a state dict (.pt) or a training checkpoint.pt")
    p.add_argument("--out", required=True, help="the .onnx to write (spec .json beside it)")
    p.add_argument("--crf-iterations", type=int, default=3, choices=range(4))
    p.add_argument("--height", type=int, default=64)
    p.add_argument("--width", type=int, default=512)
    p.add_argument("--note", action="append", default=[], metavar="KEY=VALUE",
                   help="extra facts recorded in the spec (repeatable)")
    p.add_argument("--int8", default=None, metavar="PATH",
                   help="also write a static int8 copy (CRF kept fp32) to PATH, calibrated on "
                   "training-style synthetic scenes")
    a = p.parse_args(argv)

    def fail(message: str) -> int:
        print(f"python -m falsify.models.export: error: {message}", file=sys.stderr)
        return 2

    if a.int8 and (a.height, a.width) != (64, 512):
        return fail("--int8 calibrates on the kitti-hdl64e-front preset: 64 x 512 only")
    bad = [n for n in a.note if "=" not in n or not n.split("=", 1)[0]]
    if bad:
        return fail(f"--note {bad[0]!r}: write KEY=VALUE")
    import torch
    from falsify.models.squeezeseg import SqueezeSeg
    try:
        state = torch.load(a.weights, map_location="cpu", weights_only=True)
    except Exception as exc:  # OSError, RuntimeError, pickle.UnpicklingError, ...
        return fail(f"{a.weights}: cannot load weights ({str(exc).splitlines()[0]})")
    if not isinstance(state, dict):
        return fail(f"{a.weights}: not a state dict or training checkpoint")
    state = state.get("model", state)
    model = SqueezeSeg(crf_iterations=a.crf_iterations)
    try:
        model.load_state_dict(state)
    except RuntimeError as exc:
        return fail(f"{a.weights}: not SqueezeSeg weights ({str(exc).splitlines()[0]})")
    extra = dict(n.split("=", 1) for n in a.note)
    out = Path(a.out)
    path, spec = export_onnx(model, out, H=a.height, W=a.width, name=out.stem, **extra)
    torch.save({k: v.contiguous() for k, v in model.state_dict().items()}, out.with_suffix(".pt"))
    written = {"onnx": str(path), "spec": str(spec_path_for(path)),
               "weights": str(out.with_suffix(".pt"))}
    if a.int8:
        from falsify.dataset import calibration_scans
        from falsify.sensor import load_sensor

        Path(a.int8).parent.mkdir(parents=True, exist_ok=True)
        scans = calibration_scans(load_sensor("kitti-hdl64e-front"))
        written["int8"] = str(quantize_int8(path, a.int8, scans=scans))
    print(json.dumps(written))
    return 0


if __name__ == "__main__":
    import sys

    sys.exit(main())
