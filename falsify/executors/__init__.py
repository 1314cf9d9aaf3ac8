"""Where samples are scored: in this process, in local worker processes, or on Ray actors.

Every executor scores chunks of samples with warm Evaluators and yields their results in the
order of the chunks; `make_executor` picks one by name, so the driver never names a backend.
"""

from __future__ import annotations

from falsify.executors.evaluator import EvalSettings
from falsify.models.runner import Segmenter

EXECUTORS = ("process", "ray")


def make_executor(kind: str, settings: EvalSettings, workers: int,
                  address: str | None = None, model: Segmenter | None = None):
    """An executor (a context manager with `map(chunks)`) for `kind`: "process" runs one warm
    evaluator here for one worker, else a pool of worker processes; "ray" runs actors on the
    cluster at `address`. `model` is this process's open model, used in-process only."""
    if kind == "ray":
        from falsify.executors.ray import RayExecutor
        return RayExecutor(settings, workers, address)
    from falsify.executors.local import InlineExecutor, ProcessExecutor
    if workers <= 1:
        return InlineExecutor(settings, model)
    return ProcessExecutor(settings, workers)
