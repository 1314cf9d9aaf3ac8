"""Ray executor: warm evaluator actors on a Ray cluster, fed by the driver, re-run on death.

The driver keeps the SQLite store and the sampler; actors only score chunks of samples and hand
back SampleResults. The model file, its spec and the user car meshes travel through Ray's object
store as bytes named by their sha256, and each actor writes them to a cache folder of its node
under that hash, so a worker node needs nothing but the package. A chunk whose actor dies is
scored again on a replacement actor; results are yielded in chunk order, so the rows written are
the same as with local processes. Several driver threads may call `map` at once (a search
running combinations concurrently): the actors are shared through one queue of idle actors.
"""

from __future__ import annotations

import dataclasses
import hashlib
import os
import socket
import tempfile
import threading
from collections import deque
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

from falsify.errors import FalsifyError
from falsify.models.runner import resolve_model
from falsify.models.spec import spec_path_for
from falsify.pipeline import EvalSettings, Evaluator
from falsify.space import Sample
from falsify.store import SampleResult

EXECUTORS = ("process", "ray")
MAX_ATTEMPTS = 3   # a chunk whose actors die this many times stops the run (a crashing sample)
RAY_EXTRA = 'pip install "falsify[ray]"'


def import_ray():
    """The ray module, or a FalsifyError saying how to install it."""
    try:
        import ray
    except ImportError:
        raise FalsifyError(f"--executor ray: ray is not installed; {RAY_EXTRA}") from None
    return ray


def check_address(address: str | None, executor: str) -> None:
    """A Ray head address (HOST:PORT, ray://HOST:PORT or auto) that answers; else FalsifyError.

    Only `auto` is left to Ray: a HOST:PORT is probed with a plain TCP connect (3 s), so a typo
    fails in seconds with one line instead of Ray's long retry loop."""
    if address is None:
        return
    if executor != "ray":
        raise FalsifyError(f"--address {address}: only with --executor ray")
    if address == "auto":
        return
    hostport = address.removeprefix("ray://")
    host, sep, port = hostport.rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise FalsifyError(f"--address {address!r}: expected HOST:PORT (the head's GCS port, "
                           "e.g. 10.0.0.1:6379), ray://HOST:PORT or auto")
    try:
        with socket.create_connection((host, int(port)), timeout=3.0):
            pass
    except OSError as exc:
        why = exc.strerror or type(exc).__name__
        raise FalsifyError(f"--address {address}: no Ray head answers there ({why}); start one "
                           "with `ray start --head` or check the address") from None


@dataclass(frozen=True)
class Blob:
    """A file's bytes named by their sha256, as shipped to the actors."""

    sha256: str
    name: str
    data: bytes

    @classmethod
    def of(cls, path: Path) -> Blob:
        data = path.read_bytes()
        return cls(hashlib.sha256(data).hexdigest(), path.name, data)


def cache_dir() -> Path:
    """Where an actor keeps shipped files, one folder per content hash."""
    return Path(os.environ.get("FALSIFY_CACHE", Path(tempfile.gettempdir()) / "falsify-blobs"))


def materialise(blob: Blob) -> Path:
    """The blob's file in this node's cache, written once (atomically) and checked by hash."""
    folder = cache_dir() / blob.sha256
    path = folder / blob.name
    if not path.is_file() or hashlib.sha256(path.read_bytes()).hexdigest() != blob.sha256:
        folder.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=folder)
        with os.fdopen(fd, "wb") as f:
            f.write(blob.data)
        os.replace(tmp, path)
    return path


def model_files(settings: EvalSettings) -> tuple[Path, Path]:
    """The model file the settings load (as load_segmenter resolves it) and its spec."""
    p = resolve_model(settings.model, settings.backend)
    return p, spec_path_for(p)


@dataclass(frozen=True)
class Shipment:
    """What an actor needs besides the package: settings with paths replaced by blobs."""

    settings: EvalSettings
    model: Blob
    spec: Blob
    cars: dict[str, Blob]

    @classmethod
    def of(cls, settings: EvalSettings) -> Shipment:
        model, spec = model_files(settings)
        cars = {n: Blob.of(c.file) for n, c in settings.space.user_cars.items()}
        return cls(settings, Blob.of(model), Blob.of(spec), cars)

    def local_settings(self) -> EvalSettings:
        """The settings with every file pointing into this node's cache."""
        model = materialise(self.model)
        spec = materialise(self.spec)
        if spec != spec_path_for(model):   # the spec must sit beside the model as <stem>.json
            beside = spec_path_for(model)
            if not beside.is_file():
                beside.write_bytes(self.spec.data)
        space = self.settings.space
        cars = {n: dataclasses.replace(c, file=materialise(self.cars[n]))
                for n, c in space.user_cars.items()}
        return dataclasses.replace(self.settings, model=str(model),
                                   space=dataclasses.replace(space, user_cars=cars))


class EvalActor:
    """A Ray actor: one warm Evaluator built from a Shipment."""

    def __init__(self, shipment: Shipment):
        self.evaluator = Evaluator(shipment.local_settings())
        self.model_hash = self.evaluator.model_hash

    def ready(self) -> str:
        return self.model_hash

    def score(self, samples: list[Sample]) -> list[SampleResult]:
        return self.evaluator.score_batch(samples)


class RayExecutor:
    """`workers` EvalActors on the Ray cluster at `address` (None: the running instance, else a
    new local one); `map` scores chunks in order and re-runs a chunk whose actor died."""

    def __init__(self, settings: EvalSettings, workers: int, address: str | None = None,
                 max_attempts: int = MAX_ATTEMPTS):
        self.settings = settings
        self.workers = workers
        self.address = address
        self.max_attempts = max_attempts
        self.ray = import_ray()
        self.actors: list = []
        self.reruns = 0            # chunks scored again after their actor died
        self.replaced = 0          # actors started to replace dead ones
        self.in_flight: dict = {}  # task ref -> (chunk index, actor), of every caller
        self._idle: deque = deque()   # actors no caller holds
        self._cond = threading.Condition()   # guards the above; told when an actor is freed
        self._closed = False
        self._started_ray = False
        self._shipment_ref = None
        self._actor_cls = None

    def __enter__(self) -> RayExecutor:
        ray = self.ray
        if not ray.is_initialized():
            kw = {"address": self.address} if self.address else {
                "num_cpus": self.workers, "include_dashboard": False}
            try:
                ray.init(log_to_driver=False, logging_level="ERROR", **kw)
            except (ConnectionError, RuntimeError, ValueError) as exc:
                raise FalsifyError(f"--address {self.address}: cannot join the Ray cluster "
                                   f"({exc})") from None
            self._started_ray = True
        self._shipment_ref = ray.put(Shipment.of(self.settings))
        self._actor_cls = ray.remote(num_cpus=1, max_restarts=0)(EvalActor)
        self.actors = [self._new_actor() for _ in range(self.workers)]
        ray.get([a.ready.remote() for a in self.actors])
        self._idle = deque(self.actors)
        return self

    def __exit__(self, *exc) -> None:
        with self._cond:
            self._closed = True
            actors, self.actors = self.actors, []
            self._idle.clear()
            self._cond.notify_all()
        for a in actors:
            self.ray.kill(a)
        if self._started_ray:
            self.ray.shutdown()

    def _new_actor(self):
        return self._actor_cls.remote(self._shipment_ref)

    def map(self, chunks: Sequence[list[Sample]]) -> Iterator[list[SampleResult]]:
        """Results of each chunk, in chunk order, as soon as every earlier chunk is done.

        Safe to call from several threads at once. A caller takes an idle actor for each chunk
        and waits only on its own tasks; it waits for an actor to come free only while it has
        no task in flight, and hands each actor back as soon as its task is done (and all it
        holds when it stops early), so callers never wait on each other's results."""
        ray = self.ray
        todo = deque(range(len(chunks)))
        attempts = [0] * len(chunks)
        mine: dict = {}            # this call's tasks: ref -> (chunk index, actor)
        done: dict[int, list[SampleResult]] = {}
        nxt = 0
        try:
            while nxt < len(chunks):
                while todo:
                    actor = self._take(wait=not mine)
                    if actor is None:
                        break
                    i = todo.popleft()
                    attempts[i] += 1
                    ref = actor.score.remote(chunks[i])
                    mine[ref] = (i, actor)
                    with self._cond:
                        self.in_flight[ref] = (i, actor)
                ready, _ = ray.wait(list(mine), num_returns=1)
                for ref in ready:
                    i, actor = mine.pop(ref)
                    with self._cond:
                        self.in_flight.pop(ref, None)
                    try:
                        done[i] = ray.get(ref)
                    except ray.exceptions.RayActorError as exc:
                        if attempts[i] >= self.max_attempts:
                            raise FalsifyError(f"--executor ray: a chunk of {len(chunks[i])} "
                                               f"samples (first {chunks[i][0].as_dict()}) "
                                               f"killed its actor {attempts[i]} times: "
                                               f"{exc}") from None
                        self._replace(actor)
                        todo.appendleft(i)
                        continue
                    self._give(actor)
                while nxt in done:
                    yield done.pop(nxt)
                    nxt += 1
        finally:
            # Stopped early (an error here or in the caller): hand back what this call holds;
            # a task still running on an actor only delays the next task sent to it.
            for ref, (_, actor) in mine.items():
                with self._cond:
                    self.in_flight.pop(ref, None)
                self._give(actor)

    def _take(self, wait: bool):
        """An idle actor, taken from the queue; None if none is idle and not `wait`."""
        with self._cond:
            while not self._idle:
                if self._closed:
                    raise FalsifyError("--executor ray: the executor was shut down")
                if not wait:
                    return None
                self._cond.wait(timeout=1.0)
            return self._idle.popleft()

    def _give(self, actor) -> None:
        """Hand an actor back to the idle queue (unless it was replaced or already there)."""
        with self._cond:
            if actor in self.actors and actor not in self._idle:
                self._idle.append(actor)
                self._cond.notify()

    def _replace(self, dead) -> None:
        """Drop a dead actor and queue a new one in its place (once, however many callers saw it
        die); any other task it held is re-run when its error arrives."""
        with self._cond:
            self.reruns += 1
            if dead not in self.actors:
                return
            self.actors.remove(dead)
            if dead in self._idle:
                self._idle.remove(dead)
            fresh = self._new_actor()
            self.actors.append(fresh)
            self._idle.append(fresh)
            self.replaced += 1
            self._cond.notify()
