"""Python plug-ins: any segmentation network that a Python function builds, named on the command
line as ``--model package.module:factory`` or ``--model path/to/file.py:factory``.

The factory returns an object with a ``spec`` and a ``predict``; the runner's `PluginSegmenter`
feeds it scans and folds its answers into our classes like any other model's. A factory that
takes a ``device`` keyword gets the run's device ("cpu" or "cuda"), one that takes ``threads``
the run's inference threads (None: the library's default). A file plug-in's folder is on
``sys.path`` while it loads, so it may import modules beside it.

Its model hash (what a run records and ``--resume`` compares) is the sha256 of the module's
source file, the factory's name, the spec (as JSON) and every file listed in the object's
optional ``files`` (e.g. its weights); the paths themselves are left out, so the same plug-in
hashes alike on every machine. Code the module imports from elsewhere is not hashed: list any
file its answers depend on in ``files``.

Importing this module needs numpy only (no torch).
"""

from __future__ import annotations

import hashlib
import importlib
import importlib.util
import inspect
import json
import re
import sys
from collections.abc import Callable, Mapping, Sequence
from os import PathLike
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import numpy as np

from falsify.errors import FalsifyError
from falsify.models.spec import ALL_CHANNELS, ModelSpec, spec_from_dict

DEVICES = ("cpu", "cuda")
_DRIVE = re.compile(r"^[A-Za-z]:[\\/]")


@runtime_checkable
class SegmentationPlugin(Protocol):
    """What a plug-in factory returns.

    ``spec``: a ModelSpec, or a dict as a spec file holds it. Its ``input_kind`` says what
    ``predict`` gets, one entry per scan (falsify batches scans across samples):

    - "points": a list of (N, 4) float32 arrays of x, y, z and remission (each column as
      (value - mean) / std where the spec gives mean and std), one per scan, N differing from
      scan to scan; answer per point, in the same order: (N,) integer output indices or (N, C)
      float scores (``output_kind``: logits or probabilities). In grids, searches and `falsify
      predict --score pixels`, the points are a range image's valid pixels in row-major order
      and every metric is per pixel; under `falsify predict --score points` on .bin scans they
      are every point of the scan that has a pixel in the sensor's image (all of them with the
      360-degree `semantickitti-hdl64e`), in the file's order, each scored with its own answer.
      Scans without a valid point are not sent.
    - "range": the (H, W, 6) float32 range image (x, y, z, intensity, range, label; the label
      channel is zeroed); answer (H, W) integer output indices or (C, H, W) float scores.

    ``classes`` maps our names (unknown, car, pedestrian, cyclist) or SemanticKITTI's train
    classes (car, bicycle, ..., person, bicyclist, ..., traffic-sign) to output indices; a
    "range" dict spec may leave out channels, mean, std, input_name and output_name (unused).
    Answers may be numpy arrays or torch tensors, as a list or one stacked array.

    Optional ``files``: paths whose bytes the model hash covers (weights, configs).
    """

    spec: ModelSpec | Mapping[str, Any]

    def predict(self, batch: list[np.ndarray]) -> Sequence[Any]: ...


def is_plugin(model: str | PathLike | None) -> bool:
    """True for a `module:factory` or `file.py:factory` string: a ':' that is not a Windows
    drive's, in a string that names no existing file."""
    if model is None:
        return False
    text = str(model)
    rest = text[2:] if _DRIVE.match(text) else text
    return ":" in rest and not Path(text).exists()


def check_device(device: str) -> str:
    """The device if it is one we run on; else FalsifyError naming the allowed ones."""
    if device not in DEVICES:
        raise FalsifyError(f"--device {device!r}; allowed: {', '.join(DEVICES)}")
    return device


def torch_device(device: str) -> str:
    """The device for torch; FalsifyError for cuda where torch sees no CUDA GPU."""
    check_device(device)
    if device == "cuda":
        import torch

        if not torch.cuda.is_available():
            raise FalsifyError(
                f"--device cuda: torch {torch.__version__} finds no CUDA GPU "
                "(torch.cuda.is_available() is False); run with --device cpu, or install a "
                "CUDA build of torch on a machine with an NVIDIA GPU")
    return device


def cuda_hint(device: str) -> str:
    """For an error under --device cuda: why, where torch is loaded and finds no CUDA GPU (a
    plug-in that asks torch for cuda fails deep inside torch otherwise); else ""."""
    torch = sys.modules.get("torch")
    if device != "cuda" or torch is None:
        return ""
    try:
        available = bool(torch.cuda.is_available())
    except Exception:
        return ""
    if available:
        return ""
    return (f" (--device cuda: torch {getattr(torch, '__version__', '?')} finds no CUDA GPU; "
            "run with --device cpu)")


def _split(ref: str) -> tuple[str, str]:
    """`module:factory` -> (module or file, factory); FalsifyError when either is malformed."""
    where, _, name = ref.rpartition(":")
    if not where or not all(part.isidentifier() for part in name.split(".")):
        raise FalsifyError(f"--model {ref}: a plug-in is MODULE:FACTORY or FILE.py:FACTORY "
                           "(FACTORY a Python name)")
    return where, name


def _is_file(where: str) -> bool:
    return where.endswith(".py") or "/" in where or "\\" in where


def absolute_ref(ref: str) -> str:
    """A `file.py:factory` plug-in with its file as an absolute path (for processes that may
    start in another folder); module plug-ins and malformed strings as given."""
    where, _, name = ref.rpartition(":")
    if where and _is_file(where):
        return f"{Path(where).resolve()}:{name}"
    return ref


def _import(ref: str, where: str) -> tuple[Any, Path]:
    """The plug-in's module (a file run afresh, or an importable module) and its source file."""
    if _is_file(where):
        path = Path(where).resolve()
        if not path.is_file():
            raise FalsifyError(f"--model {ref}: plug-in file {where} not found")
        name = f"_falsify_plugin_{hashlib.sha256(str(path).encode()).hexdigest()[:12]}"
        spec = importlib.util.spec_from_file_location(name, path)
        if spec is None or spec.loader is None:
            raise FalsifyError(f"--model {ref}: {where} is not a Python source file")
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module   # dataclasses and pickling look their module up here
        sys.path.insert(0, str(path.parent))
        try:
            spec.loader.exec_module(module)
        except Exception as e:
            sys.modules.pop(name, None)
            raise FalsifyError(f"--model {ref}: loading {where} failed: "
                               f"{type(e).__name__}: {e}") from e
        finally:
            if str(path.parent) in sys.path:
                sys.path.remove(str(path.parent))
        return module, path
    try:
        module = importlib.import_module(where)
    except Exception as e:
        raise FalsifyError(f"--model {ref}: cannot import {where}: {type(e).__name__}: {e}"
                           ) from e
    try:
        source = inspect.getsourcefile(module)
    except TypeError:
        source = None
    if source is None or not Path(source).is_file():
        raise FalsifyError(f"--model {ref}: module {where} has no source file to hash")
    return module, Path(source)


def _call(factory: Callable, ref: str, threads: int | None, device: str) -> Any:
    """factory(device=..., threads=...), each keyword only where the factory takes it."""
    try:
        params = inspect.signature(factory).parameters
    except (TypeError, ValueError):
        params = {}
    anything = any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values())
    kwargs: dict[str, Any] = {}
    if "device" in params or anything:
        kwargs["device"] = device
    elif device != "cpu":
        raise FalsifyError(f"--model {ref}: --device {device} asked, but the factory takes no "
                           "'device' keyword")
    if threads and ("threads" in params or anything):
        kwargs["threads"] = int(threads)
    try:
        return factory(**kwargs)
    except FalsifyError:
        raise
    except Exception as e:
        raise FalsifyError(f"--model {ref}: the factory failed: {type(e).__name__}: {e}"
                           f"{cuda_hint(device)}") from e


def plugin_spec(spec: Any, ref: str) -> ModelSpec:
    """A plug-in's `spec` (ModelSpec or dict) checked as a spec file is; FalsifyError names
    the plug-in and the key."""
    if isinstance(spec, ModelSpec):
        d = json.loads(spec.to_json())
    elif isinstance(spec, Mapping):
        d = dict(spec)
    else:
        raise FalsifyError(f"--model {ref}: the plug-in's spec must be a ModelSpec or a dict, "
                           f"got {type(spec).__name__}")
    if d.get("input_kind", "range") == "range":   # a plug-in takes raw scans: names unused
        n = len(d.get("channels", ALL_CHANNELS))
        d = {"channels": list(ALL_CHANNELS), "mean": [0.0] * n, "std": [1.0] * n,
             "input_name": "scans", "output_name": "classes", **d}
    return spec_from_dict(d, f"of plug-in {ref}")


def plugin_hash(source: Path, factory: str, spec: ModelSpec,
                files: Sequence[str | PathLike]) -> str:
    """sha256 (hex) of the source file, the factory name, the spec JSON and the files' bytes,
    each part length-prefixed."""
    h = hashlib.sha256(b"falsify-plugin-1")
    parts = [source.read_bytes(), factory.encode(), spec.to_json().encode()]
    for f in files:
        try:
            parts.append(Path(f).read_bytes())
        except OSError as e:
            raise FalsifyError(f"plug-in file {f}: cannot read it ({e.strerror or e})") from e
    for part in parts:
        h.update(len(part).to_bytes(8, "little"))
        h.update(part)
    return h.hexdigest()


def open_plugin(ref: str, threads: int | None = None, device: str = "cpu"
                ) -> tuple[SegmentationPlugin, ModelSpec, str]:
    """Import `ref`'s module, call its factory; the plug-in object, its checked spec and its
    model hash. FalsifyError on anything missing or malformed."""
    check_device(device)
    where, name = _split(ref)
    module, source = _import(ref, where)
    factory: Any = module
    for part in name.split("."):
        factory = getattr(factory, part, None)
        if factory is None:
            raise FalsifyError(f"--model {ref}: {where} has no {name}")
    if not callable(factory):
        raise FalsifyError(f"--model {ref}: {name} is not callable")
    obj = _call(factory, ref, threads, device)
    if not callable(getattr(obj, "predict", None)) or not hasattr(obj, "spec"):
        raise FalsifyError(f"--model {ref}: the factory returned {type(obj).__name__}, which "
                           "lacks a `spec` or a `predict(batch)` (see falsify.models.plugin)")
    spec = plugin_spec(obj.spec, ref)
    files = getattr(obj, "files", None) or ()
    if isinstance(files, str | PathLike):
        files = [files]
    return obj, spec, plugin_hash(source, name, spec, list(files))
