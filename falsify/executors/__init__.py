"""Where samples are scored: in this process, in local worker processes, or on Ray actors.

Every executor scores chunks of samples with warm Evaluators and yields their results in the
order of the chunks (the `Executor` protocol of base.py); `make_executor` picks one by name, so
the driver never names a backend.
"""

from __future__ import annotations

from falsify.executors.base import Executor
from falsify.executors.evaluator import EvalSettings
from falsify.models.runners import Segmenter

EXECUTORS = ("process", "ray")


INFERENCE = ("auto", "worker", "shared")


def shared_inference(inference: str, kind: str, settings: EvalSettings, workers: int) -> bool:
    """Whether one inference process runs the network for all workers: asked for ("shared"),
    or "auto" on a GPU with several local workers; never for one worker (it runs in-process)."""
    if inference not in INFERENCE:
        raise ValueError(f"inference {inference!r}; allowed: {', '.join(INFERENCE)}")
    if kind == "ray" or workers <= 1:
        return False
    return inference == "shared" or (inference == "auto" and settings.device == "cuda")


def make_executor(kind: str, settings: EvalSettings, workers: int,
                  address: str | None = None, model: Segmenter | None = None,
                  inference: str = "auto") -> Executor:
    """An executor (a context manager with `map(chunks)`) for `kind`: "process" runs one warm
    evaluator here for one worker, else a pool of worker processes (with one shared inference
    process where `shared_inference` says so); "ray" runs actors on the cluster at `address`.
    `model` is this process's open model, used in-process only."""
    if kind == "ray":
        from falsify.executors.ray import RayExecutor
        return RayExecutor(settings, workers, address)
    from falsify.executors.local import InlineExecutor, ProcessExecutor
    if workers <= 1:
        return InlineExecutor(settings, model)
    return ProcessExecutor(settings, workers,
                           shared_inference(inference, kind, settings, workers))
