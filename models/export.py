"""ONNX export of SqueezeSeg (+ its spec JSON) and int8 / fp16 variants for ONNX Runtime."""

from __future__ import annotations

import contextlib
import copy
import logging
import warnings
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from falsify.checks import check_out_file, check_range
from falsify.errors import FalsifyError
from falsify.fileio import atomic_path, file_sha256
from falsify.models.spec import (
    ModelSpec,
    default_spec,
    load_paired_spec,
    normalise,
    save_spec,
    spec_path_for,
)

if TYPE_CHECKING:
    from falsify.models.squeezeseg import SqueezeSeg

OPSET = 17
# int8 input convs want the input's channels padded to a multiple of this (`pad_input_channels`)
INT8_INPUT_CHANNELS = 8
# Activation ranges from the 99.99th percentile, not the extremes: on 100 synthetic test scans,
# the int8 network with one CRF iteration differed from fp32 by 0.0117 car IoU per scan on
# average with min-max on 16 scans, 0.0102 with min-max on 64, 0.0062 with this on 64.
CALIBRATION_PERCENTILE = 99.99
# static int8: the backbone's ops, with its ReLUs and `PhaseDeconv`'s reshapes
INT8_OPS = ("Conv", "Relu", "MaxPool", "Concat", "Add", "Pad", "Reshape", "Transpose")


def export_onnx(model: SqueezeSeg, path: str | Path, H: int = 64, W: int = 512,
                name: str | None = None, classes: str | None = None, weights: bool = False,
                **extra: Any) -> tuple[Path, ModelSpec]:
    """Export ``model`` (eval mode, batch dynamic) to ``path`` and write ``<path>.json`` (with
    `weights`, also its state dict as ``<path>.pt``, hashed in the spec beside the .onnx);
    ``classes="semantickitti"`` maps its outputs to SemanticKITTI's train classes (output i is
    train id i), else to our four.

    The graph holds `models.inference.for_export`'s equivalent, faster layers. Uses the legacy
    TorchScript exporter (opset 17): same weights give the same bytes.
    """
    return _export(model, Path(path), H, W, name, classes, extra, weights=weights)


def _export(model: SqueezeSeg, path: Path, H: int, W: int, name: str | None,
            classes: str | None, extra: dict[str, Any], weights: bool) -> tuple[Path, ModelSpec]:
    """`export_onnx`, with `weights` also the state dict as ``<path>.pt``. The spec records
    each file's sha256 and is written first, the files renamed into place after it: a stop
    between them leaves a spec its old files do not match, which every runner refuses (an
    old spec, written last, would pass a new file of an export without hashes)."""
    import torch

    from falsify.models.inference import for_export

    path.parent.mkdir(parents=True, exist_ok=True)
    m = for_export(copy.deepcopy(model).float().to(memory_format=torch.contiguous_format))
    spec = default_spec(name or path.stem, m.channels, H, W, m.crf_iterations, **extra)
    if classes == "semantickitti":
        from falsify.semantic import TRAIN_CLASSES
        spec = replace(spec, num_classes=len(TRAIN_CLASSES),
                       classes={c: (i,) for i, c in enumerate(TRAIN_CLASSES) if i})
    c = len(spec.channels)
    args: tuple[torch.Tensor, ...] = (torch.zeros(1, c, H, W),)
    names = [spec.input_name]
    if m.crf_iterations:
        args += (torch.zeros(1, 3, H, W), torch.ones(1, 1, H, W))
        names += [spec.xyz_input, spec.mask_input]
    dyn = {n: {0: "batch"} for n in [*names, spec.output_name]}
    pt = path.with_suffix(".pt")
    # leaving the block renames the .pt, then the .onnx, both after the spec
    with atomic_path(path) as tmp, (atomic_path(pt) if weights
                                    else contextlib.nullcontext(None)) as pt_tmp:
        with warnings.catch_warnings(), torch.no_grad():
            warnings.simplefilter("ignore")
            torch.onnx.export(m, args, str(tmp), dynamo=False, opset_version=OPSET,
                              input_names=names, output_names=[spec.output_name],
                              dynamic_axes=dyn, do_constant_folding=True)
        hashes = {"onnx": file_sha256(tmp)}
        if pt_tmp is not None:
            torch.save({k: v.contiguous() for k, v in model.state_dict().items()}, pt_tmp)
            hashes["pt"] = file_sha256(pt_tmp)
        spec = replace(spec, sha256=hashes)
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


def _fp32_nodes(onnx_path: Path) -> list[str]:
    """Names of the graph nodes kept in fp32 when quantising: the CRF's, and a `TapConv`'s
    shifted sum (its 1x1 taps conv is quantised)."""
    import onnx

    g = onnx.load(str(onnx_path)).graph
    tap_scopes = {n.name.split("taps/")[0] for n in g.node if "/taps/" in n.name}
    return [n.name for n in g.node if "crf" in n.name.lower()
            or any("crf" in i for i in n.input)
            or any(n.name.startswith(s) and "/taps/" not in n.name for s in tap_scopes)]


def pad_input_channels(model: Any, input_name: str, multiple: int = INT8_INPUT_CHANNELS) -> bool:
    """Widen the network input to a multiple of ``multiple`` channels in the graph: a zero Pad
    on the input, and zero weights for the new channels in every Conv reading it (directly or
    through a spatial Pad). Same outputs; ONNX Runtime's int8 convs run a 5-channel input
    slowly (conv1 and its skip: 1.9 -> 0.5 ms/frame at 8 channels, 1 thread), while its fp32
    ones prefer it unpadded, so only the int8 graph gets this. False if the graph does not
    have that shape (nothing changed)."""
    from onnx import helper, numpy_helper

    g = model.graph
    inp = next((i for i in g.input if i.name == input_name), None)
    dims = inp.type.tensor_type.shape.dim if inp is not None else []
    if len(dims) != 4 or not dims[1].HasField("dim_value"):
        return False
    extra = -dims[1].dim_value % multiple
    readers = [n for n in g.node if input_name in n.input]
    convs = []
    for n in readers:
        if n.op_type == "Pad":  # a spatial pad (conv1's), whose every reader must be a Conv
            after = [m for m in g.node if n.output[0] in m.input]
            if not after or any(m.op_type != "Conv" for m in after):
                return False
            convs += after
        elif n.op_type == "Conv" and n.input[0] == input_name:
            convs.append(n)
        else:
            return False
    inits = {i.name: i for i in g.initializer}
    if not extra or any(c.input[1] not in inits for c in convs):
        return False
    padded = f"{input_name}_channels_padded"
    for n in readers:
        n.input[list(n.input).index(input_name)] = padded
    for c in convs:
        old = inits[c.input[1]]
        w = numpy_helper.to_array(old)
        wide = np.concatenate([w, np.zeros((w.shape[0], extra, *w.shape[2:]), w.dtype)], 1)
        c.input[1] = f"{old.name}_channels_padded"
        g.initializer.append(numpy_helper.from_array(wide, c.input[1]))
        if not any(old.name in n.input for n in g.node):
            g.initializer.remove(old)
    pads = numpy_helper.from_array(np.array([0, 0, 0, 0, 0, extra, 0, 0], np.int64),
                                   f"{padded}_pads")
    g.initializer.append(pads)
    g.node.insert(0, helper.make_node("Pad", [input_name, pads.name], [padded],
                                      name="/input/channel_pad"))
    return True


def quantize_int8(onnx_in: str | Path, onnx_out: str | Path, scans: np.ndarray | None = None,
                  method: str = "static") -> Path:
    """Write an int8 model (+ a copy of the spec). ``static``: QDQ, calibrated on ``scans``
    (default: a few synthetic plausible scans); ``dynamic``: weights-only ConvInteger.

    The CRF stays fp32. The ReLUs are among the quantised op types so that each conv and its
    ReLU share one output scale and fold into one QLinearConv: without them every conv was
    followed by a dequantise-requantise pair (4 ms/frame of 29, 1 thread). Measured on the
    2-core EPYC: see models/README.md.
    """
    from onnxruntime.quantization import QuantType, quantize_dynamic

    onnx_in, onnx_out = Path(onnx_in), Path(onnx_out)
    if not onnx_in.is_file():
        raise FalsifyError(f"model file {onnx_in} not found")
    _, spec = load_paired_spec(onnx_in, "onnx")
    exclude = _fp32_nodes(onnx_in)
    root = logging.getLogger()
    level = root.level
    root.setLevel(logging.ERROR)  # its 'consider pre-processing' advice, on every call
    try:
        with atomic_path(onnx_out) as tmp_out:
            if method == "dynamic":
                quantize_dynamic(str(onnx_in), str(tmp_out), weight_type=QuantType.QInt8,
                                 nodes_to_exclude=exclude, op_types_to_quantize=["Conv"])
            elif method == "static":
                if scans is None:
                    from falsify.models.plausible import plausible_scans

                    scans = plausible_scans(8, spec.height, spec.width, seed=123)
                import tempfile

                import onnx

                model = onnx.load(str(onnx_in))
                with tempfile.TemporaryDirectory() as tmp:
                    src = Path(tmp) / "padded.onnx"
                    pad_input_channels(model, spec.input_name)  # changes nothing if it cannot
                    onnx.save(model, str(src))
                    _quantize_static(src, tmp_out, spec, scans, exclude)
            else:
                raise FalsifyError("quantisation method must be 'static' or 'dynamic', got "
                                   f"{method!r}")
            _save_spec_of(spec, tmp_out, onnx_out)   # before the model: see `_export`
    finally:
        root.setLevel(level)
    return onnx_out


def _save_spec_of(spec: ModelSpec, tmp: Path, onnx_out: Path) -> None:
    """Write the spec of a derived model made at `tmp` (to be renamed to `onnx_out`) beside
    `onnx_out`, recording that model's sha256 alone (not its source's files)."""
    save_spec(replace(spec, sha256={"onnx": file_sha256(tmp)}), spec_path_for(onnx_out))


def _percentile_ranges(onnx_in: Path, spec: ModelSpec, scans: np.ndarray,
                       chunk: int = 8) -> dict[str, tuple[float, float]]:
    """Each quantisable tensor's (min, max) from ONNX Runtime's percentile calibrator, fed
    `chunk` scans at a time: its histograms merge across calls, while one call holds every
    activation of every scan in memory (64 scans at once: 23 GB; in chunks of 8 the whole
    int8 export peaks at 3.9 GB)."""
    import contextlib
    import io
    import tempfile

    from onnxruntime.quantization.calibrate import CalibrationMethod, create_calibrator

    with tempfile.TemporaryDirectory() as tmp, contextlib.redirect_stdout(io.StringIO()):
        calibrator = create_calibrator(
            str(onnx_in), list(INT8_OPS), str(Path(tmp) / "augmented.onnx"),
            calibrate_method=CalibrationMethod.Percentile,
            extra_options={"percentile": CALIBRATION_PERCENTILE})
        for i in range(0, len(scans), chunk):
            calibrator.collect_data(_ScanReader(spec, scans[i:i + chunk]))
        data = calibrator.compute_data()
    return {name: (float(np.min(data[name].range_value[0])),
                   float(np.max(data[name].range_value[1]))) for name in data}


def _quantize_static(onnx_in: Path, onnx_out: Path, spec: ModelSpec, scans: np.ndarray,
                     exclude: list[str]) -> None:
    """QDQ int8: uint8 activations, per-channel int8 weights, activation ranges from
    `_percentile_ranges`. Each Concat's inputs take its output's range, so they share its scale
    and ONNX Runtime's QLinearConcat copies bytes instead of requantising every input (the fire
    modules' concats: 3.5 -> 0.7 ms/frame, 1 thread)."""
    import contextlib
    import io

    import onnx
    from onnxruntime.quantization import CalibrationMethod, QuantFormat, QuantType, quantize_static

    ranges = _percentile_ranges(onnx_in, spec, scans)
    for n in onnx.load(str(onnx_in)).graph.node:
        if n.op_type == "Concat" and n.output[0] in ranges:
            for name in n.input:
                ranges[name] = ranges[n.output[0]]
    overrides = {name: [{"rmin": np.float32(lo), "rmax": np.float32(hi)}]
                 for name, (lo, hi) in ranges.items()}
    # the calibration quantize_static runs itself is replaced by the ranges: one scan does
    with contextlib.redirect_stdout(io.StringIO()):
        quantize_static(str(onnx_in), str(onnx_out), _ScanReader(spec, scans[:1]),
                        quant_format=QuantFormat.QDQ, activation_type=QuantType.QUInt8,
                        weight_type=QuantType.QInt8, per_channel=True,
                        calibrate_method=CalibrationMethod.MinMax,
                        extra_options={"TensorQuantOverrides": overrides},
                        nodes_to_exclude=exclude, op_types_to_quantize=list(INT8_OPS))


def convert_fp16(onnx_in: str | Path, onnx_out: str | Path,
                 keep_fp32: Sequence[str] = ()) -> Path:
    """fp16 weights and activations with fp32 inputs/outputs (keep_io_types); spec copied.

    No speedup on this CPU (ORT has few fp16 CPU kernels); kept for agreement checks.
    """
    import onnx
    from onnxruntime.transformers.float16 import convert_float_to_float16

    onnx_in, onnx_out = Path(onnx_in), Path(onnx_out)
    _, spec = load_paired_spec(onnx_in, "onnx")
    model = onnx.load(str(onnx_in))
    m16 = convert_float_to_float16(model, keep_io_types=True,
                                   node_block_list=list(keep_fp32) or None)
    onnx_out.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(onnx_out) as tmp:
        onnx.save(m16, str(tmp))
        _save_spec_of(spec, tmp, onnx_out)
    return onnx_out


def export_weights(weights: str | Path, out: str | Path, crf_iterations: int = 3,
                   height: int = 64, width: int = 512, notes: Sequence[str] = (),
                   int8: str | Path | None = None,
                   calibration_scans: int | None = None) -> dict[str, str]:
    """Export trained SqueezeSeg weights (a state dict or a training checkpoint.pt) to `out`
    (.onnx, its spec .json and a .pt of the weights beside it), each KEY=VALUE of `notes`
    recorded in the spec; with `int8`, also a static int8 copy there, calibrated on
    `calibration_scans` training-style synthetic scenes (default 64), the old one removed
    first. Returns the files written; FalsifyError before writing anything on bad input. The
    spec records the .onnx and .pt's sha256 (see `_export`): a stop between files leaves a
    set that runners refuse, never a new file run beside an old one."""
    out = check_out_file(out, suffixes=(".onnx",))   # the spec and weights go beside it
    beside = out.with_suffix(".pt")
    if beside.exists() and Path(weights).exists() and beside.samefile(weights):
        raise FalsifyError(f"--out {out}: its weights go beside it as {beside}, which is the "
                           f"input {weights} (a training checkpoint would lose its optimiser "
                           "and resume state); give --out another name")
    check_range(height, "--height", 1)
    check_range(width, "--width", 1)
    if int8:
        int8 = check_out_file(int8, "--int8", suffixes=(".onnx",))   # its spec beside it
        if int8.resolve() == out.resolve():   # it would overwrite the fp32 model
            raise FalsifyError(f"--int8 {int8}: is --out; give the int8 copy another name")
    if int8 and (height, width) != (64, 512):
        raise FalsifyError("--int8 calibrates on the kitti-hdl64e-front preset: 64 x 512 only")
    bad = [n for n in notes if "=" not in n or not n.split("=", 1)[0]]
    if bad:
        raise FalsifyError(f"--note {bad[0]!r}: write KEY=VALUE")
    from falsify.models.squeezeseg import SqueezeSeg, load_state, load_weights_into
    state = load_state(weights)
    model = SqueezeSeg(crf_iterations=crf_iterations)
    load_weights_into(model, state, weights)
    extra = dict(n.split("=", 1) for n in notes)
    if int8:   # an old int8 copy must not outlive this export beside a new fp32 model
        for f in (int8, spec_path_for(int8)):
            f.unlink(missing_ok=True)
    path, spec = _export(model, out, height, width, out.stem, None, extra, weights=True)
    written = {"onnx": str(path), "spec": str(spec_path_for(path)),
               "weights": str(out.with_suffix(".pt"))}
    if int8:
        from falsify.data.training import calibration_scans as scenes
        from falsify.sensor.lidar import load_sensor

        Path(int8).parent.mkdir(parents=True, exist_ok=True)
        scans = scenes(load_sensor("kitti-hdl64e-front"), calibration_scans)
        written["int8"] = str(quantize_int8(path, int8, scans=scans))
    return written
