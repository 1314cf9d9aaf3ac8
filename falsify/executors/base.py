"""What every executor is: a context manager that, once entered, scores chunks of samples with
warm evaluators and yields each chunk's results in the order of the chunks."""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from typing import Protocol

from falsify.results.samples import SampleResult
from falsify.world.space import Sample


class Executor(Protocol):
    """Entered once for a run (its evaluators start and warm up), asked to `map` chunks any
    number of times, exited once (its evaluators end, at once when it exits on an error)."""

    def __enter__(self) -> Executor: ...

    def __exit__(self, exc_type: object, exc: object, tb: object) -> None: ...

    def map(self, chunks: Sequence[list[Sample]]) -> Iterator[list[SampleResult]]:
        """Each chunk's results, in the order of the chunks."""
        ...

    def environments(self) -> list[dict]:
        """The distinct environments (`falsify.executors.environment`) of the processes that
        score, once entered."""
        ...
