"""The ONNX Runtime runner (the default; no torch needed), on the CPU or a CUDA GPU, and the
sessions it opens."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from falsify.errors import FalsifyError
from falsify.models.plugin import check_device
from falsify.models.runners.base import (
    BATCH,
    Prediction,
    check_finite,
    check_scans,
    feeds,
    open_model,
    points_of,
    scatter,
    to_prediction,
)

# ONNX input element types a runner feeds, as numpy dtypes: scans are made in float32 and cast
# to the graph's own type (an fp16 export takes float16); outputs are read back as float32.
INPUT_TYPES = {"tensor(float)": np.float32, "tensor(float16)": np.float16,
               "tensor(double)": np.float64}

# ONNX Runtime chooses how some reductions sum by comparing a tensor's size with its thread
# count (ReduceSum over a middle axis takes its fast path while the outer size >= max(2,
# threads)). SqueezeSeg's CRF sums (4, 14, H*W) a frame: 1 to 4 threads give the same logits,
# 5 or more differ in the last bits (63 of 1.0 M on 8 scans). Sessions not told how many
# threads take at most this many, so the scores do not depend on the machine's core count.
MAX_DEFAULT_THREADS = 4


def default_threads() -> int:
    """Intra-op threads of a session not told how many: the cores this process may use, at most
    MAX_DEFAULT_THREADS (ONNX Runtime's own default, every core, varies the bytes by machine)."""
    try:
        usable = len(os.sched_getaffinity(0))
    except AttributeError:   # not Linux
        usable = os.cpu_count() or 1
    return max(1, min(usable, MAX_DEFAULT_THREADS))


def cpu_session(model: str | bytes, threads: int | None = None):
    """An ONNX Runtime CPU session for a model file (path) or serialised graph (bytes): `threads`
    intra-op threads (None: `default_threads()`) and one inter-op thread, warnings off.

    Subnormal floats flush to zero (FTZ/DAZ; ONNX Runtime sets it on its threads and on the
    thread that opens the process's first session): 2 % of the CRF's bilateral weights on
    synthetic test scans are subnormal, which Intel cores handle by microcode assists; AMD's
    at full speed (the 2-core EPYC: same time either way) and the outputs were bit for bit the
    same on 24 scans."""
    return onnx_session(model, threads)


def _torch_sees_cuda() -> bool:
    """Whether torch is installed here and sees a CUDA GPU (False without torch)."""
    import importlib.util
    if importlib.util.find_spec("torch") is None:
        return False
    import torch
    return bool(torch.cuda.is_available())


def onnx_session(model: str | bytes, threads: int | None = None, device: str = "cpu"):
    """An ONNX Runtime session as `cpu_session` makes it, on the CUDA GPU for device "cuda"
    (CUDAExecutionProvider; FalsifyError where this onnxruntime has none)."""
    import onnxruntime as ort

    providers = ["CPUExecutionProvider"]
    if check_device(device) == "cuda":
        have = ort.get_available_providers()
        if "CUDAExecutionProvider" not in have:
            torch_too = (", or --backend torch for a model with its .pt beside it (torch here "
                         "sees a CUDA GPU)" if _torch_sees_cuda() else "")
            raise FalsifyError(
                f"--device cuda: onnxruntime {ort.__version__} has no CUDAExecutionProvider "
                f"(it has {', '.join(have)}); pip install onnxruntime-gpu in place of "
                f"onnxruntime on a machine with an NVIDIA GPU, or run with --device cpu"
                f"{torch_too}")
        providers = ["CUDAExecutionProvider", *providers]
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = int(threads) if threads else default_threads()
    opts.inter_op_num_threads = 1
    opts.log_severity_level = 3
    opts.add_session_config_entry("session.set_denormal_as_zero", "1")
    session = ort.InferenceSession(model, opts, providers=providers)
    if providers[0] not in session.get_providers():   # CUDA libraries missing: ORT fell back
        raise FalsifyError(f"--device cuda: onnxruntime could not start the "
                           f"CUDAExecutionProvider (check the CUDA and cuDNN libraries "
                           f"onnxruntime-gpu {ort.__version__} needs), or run with --device cpu")
    return session


class OnnxSegmenter:
    """ONNX Runtime on the CPU or a CUDA GPU; the CRF (if any) is part of the graph. A spec with
    input_kind "points" runs the graph once per scan on its valid points: (1, N, 4) float32 in,
    (1, N, C) scores out."""

    def __init__(self, path: str | Path, threads: int | None = None,
                 spec_path: str | Path | None = None, batch: int = BATCH,
                 device: str = "cpu") -> None:
        self.path, spec_path, self.spec, self.model_hash = open_model(path, spec_path,
                                                                          "onnx")
        self.batch = max(1, int(batch))
        self.points = self.spec.input_kind == "points"
        try:
            self.session = onnx_session(str(self.path), threads, device)
        except FalsifyError:
            raise
        except Exception as e:  # onnxruntime raises its own exception types
            raise FalsifyError(f"cannot load ONNX model {self.path}: {e}") from e
        # the intra-op threads the session runs on (a run records them)
        self.threads = int(self.session.get_session_options().intra_op_num_threads)
        self._dtypes = self._input_dtypes()
        self._check_points() if self.points else self._check()

    def _input_dtypes(self) -> dict[str, Any]:
        """Each graph input's numpy dtype; FalsifyError naming the input and the allowed types
        for any other (an integer input is no segmentation network's scan)."""
        out = {}
        for i in self.session.get_inputs():
            if i.type not in INPUT_TYPES:
                raise FalsifyError(f"model {self.path}: input '{i.name}' is {i.type}; allowed: "
                                   f"{', '.join(INPUT_TYPES)}")
            out[i.name] = INPUT_TYPES[i.type]
        return out

    def _session_run(self, name: str, inputs: dict[str, np.ndarray]) -> np.ndarray:
        """One output of the graph as float32, the inputs cast to the graph's own types."""
        typed = {k: v.astype(self._dtypes.get(k, np.float32), copy=False)
                 for k, v in inputs.items()}
        return np.asarray(self.session.run([name], typed)[0]).astype(np.float32, copy=False)

    def _check_points(self) -> None:
        """A points graph: one input (1, N, 4), output (1, N, num_classes); FalsifyError on any
        mismatch with the spec."""
        s, where = self.spec, f"model {self.path} does not match its spec"
        inputs = {i.name: i.shape for i in self.session.get_inputs()}
        if list(inputs) != [s.input_name]:
            raise FalsifyError(f"{where}: spec input ['{s.input_name}'], model inputs "
                               f"{list(inputs)}")
        outputs = {o.name: o.shape for o in self.session.get_outputs()}
        if s.output_name not in outputs:
            raise FalsifyError(f"{where}: output '{s.output_name}' not in {list(outputs)}")
        shape, ishape = outputs[s.output_name], inputs[s.input_name]
        if len(ishape) != 3 or isinstance(ishape[2], int) and ishape[2] != 4:
            raise FalsifyError(f"{where}: input '{s.input_name}' has shape {ishape}, expected "
                               "(1, N, 4) points")
        if len(shape) != 3 or not isinstance(shape[2], int):   # dynamic: run eight points
            zero = np.zeros((1, 8, 4), np.float32)
            shape = self._session_run(s.output_name, {s.input_name: zero}).shape
        if len(shape) != 3 or shape[2] != s.num_classes:
            raise FalsifyError(f"{where}: output '{s.output_name}' has shape {tuple(shape)}, "
                               f"expected (1, N, {s.num_classes}) scores per point")

    def _check(self) -> None:
        """Compare the graph's inputs and outputs with the spec; FalsifyError on any mismatch."""
        s, where = self.spec, f"model {self.path} does not match its spec"
        inputs = {i.name: i.shape for i in self.session.get_inputs()}
        want = {s.input_name: len(s.channels)}
        if s.xyz_input:
            want[s.xyz_input] = 3
        if s.mask_input:
            want[s.mask_input] = 1
        missing = [n for n in want if n not in inputs]
        extra = [n for n in inputs if n not in want]
        if missing or extra:
            raise FalsifyError(f"{where}: spec inputs {list(want)}, model inputs {list(inputs)}")
        for name, c in want.items():
            self._check_dims(where, f"input '{name}'", inputs[name], c)
        outputs = {o.name: o.shape for o in self.session.get_outputs()}
        if s.output_name not in outputs:
            raise FalsifyError(f"{where}: output '{s.output_name}' not in {list(outputs)}")
        shape = outputs[s.output_name]
        if not all(isinstance(d, int) for d in shape[1:]):  # dynamic: run one zero frame
            zero = np.zeros((1, s.height, s.width, 6), np.float32)
            shape = self._session_run(s.output_name, feeds(s, zero)).shape
        self._check_dims(where, f"output '{s.output_name}'", shape, s.num_classes,
                         what="classes")

    def _check_dims(self, where: str, label: str, shape: Any, c: int,
                    what: str = "channels") -> None:
        s = self.spec
        if len(shape) != 4:
            raise FalsifyError(f"{where}: {label} has rank {len(shape)}, expected 4 (NCHW)")
        for got, exp, key in ((shape[1], c, what), (shape[2], s.height, "height"),
                              (shape[3], s.width, "width")):
            if isinstance(got, int) and got != exp:
                raise FalsifyError(f"{where}: {label} has {got} {key}, spec says {exp}")

    def run_raw(self, scans: np.ndarray) -> np.ndarray:
        """Raw model output (B,K,H,W) for checked scans."""
        return self._run(check_scans(scans, self.spec, self.path))

    def _run(self, a: np.ndarray) -> np.ndarray:
        if self.points:
            return self._run_points(a)
        outs = [self._session_run(self.spec.output_name, feeds(self.spec, a[i:i + self.batch]))
                for i in range(0, len(a), self.batch)]
        return np.concatenate(outs)

    def _run_points(self, a: np.ndarray) -> np.ndarray:
        s, valid = self.spec, a[..., 4] > 0
        per_scan: list[np.ndarray | None] = []
        for b in range(len(a)):
            if not valid[b].any():
                per_scan.append(None)
                continue
            x = points_of(a[b], valid[b], s)[None]
            per_scan.append(self._session_run(s.output_name, {s.input_name: x})[0])
        return scatter(per_scan, valid, s.num_classes)

    def predict(self, scans: np.ndarray) -> Prediction:
        a = check_scans(scans, self.spec, self.path)
        valid = a[..., 4] > 0
        return to_prediction(check_finite(self._run(a), valid, self.path), self.spec, valid)
