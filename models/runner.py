"""Segmentation runners: ONNX Runtime (default, no torch needed), torch and Python plug-ins
(`falsify.models.plugin`), one interface, on the CPU or a CUDA GPU.

``load_segmenter()`` checks the model against its spec JSON when it is created, so a wrong model
fails before any sample runs. Predictions are in our class ids: 0 unknown, 1 car, 2 pedestrian,
3 cyclist, with SemanticKITTI's train ids beside them; invalid pixels (range == 0) are always 0.
"""

from __future__ import annotations

import dataclasses
import hashlib
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any, Protocol

import numpy as np
from falsify.models.plugin import check_device, is_plugin, open_plugin, torch_device
from falsify.models.spec import (
    POINT_CHANNELS,
    SCAN_INDEX,
    ModelSpec,
    load_spec,
    model_hash,
    normalise,
    spec_path_for,
)

from falsify.classes import CLASSES
from falsify.errors import FalsifyError

WEIGHTS_DIR = Path(__file__).resolve().parent / "weights"
CARDS_DIR = Path(__file__).resolve().parent / "cards"   # one model card per network, shipped
BUNDLED_ONNX = WEIGHTS_DIR / "squeezeseg.onnx"
BUNDLED_PT = WEIGHTS_DIR / "squeezeseg.pt"
# Frames per forward pass. Both backends run SqueezeSeg fastest one frame at a time on the 2-core
# EPYC: the activations stay in cache (fp32 with CRF, ONNX Runtime 1 thread: 46 ms/frame at
# batch 1 against 54 at 8; 2 threads: 25 against 35; torch 2 threads: 52 against 105).
BATCH = 1
BACKENDS = ("onnx", "torch", "python")


@dataclass(frozen=True)
class Prediction:
    """Per-pixel classes (B,H,W) uint8 in our ids; on demand ``probabilities`` (B,H,W,4)
    float32 and ``train_ids`` (B,H,W) uint8, SemanticKITTI's train id of the top output index (0
    where that index maps to no train class, and on invalid pixels).

    The pipeline needs only the classes; the probabilities cost 1.5 ms/frame, so they are
    computed the first time they are read.
    """

    classes: np.ndarray
    raw: np.ndarray = field(repr=False)
    spec: ModelSpec = field(repr=False)
    valid: np.ndarray = field(repr=False)

    @cached_property
    def probabilities(self) -> np.ndarray:
        return _our_probabilities(self.raw, self.spec, self.valid)

    @cached_property
    def train_ids(self) -> np.ndarray:
        ids = self.spec.train_id_table()[np.asarray(self.raw).argmax(axis=1)]
        ids[~self.valid] = 0
        return ids


class Segmenter(Protocol):
    """What the rest of falsify calls: a spec, a content hash and ``predict``."""

    spec: ModelSpec
    model_hash: str

    def predict(self, scans: np.ndarray) -> Prediction: ...


def check_scans(scans: np.ndarray, spec: ModelSpec, source: Path) -> np.ndarray:
    """(H,W,C) or (B,H,W,C) with C >= 5 -> float32 (B,H,W,C); FalsifyError on shape or NaN/inf."""
    a = np.asarray(scans)
    if a.ndim == 3:
        a = a[None]
    any_size = spec.input_kind == "points"
    if a.ndim != 4 or not any_size and a.shape[1:3] != (spec.height, spec.width) or (
            a.shape[3] < 5):
        if any_size:
            raise FalsifyError(f"model {source} expects scans of shape (B, H, W, 6) (x, y, z, "
                               f"intensity, range, label), got {tuple(np.shape(scans))}")
        raise FalsifyError(
            f"model {source} expects scans of shape (B, {spec.height}, {spec.width}, 6) "
            f"(x, y, z, intensity, range, label), got {tuple(np.shape(scans))}")
    if not np.issubdtype(a.dtype, np.number):
        raise FalsifyError(f"model {source}: scans must be numeric, got dtype {a.dtype}")
    a = a.astype(np.float32, copy=False)
    if not np.isfinite(a[..., :5]).all():
        bad = np.argwhere(~np.isfinite(a[..., :5]))[0]
        raise FalsifyError(f"model {source}: scan input holds NaN or inf (first at batch, row, "
                           f"col, channel = {tuple(int(i) for i in bad)}); refusing to score it")
    return a


def _our_probabilities(out: np.ndarray, spec: ModelSpec, valid: np.ndarray) -> np.ndarray:
    """Model output (B,K,H,W) -> (B,H,W,4) probabilities of our classes; unmapped outputs count
    as unknown, invalid pixels are certain unknown."""
    out = out.astype(np.float32, copy=False)
    if spec.output_kind == "logits":
        e = np.exp(out - out.max(axis=1, keepdims=True))
        p = e / e.sum(axis=1, keepdims=True)
    else:
        p = out
    ours = np.zeros((p.shape[0], len(CLASSES), *p.shape[2:]), np.float32)
    used = set()
    for j, ids in enumerate(spec.four_class_outputs()):
        for i in ids:
            ours[:, j] += p[:, i]
            used.add(i)
    for i in range(p.shape[1]):
        if i not in used:
            ours[:, 0] += p[:, i]
    probs = np.ascontiguousarray(np.moveaxis(ours, 1, -1))
    probs[~valid] = np.eye(len(CLASSES), dtype=np.float32)[0]
    return probs


def _one_to_one(spec: ModelSpec) -> list[int] | None:
    """The model output index of each of our classes when every output is exactly one of ours."""
    order = spec.four_class_outputs()
    flat = [i for o in order for i in o]
    if all(len(o) == 1 for o in order) and sorted(flat) == list(range(spec.num_classes)):
        return flat
    return None


def to_prediction(out: np.ndarray, spec: ModelSpec, valid: np.ndarray) -> Prediction:
    """Model output (B,K,H,W) -> Prediction in our 4 classes; invalid pixels are unknown.
    Spec names fold into ours as `falsify.models.spec.four_class_of` says (person is
    pedestrian, bicyclist cyclist; SemanticKITTI's other classes unknown).

    With one model output per class of ours, the classes are the argmax of the raw output
    (softmax keeps the order). A spec in SemanticKITTI's names: the top output's class folded
    into ours, as its labels are folded, so `classes` agrees with `train_ids`. Otherwise the
    argmax of the summed probabilities."""
    order = _one_to_one(spec)
    if order is not None:
        classes = np.asarray(out)[:, order].argmax(axis=1).astype(np.uint8)
    elif spec.semantic:
        classes = spec.four_class_table()[np.asarray(out).argmax(axis=1)]
    else:
        classes = _our_probabilities(out, spec, valid).argmax(axis=-1).astype(np.uint8)
    classes[~valid] = 0
    return Prediction(classes=classes, raw=out, spec=spec, valid=valid)


def _feeds(spec: ModelSpec, scans: np.ndarray) -> dict[str, np.ndarray]:
    x, xyz, mask = normalise(scans, spec.channels, spec.mean, spec.std)
    feeds = {spec.input_name: x}
    if spec.xyz_input:
        feeds[spec.xyz_input] = xyz
    if spec.mask_input:
        feeds[spec.mask_input] = mask
    return feeds


def _open(path: str | Path, spec_path: str | Path | None
          ) -> tuple[Path, Path, ModelSpec, str]:
    """The model file, its spec (beside it unless given) and their content hash."""
    path = Path(path)
    spec_path = spec_path_for(path) if spec_path is None else Path(spec_path)
    if not path.is_file():
        raise FalsifyError(f"model file {path} not found")
    return path, spec_path, load_spec(spec_path), model_hash(path, spec_path)


def points_of(scan: np.ndarray, valid: np.ndarray, spec: ModelSpec) -> np.ndarray:
    """A scan's valid pixels as (N, 4) float32 points (x, y, z, intensity), row-major pixel
    order, each column as (value - mean) / std of the spec (raw values for mean 0, std 1)."""
    pts = scan[valid][:, [SCAN_INDEX[c] for c in POINT_CHANNELS]]
    if any(spec.mean) or any(s != 1 for s in spec.std):
        pts = (pts - np.float32(spec.mean)) / np.float32(spec.std)
    return np.ascontiguousarray(pts, dtype=np.float32)


def scatter(per_scan: list[np.ndarray | None], valid: np.ndarray, classes: int) -> np.ndarray:
    """Per-scan point scores (N, K) back onto their pixels: (B, K, H, W) float32, 0 on invalid
    pixels and for scans given as None (no point)."""
    out = np.zeros((valid.shape[0], classes, *valid.shape[1:]), np.float32)
    for b, scores in enumerate(per_scan):
        if scores is not None:
            rows, cols = np.nonzero(valid[b])
            out[b][:, rows, cols] = scores.T
    return out


def cpu_session(model: str | bytes, threads: int | None = None):
    """An ONNX Runtime CPU session for a model file (path) or serialised graph (bytes): `threads`
    intra-op threads and one inter-op thread (None: ONNX Runtime's default), warnings off.

    Subnormal floats flush to zero (FTZ/DAZ; ONNX Runtime sets it on its threads and on the
    thread that opens the session): 2 % of the CRF's bilateral weights on synthetic test scans
    are subnormal, which Intel cores handle by microcode assists; AMD's at full speed (the
    2-core EPYC: same time either way) and the outputs were bit for bit the same on 24 scans."""
    return onnx_session(model, threads)


def onnx_session(model: str | bytes, threads: int | None = None, device: str = "cpu"):
    """An ONNX Runtime session as `cpu_session` makes it, on the CUDA GPU for device "cuda"
    (CUDAExecutionProvider; FalsifyError where this onnxruntime has none)."""
    import onnxruntime as ort

    providers = ["CPUExecutionProvider"]
    if check_device(device) == "cuda":
        have = ort.get_available_providers()
        if "CUDAExecutionProvider" not in have:
            raise FalsifyError(
                f"--device cuda: onnxruntime {ort.__version__} has no CUDAExecutionProvider "
                f"(it has {', '.join(have)}); pip install onnxruntime-gpu in place of "
                "onnxruntime on a machine with an NVIDIA GPU, or run with --device cpu")
        providers = ["CUDAExecutionProvider", *providers]
    opts = ort.SessionOptions()
    if threads:
        opts.intra_op_num_threads = int(threads)
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
        self.path, spec_path, self.spec, self.model_hash = _open(path, spec_path)
        self.batch = max(1, int(batch))
        self.points = self.spec.input_kind == "points"
        try:
            self.session = onnx_session(str(self.path), threads, device)
        except FalsifyError:
            raise
        except Exception as e:  # onnxruntime raises its own exception types
            raise FalsifyError(f"cannot load ONNX model {self.path}: {e}") from e
        self._check_points() if self.points else self._check()

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
            shape = self.session.run([s.output_name], {s.input_name: zero})[0].shape
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
            shape = self.session.run([s.output_name], _feeds(s, zero))[0].shape
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
        outs = [self.session.run([self.spec.output_name], _feeds(self.spec, a[i:i + self.batch]))[0]
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
            per_scan.append(self.session.run([s.output_name], {s.input_name: x})[0][0])
        return scatter(per_scan, valid, s.num_classes)

    def predict(self, scans: np.ndarray) -> Prediction:
        a = check_scans(scans, self.spec, self.path)
        return to_prediction(self._run(a), self.spec, a[..., 4] > 0)


class TorchSegmenter:
    """PyTorch eager channels_last on the CPU or a CUDA GPU from a state dict (weights_only
    load): fp32, or with precision "bf16" under torch's autocast (oneDNN's bf16 kernels on CPUs
    with bf16 units; the model hash then says bf16, since the logits differ)."""

    def __init__(self, path: str | Path, threads: int | None = None,
                 spec_path: str | Path | None = None, batch: int = BATCH,
                 device: str = "cpu", precision: str = "fp32") -> None:
        self.path, spec_path, self.spec, self.model_hash = _open(path, spec_path)
        if precision not in ("fp32", "bf16"):
            raise FalsifyError(f"torch precision {precision!r}; allowed: fp32, bf16")
        self.precision = precision
        if precision != "fp32":
            self.model_hash = hashlib.sha256(
                f"{self.model_hash}:{precision}".encode()).hexdigest()
        self.batch = max(1, int(batch))
        if self.spec.input_kind != "range":
            raise FalsifyError(f"torch backend builds SqueezeSeg (range images) only; {spec_path} "
                               f"says input_kind {self.spec.input_kind!r}: run it as a plug-in "
                               "(--model MODULE:FACTORY) or as ONNX")
        if self.spec.architecture != "squeezeseg":
            raise FalsifyError(f"torch backend builds SqueezeSeg only; {spec_path} says "
                               f"architecture {self.spec.architecture!r}")
        self.device = torch_device(device)
        import torch
        from falsify.models.squeezeseg import SqueezeSeg

        if threads:
            torch.set_num_threads(int(threads))
        self.torch = torch
        self.model = SqueezeSeg([c for c in self.spec.channels if c != "mask"],
                                crf_iterations=self.spec.crf_iterations,
                                num_classes=self.spec.num_classes)
        if self.spec.channels[-1] != "mask":
            raise FalsifyError(f"model spec {spec_path}: key 'channels' must end with 'mask' "
                               "for the torch SqueezeSeg")
        try:
            state = torch.load(str(self.path), map_location="cpu", weights_only=True)
            self.model.load_state_dict(state)
        except Exception as e:
            raise FalsifyError(f"cannot load torch weights {self.path}: {e}") from e
        # channels_last: about 2x faster than channels-first eager on this CPU (measured)
        self.model = self.model.to(self.device, memory_format=torch.channels_last).eval()

    def run_raw(self, scans: np.ndarray) -> np.ndarray:
        """Raw model output (B,K,H,W) for checked scans."""
        return self._run(check_scans(scans, self.spec, self.path))

    def _run(self, a: np.ndarray) -> np.ndarray:
        outs = []
        # fp32 convolutions on the GPU too: cuDNN's default TF32 moved the bundled network's
        # logits by up to 0.02 from the CPU's on an H100 (3 % of them by more than 1e-3)
        with self.torch.inference_mode(), self.torch.backends.cudnn.flags(
                enabled=True, allow_tf32=False), self.torch.autocast(
                self.device, dtype=self.torch.bfloat16,
                enabled=self.precision == "bf16"):
            for i in range(0, len(a), self.batch):
                f = _feeds(self.spec, a[i:i + self.batch])
                t = {k: self.torch.from_numpy(v).to(self.device) for k, v in f.items()}
                x = t[self.spec.input_name].contiguous(memory_format=self.torch.channels_last)
                y = self.model(x, t.get(self.spec.xyz_input or ""),
                               t.get(self.spec.mask_input or ""))
                outs.append(y.float().cpu().numpy())
        return np.concatenate(outs)

    def predict(self, scans: np.ndarray) -> Prediction:
        a = check_scans(scans, self.spec, self.path)
        return to_prediction(self._run(a), self.spec, a[..., 4] > 0)


class PluginSegmenter:
    """A Python plug-in (`falsify.models.plugin`) as a Segmenter. A points plug-in gets each
    scan's valid pixels as its points and its per-point answers go back to those pixels, so
    every metric stays per pixel; integer answers (output indices) read as certain."""

    def __init__(self, ref: str, threads: int | None = None, device: str = "cpu") -> None:
        self.path = ref
        self.device = device
        self.plugin, self.spec, self.model_hash = open_plugin(ref, threads, device)

    def predict(self, scans: np.ndarray) -> Prediction:
        a = check_scans(scans, self.spec, Path(self.path))
        valid = a[..., 4] > 0
        raw, spec = self._run(a, valid)
        return to_prediction(raw, spec, valid)

    def run_raw(self, scans: np.ndarray) -> np.ndarray:
        """The plug-in's answers as (B,K,H,W) scores (one-hot for integer answers)."""
        a = check_scans(scans, self.spec, Path(self.path))
        return self._run(a, a[..., 4] > 0)[0]

    def _run(self, a: np.ndarray, valid: np.ndarray) -> tuple[np.ndarray, ModelSpec]:
        s, points = self.spec, self.spec.input_kind == "points"
        if points:
            sent = [b for b in range(len(a)) if valid[b].any()]
            batch = [points_of(a[b], valid[b], s) for b in sent]
        else:
            sent = list(range(len(a)))
            batch = []
            for b in sent:
                scan = a[b, ..., :6].copy()
                scan[..., 5:] = 0   # the label: a network must not see the answer
                batch.append(scan)
        answers = self.plugin.predict(batch) if batch else []
        answers = [_numpy(x) for x in answers]
        if len(answers) != len(batch):
            raise FalsifyError(f"plug-in {self.path}: predict returned {len(answers)} answers "
                               f"for {len(batch)} scans")
        ints = {np.issubdtype(x.dtype, np.integer) or x.dtype == bool for x in answers}
        if len(ints) > 1:
            raise FalsifyError(f"plug-in {self.path}: predict returned integer classes for "
                               "some scans and float scores for others")
        onehot = ints == {True}
        k = s.num_classes
        per_scan: list[np.ndarray | None] = [None] * len(a)
        for b, x in zip(sent, answers, strict=True):
            n = int(valid[b].sum()) if points else None
            want = ((n,) if onehot else (n, k)) if points else (
                a.shape[1:3] if onehot else (k, *a.shape[1:3]))
            if tuple(x.shape) != tuple(want):
                what = "classes" if onehot else "scores"
                raise FalsifyError(f"plug-in {self.path}: predict returned {what} of shape "
                                   f"{tuple(x.shape)} for a scan, expected {tuple(want)}")
            if onehot:
                if x.size and (x.min() < 0 or x.max() >= k):
                    raise FalsifyError(f"plug-in {self.path}: predict returned class index "
                                       f"{int(x.min() if x.min() < 0 else x.max())}; the spec "
                                       f"has {k} outputs (0..{k - 1})")
                x = np.eye(k, dtype=np.float32)[x.astype(np.int64)]   # (N, K) or (H, W, K)
                if not points:
                    x = np.moveaxis(x, -1, 0)
            per_scan[b] = x.astype(np.float32, copy=False)
        if points:
            raw = scatter(per_scan, valid, k)
        else:
            raw = np.stack(per_scan) if len(a) else np.zeros((0, k, *a.shape[1:3]), np.float32)
        return raw, dataclasses.replace(s, output_kind="probabilities") if onehot else s


def _numpy(x: Any) -> np.ndarray:
    """A plug-in's answer (numpy array or torch tensor, any device) as a numpy array."""
    if hasattr(x, "detach"):
        x = x.detach().cpu().numpy()
    return np.asarray(x)


def resolve_model(path: str | Path | None, backend: str = "onnx") -> Path:
    """The file `load_segmenter` opens: the bundled model for None, a bundled model by name
    (e.g. "squeezeseg-drive": models/weights/squeezeseg-drive.onnx) where no such file exists,
    else the path, with .onnx and .pt mapped to the backend's file of the same stem."""
    if path is not None and not Path(path).suffix and not Path(path).exists():
        if (WEIGHTS_DIR / f"{path}.onnx").is_file():
            path = WEIGHTS_DIR / f"{path}.onnx"
        elif (CARDS_DIR / f"{path}.md").is_file():   # a network the wheel leaves out
            raise FalsifyError(
                f"--model {path}: not installed (the package ships the default network, "
                f"squeezeseg, and its int8 variants); its card {CARDS_DIR / f'{path}.md'} says "
                f"how to make it, or take {path}.onnx and {path}.json from the source "
                f"repository's models/weights/ and pass --model PATH/{path}.onnx")
    if backend == "torch":
        p = BUNDLED_PT if path is None else Path(path)
        return p.with_suffix(".pt") if p.suffix == ".onnx" else p
    p = BUNDLED_ONNX if path is None else Path(path)
    return p.with_suffix(".onnx") if p.suffix == ".pt" else p


def backend_for(path: str | Path | None, backend: str) -> str:
    """The backend a model runs on: "python" for a plug-in (`module:factory`), else `backend`."""
    return "python" if is_plugin(path) else backend


def load_segmenter(path: str | Path | None = None, backend: str = "onnx",
                   threads: int | None = None, device: str = "cpu") -> Segmenter:
    """Load a model: ``path=None`` is the bundled models/weights/squeezeseg.onnx (or .pt); a
    bundled model can also be named (see `resolve_model`).

    backend "onnx" reads ``<path>`` (.onnx) + ``<path>.json``; "torch" reads the .pt state dict
    beside it (a .onnx path is mapped to the .pt of the same stem); "python" (set for any
    ``module:factory`` or ``file.py:factory`` path) runs a plug-in. ``device`` is "cpu" or
    "cuda".
    """
    check_device(device)
    backend = backend_for(path, backend)
    if backend not in BACKENDS:
        raise FalsifyError(f"unknown model backend {backend!r}; choose 'onnx', 'torch' or "
                           "'python' (a plug-in, MODULE:FACTORY)")
    if backend == "python":
        if path is None or not is_plugin(path):
            raise FalsifyError(f"backend 'python' runs a plug-in: --model MODULE:FACTORY or "
                               f"FILE.py:FACTORY, got {path}")
        return PluginSegmenter(str(path), threads, device)
    p = resolve_model(path, backend)
    if backend == "torch":
        return TorchSegmenter(p, threads, device=device)
    if path is None and not p.is_file():
        raise FalsifyError(f"bundled model {p} not found; train one with "
                           "`python -m falsify.models.train --data DIR --out models/weights`")
    return OnnxSegmenter(p, threads, device=device)
