"""Segmentation runners: ONNX Runtime (default, no torch needed), torch and Python plug-ins
(`falsify.models.plugin`), one interface, on the CPU or a CUDA GPU; `load_segmenter` picks one.

``load_segmenter()`` checks the model against its spec JSON when it is created, so a wrong model
fails before any sample runs. Predictions are in our class ids: 0 unknown, 1 car, 2 pedestrian,
3 cyclist, with SemanticKITTI's train ids beside them; invalid pixels (range == 0) are always 0.
"""

from __future__ import annotations

from pathlib import Path

from falsify.errors import FalsifyError
from falsify.models.plugin import check_device, is_plugin
from falsify.models.runners.base import (
    BACKENDS,
    BATCH,
    BUNDLED_ONNX,
    BUNDLED_PT,
    CARDS_DIR,
    WEIGHTS_DIR,
    Prediction,
    Segmenter,
    check_scans,
    feeds,
    points_of,
    scatter,
    to_prediction,
)
from falsify.models.runners.onnx import (
    MAX_DEFAULT_THREADS,
    OnnxSegmenter,
    cpu_session,
    default_threads,
    onnx_session,
)
from falsify.models.runners.plugin import PluginSegmenter
from falsify.models.runners.torch import TorchSegmenter

__all__ = [
    "BACKENDS", "BATCH", "BUNDLED_ONNX", "BUNDLED_PT", "CARDS_DIR", "MAX_DEFAULT_THREADS",
    "WEIGHTS_DIR", "OnnxSegmenter", "PluginSegmenter", "Prediction", "Segmenter", "TorchSegmenter",
    "backend_for", "check_scans", "cpu_session", "default_threads", "feeds", "load_segmenter",
    "not_installed", "onnx_session", "points_of", "resolve_model", "scatter", "to_prediction",
]


# Bundled networks that run as plug-ins (a card, no ONNX file), by the name their card gives;
# each loads its weights from WEIGHTS_DIR/NAME.pt.
PLUGIN_NAMES = {"pointnet20": "falsify.models.pointnet:reference"}


def not_installed(name: str, flag: str | None = None) -> str:
    """The error for a bundled network whose weights this installation lacks (a wheel ships the
    default and its int8 variants only): its card, and where the source repository keeps it."""
    flag = flag or f"--model {name}"
    head = (f"{flag}: not installed (the package ships the default network, squeezeseg, and "
            f"its int8 variants); its card {CARDS_DIR / f'{name}.md'} says how to make it, or ")
    if name in PLUGIN_NAMES:
        module = PLUGIN_NAMES[name].split(":")[0]
        return head + (f"take {name}.pt from the source repository's models/weights/ and load it "
                       f"with {module}.factory(weights=PATH) in a plug-in file "
                       "(--model FILE.py:FACTORY)")
    return head + (f"take {name}.onnx and {name}.json from the source repository's "
                   f"models/weights/ and pass --model PATH/{name}.onnx")


def resolve_model(path: str | Path | None, backend: str = "onnx") -> Path:
    """The file `load_segmenter` opens: the bundled model for None, a bundled model by name
    (e.g. "squeezeseg-drive": models/weights/squeezeseg-drive.onnx) where no such file exists,
    else the path, with .onnx and .pt mapped to the backend's file of the same stem."""
    if path is not None and not Path(path).suffix and not Path(path).exists():
        if (WEIGHTS_DIR / f"{path}.onnx").is_file():
            path = WEIGHTS_DIR / f"{path}.onnx"
        elif str(path) in PLUGIN_NAMES and (WEIGHTS_DIR / f"{path}.pt").is_file():
            raise FalsifyError(f"--model {path}: a plug-in; run it as --model "
                               f"{PLUGIN_NAMES[str(path)]}")
        elif (CARDS_DIR / f"{path}.md").is_file():   # a network the wheel leaves out
            raise FalsifyError(not_installed(str(path)))
        else:
            names = sorted(({f.stem for f in WEIGHTS_DIR.glob("*.onnx")}
                            | {f.stem for f in CARDS_DIR.glob("*.md")}) - set(PLUGIN_NAMES))
            raise FalsifyError(f"--model {path}: no such file, and not a bundled network; "
                               f"bundled: {', '.join(names)}; or a path to an .onnx (its "
                               ".json spec beside it), or MODULE:FACTORY for a plug-in")
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
        if path is not None and p != Path(path) and not p.is_file():
            raise FalsifyError(f"--backend torch reads the state dict beside {path}: {p} not "
                               "found (save one with torch.save(model.state_dict(), PATH))")
        return TorchSegmenter(p, threads, device=device)
    if path is None and not p.is_file():
        raise FalsifyError(f"bundled model {p} not found; train one with "
                           "`falsify train --data DIR --out models/weights`")
    return OnnxSegmenter(p, threads, device=device)
