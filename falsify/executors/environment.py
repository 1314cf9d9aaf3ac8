"""What a run's rows were computed under: falsify's, Python's and the libraries' versions, the
CPU, the backend, device and inference threads. Each invocation of a run records the
environments of the processes that scored its samples (its session), so that a user can tell why
two runs' bytes differ and whether a resumed run mixed environments.

Nothing here imports torch or ray: torch's version is recorded only where the run's network is
torch's (the torch backend, or a plug-in that imported it), ray's only for --executor ray.
"""

from __future__ import annotations

import importlib.metadata
import platform
import re
import sys
from typing import Any

import falsify
from falsify.cpu import cpu_name
from falsify.models.runners import MAX_DEFAULT_THREADS

# The libraries whose kernels make a row's numbers (ray casting, network, metrics) or the
# exported tables, recorded by their package versions.
LIBRARIES = ("numpy", "onnxruntime", "embreex", "trimesh", "pandas")
# Recorded but not compared: ray only carries samples and results, it computes no number.
NOT_COMPARED = ("ray", "inference_threads", "torch_threads")


def package_version(name: str) -> str | None:
    """The version of an installed package: the module's own `__version__` where it is loaded
    (onnxruntime-gpu installs the module onnxruntime), else its distribution's; None if absent."""
    module = sys.modules.get(name)
    version = getattr(module, "__version__", None)
    if isinstance(version, str):
        return version
    try:
        return importlib.metadata.version(name)
    except importlib.metadata.PackageNotFoundError:
        return None


def embree_version() -> str | None:
    """The Embree library's version as embreex was built against it (its device names it);
    None where embreex does not say."""
    try:
        from embreex import rtcore
        text = repr(rtcore.EmbreeDevice())
    except Exception:   # noqa: BLE001 - an embreex without the device or its repr: unknown
        return None
    found = re.search(r"(\d+\.\d+\.\d+)", text)
    return found.group(1) if found else None


def uses_torch(backend: str) -> bool:
    """Whether the run's network runs on torch: the torch backend, or a plug-in whose module
    imported torch (this process opened the network first, so its imports are here)."""
    return backend == "torch" or (backend == "python" and "torch" in sys.modules)


def environment(backend: str, device: str, threads: int | None, *, ray: bool = False
                ) -> dict[str, Any]:
    """This process's environment as plain JSON data: versions, CPU, backend, device, and the
    threads each copy of the network runs on (ONNX Runtime's intra-op threads, torch's, or what
    a plug-in is given; None: its library's default); torch's own thread count beside them
    where torch runs the network."""
    env: dict[str, Any] = {"falsify": falsify.__version__, "python": platform.python_version()}
    for name in LIBRARIES:
        env[name] = package_version(name)
    env["embree"] = embree_version()
    torch = sys.modules.get("torch") if uses_torch(backend) else None
    if uses_torch(backend):
        env["torch"] = package_version("torch")
    if ray:
        env["ray"] = package_version("ray")
    env["cpu"] = cpu_name() or platform.processor() or platform.machine()
    env.update(backend=backend, device=device, inference_threads=threads)
    if torch is not None:
        env["torch_threads"] = int(torch.get_num_threads())
        gpu = gpu_name() if device == "cuda" else None
        if gpu:
            env["gpu"] = gpu
    return env


def gpu_name() -> str | None:
    """The CUDA device torch runs on, by name; None where torch is not loaded or sees none."""
    torch = sys.modules.get("torch")
    if torch is None or not torch.cuda.is_available():
        return None
    return torch.cuda.get_device_name(torch.cuda.current_device())


def same_bytes_threads(env: dict) -> object:
    """What of an environment's threads its bytes may depend on: ONNX Runtime computes the same
    logits on 1 to MAX_DEFAULT_THREADS intra-op threads (models/runners/onnx.py), torch on the
    CPU is held at 1; any other count stands for itself. On a GPU threads do not compute it."""
    threads = env.get("inference_threads")
    if env.get("device") == "cuda":
        return None
    if env.get("backend") == "onnx" and isinstance(threads, int) and threads <= \
            MAX_DEFAULT_THREADS:
        return f"1-{MAX_DEFAULT_THREADS}"
    return (threads, env.get("torch_threads"))


def changes(before: dict, after: dict) -> list[str]:
    """What differs from `before` to `after` that may change a row's bytes, one "name old -> new"
    each ("onnxruntime 1.22.0 -> 1.23.0"): versions, CPU, backend, device, GPU, and threads
    only where their counts are not known to give the same bytes."""
    out = []
    for key in dict.fromkeys([*before, *after]):
        if key in NOT_COMPARED:
            continue
        old, new = before.get(key), after.get(key)
        if old != new:
            out.append(f"{key} {_text(old)} -> {_text(new)}")
    if before.get("device") == after.get("device") and \
            same_bytes_threads(before) != same_bytes_threads(after):
        out.append(f"inference threads {_threads(before)} -> {_threads(after)}")
    return out


def session_changes(previous: list[dict], current: list[dict]) -> list[str]:
    """What changed from the environments a run was last computed under (`previous`: its
    latest session that recorded any) to this session's, and between this session's own (Ray
    actors on nodes set up differently); each change once, in order."""
    found: list[str] = []
    for env in current:
        for ref in previous or current[:1]:
            found += changes(ref, env)
    return list(dict.fromkeys(found))


def _text(value: object) -> str:
    return "none" if value is None else str(value)


def _threads(env: dict) -> str:
    text = _text(env.get("inference_threads"))
    if "torch_threads" in env:
        text += f" (torch {env['torch_threads']})"
    return text
