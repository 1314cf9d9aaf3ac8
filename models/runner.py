"""Segmentation runners: ONNX Runtime (default, no torch needed) and torch, one interface.

``load_segmenter()`` checks the model against its spec JSON when it is created, so a wrong model
fails before any sample runs. Predictions are in our class ids: 0 unknown, 1 car, 2 pedestrian,
3 cyclist; invalid pixels (range == 0) are always 0.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any, Protocol

import numpy as np
from falsify.models.spec import ModelSpec, load_spec, model_hash, normalise, spec_path_for

from falsify.classes import CLASSES
from falsify.errors import FalsifyError

WEIGHTS_DIR = Path(__file__).resolve().parent / "weights"
BUNDLED_ONNX = WEIGHTS_DIR / "squeezeseg.onnx"
BUNDLED_PT = WEIGHTS_DIR / "squeezeseg.pt"
# Frames per forward pass. Both backends run SqueezeSeg fastest one frame at a time on the 2-core
# EPYC: the activations stay in cache (fp32 with CRF, ONNX Runtime 1 thread: 46 ms/frame at
# batch 1 against 54 at 8; 2 threads: 25 against 35; torch 2 threads: 52 against 105).
BATCH = 1


@dataclass(frozen=True)
class Prediction:
    """Per-pixel classes (B,H,W) uint8 in our ids; ``probabilities`` (B,H,W,4) float32 on demand.

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
    if a.ndim != 4 or a.shape[1:3] != (spec.height, spec.width) or a.shape[3] < 5:
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
    for j, name in enumerate(CLASSES):
        for i in spec.classes.get(name, ()):
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
    order = [list(spec.classes.get(name, ())) for name in CLASSES]
    flat = [i for o in order for i in o]
    if all(len(o) == 1 for o in order) and sorted(flat) == list(range(spec.num_classes)):
        return flat
    return None


def to_prediction(out: np.ndarray, spec: ModelSpec, valid: np.ndarray) -> Prediction:
    """Model output (B,K,H,W) -> Prediction in our 4 classes; invalid pixels are unknown.

    With one model output per class of ours, the classes are the argmax of the raw output
    (softmax keeps the order); otherwise of the summed probabilities."""
    order = _one_to_one(spec)
    if order is not None:
        classes = np.asarray(out)[:, order].argmax(axis=1).astype(np.uint8)
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


def cpu_session(model: str | bytes, threads: int | None = None):
    """An ONNX Runtime CPU session for a model file (path) or serialised graph (bytes): `threads`
    intra-op threads and one inter-op thread (None: ONNX Runtime's default), warnings off.

    Subnormal floats flush to zero (FTZ/DAZ; ONNX Runtime sets it on its threads and on the
    thread that opens the session): 2 % of the CRF's bilateral weights on synthetic test scans
    are subnormal, which Intel cores handle by microcode assists; AMD's at full speed (the
    2-core EPYC: same time either way) and the outputs were bit for bit the same on 24 scans."""
    import onnxruntime as ort

    opts = ort.SessionOptions()
    if threads:
        opts.intra_op_num_threads = int(threads)
        opts.inter_op_num_threads = 1
    opts.log_severity_level = 3
    opts.add_session_config_entry("session.set_denormal_as_zero", "1")
    return ort.InferenceSession(model, opts, providers=["CPUExecutionProvider"])


class OnnxSegmenter:
    """ONNX Runtime on the CPU; the CRF (if any) is part of the graph."""

    def __init__(self, path: str | Path, threads: int | None = None,
                 spec_path: str | Path | None = None, batch: int = BATCH) -> None:
        self.path, spec_path, self.spec, self.model_hash = _open(path, spec_path)
        self.batch = max(1, int(batch))
        try:
            self.session = cpu_session(str(self.path), threads)
        except Exception as e:  # onnxruntime raises its own exception types
            raise FalsifyError(f"cannot load ONNX model {self.path}: {e}") from e
        self._check()

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
        outs = [self.session.run([self.spec.output_name], _feeds(self.spec, a[i:i + self.batch]))[0]
                for i in range(0, len(a), self.batch)]
        return np.concatenate(outs)

    def predict(self, scans: np.ndarray) -> Prediction:
        a = check_scans(scans, self.spec, self.path)
        return to_prediction(self._run(a), self.spec, a[..., 4] > 0)


class TorchSegmenter:
    """PyTorch eager fp32 channels_last on the CPU from a state dict (weights_only load)."""

    def __init__(self, path: str | Path, threads: int | None = None,
                 spec_path: str | Path | None = None, batch: int = BATCH) -> None:
        self.path, spec_path, self.spec, self.model_hash = _open(path, spec_path)
        self.batch = max(1, int(batch))
        if self.spec.architecture != "squeezeseg":
            raise FalsifyError(f"torch backend builds SqueezeSeg only; {spec_path} says "
                               f"architecture {self.spec.architecture!r}")
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
        self.model = self.model.to(memory_format=torch.channels_last).eval()

    def run_raw(self, scans: np.ndarray) -> np.ndarray:
        """Raw model output (B,K,H,W) for checked scans."""
        return self._run(check_scans(scans, self.spec, self.path))

    def _run(self, a: np.ndarray) -> np.ndarray:
        outs = []
        with self.torch.inference_mode():
            for i in range(0, len(a), self.batch):
                f = _feeds(self.spec, a[i:i + self.batch])
                t = {k: self.torch.from_numpy(v) for k, v in f.items()}
                x = t[self.spec.input_name].contiguous(memory_format=self.torch.channels_last)
                y = self.model(x, t.get(self.spec.xyz_input or ""),
                               t.get(self.spec.mask_input or ""))
                outs.append(y.float().numpy())
        return np.concatenate(outs)

    def predict(self, scans: np.ndarray) -> Prediction:
        a = check_scans(scans, self.spec, self.path)
        return to_prediction(self._run(a), self.spec, a[..., 4] > 0)


def resolve_model(path: str | Path | None, backend: str = "onnx") -> Path:
    """The file `load_segmenter` opens: the bundled model for None, a bundled model by name
    (e.g. "squeezeseg-drive": models/weights/squeezeseg-drive.onnx) where no such file exists,
    else the path, with .onnx and .pt mapped to the backend's file of the same stem."""
    if (path is not None and not Path(path).suffix and not Path(path).exists()
            and (WEIGHTS_DIR / f"{path}.onnx").is_file()):
        path = WEIGHTS_DIR / f"{path}.onnx"
    if backend == "torch":
        p = BUNDLED_PT if path is None else Path(path)
        return p.with_suffix(".pt") if p.suffix == ".onnx" else p
    p = BUNDLED_ONNX if path is None else Path(path)
    return p.with_suffix(".onnx") if p.suffix == ".pt" else p


def load_segmenter(path: str | Path | None = None, backend: str = "onnx",
                   threads: int | None = None) -> Segmenter:
    """Load a model: ``path=None`` is the bundled models/weights/squeezeseg.onnx (or .pt); a
    bundled model can also be named (see `resolve_model`).

    backend "onnx" reads ``<path>`` (.onnx) + ``<path>.json``; "torch" reads the .pt state dict
    beside it (a .onnx path is mapped to the .pt of the same stem).
    """
    if backend not in ("onnx", "torch"):
        raise FalsifyError(f"unknown model backend {backend!r}; choose 'onnx' or 'torch'")
    p = resolve_model(path, backend)
    if backend == "torch":
        return TorchSegmenter(p, threads)
    if path is None and not p.is_file():
        raise FalsifyError(f"bundled model {p} not found; train one with "
                           "`python -m falsify.models.train --data DIR --out models/weights`")
    return OnnxSegmenter(p, threads)
