"""Ray executor: warm evaluator actors on a Ray cluster, fed by the driver, re-run on death.

The driver keeps the SQLite store and the sampler; actors only score chunks of samples and hand
back SampleResults. The model file, its spec and the user car meshes travel through Ray's object
store as bytes named by their sha256, and each actor writes them to a cache folder of its node
under that hash, so a worker node needs nothing but the package. A chunk whose actor dies is
scored again on a replacement actor; results are yielded in chunk order, so the rows written are
the same as with local processes. An actor that cannot build its Evaluator reports why instead
of dying (Ray would keep only the text of its traceback): the user's input (a FalsifyError) stops
the run with one line, anything else is raised as an ActorCrash with the actor's traceback.
Several driver threads may call `map` at once (a search running combinations concurrently):
the actors are shared through one queue of idle actors.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import os
import re
import signal
import socket
import tempfile
import threading
import traceback
from collections import deque
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

from falsify.errors import FalsifyError
from falsify.executors.environment import environment
from falsify.executors.evaluator import EvalSettings, Evaluator
from falsify.models.plugin import absolute_ref, is_plugin
from falsify.models.runners import resolve_model
from falsify.models.spec import spec_path_for
from falsify.results.samples import SampleResult
from falsify.world.space import Sample

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


class ActorCrash(RuntimeError):
    """An actor failed to start for a reason that is not the user's input (a bug in falsify, a
    process killed by the node); the first line says what, the actor's traceback follows."""


@dataclass(frozen=True)
class Blob:
    """A file's bytes named by their sha256, as shipped to the actors, with the driver's path
    (`source`) so that an actor's error about its copy can name the user's file."""

    sha256: str
    name: str
    data: bytes
    source: str = ""

    @classmethod
    def of(cls, path: Path) -> Blob:
        data = path.read_bytes()
        return cls(hashlib.sha256(data).hexdigest(), path.name, data, str(path))

    def cached(self, folder: str | None = None) -> Path:
        """Where `materialise` puts it on this node: in `folder` of the cache (default: the
        folder named by its own hash)."""
        return cache_dir() / (folder or self.sha256) / self.name


def cache_dir() -> Path:
    """Where an actor keeps shipped files, one folder per content hash."""
    return Path(os.environ.get("FALSIFY_CACHE", Path(tempfile.gettempdir()) / "falsify-blobs"))


def materialise(blob: Blob, folder: str | None = None) -> Path:
    """The blob's file in this node's cache (see `Blob.cached`), written once (atomically) and
    checked by hash; FalsifyError naming FALSIFY_CACHE when the folder cannot be written."""
    path = blob.cached(folder)
    folder = path.parent
    if not path.is_file() or hashlib.sha256(path.read_bytes()).hexdigest() != blob.sha256:
        try:
            folder.mkdir(parents=True, exist_ok=True)
            fd, tmp = tempfile.mkstemp(dir=folder)
            with os.fdopen(fd, "wb") as f:
                f.write(blob.data)
            os.replace(tmp, path)
        except OSError as exc:
            raise FalsifyError(f"FALSIFY_CACHE: cannot write {blob.name} to {folder} "
                               f"({exc.strerror or exc}); set FALSIFY_CACHE to a writable "
                               "folder on every Ray node") from None
    return path


def model_files(settings: EvalSettings) -> tuple[Path, Path] | None:
    """The model file the settings load (as load_segmenter resolves it) and its spec; None for
    a plug-in (MODULE:FACTORY), which every node imports as named: not shipped."""
    if is_plugin(settings.model):
        return None
    p = resolve_model(settings.model, settings.backend)
    return p, spec_path_for(p)


@dataclass(frozen=True)
class Shipment:
    """What an actor needs besides the package: settings with paths replaced by blobs."""

    settings: EvalSettings
    model: Blob | None      # None: a plug-in, imported by each node as named
    spec: Blob | None
    cars: dict[str, Blob]

    @classmethod
    def of(cls, settings: EvalSettings) -> Shipment:
        files = model_files(settings)
        cars = {n: Blob.of(c.file) for n, c in settings.space.user_cars.items()}
        if files is None:   # a file plug-in by its absolute path: actors start elsewhere
            settings = dataclasses.replace(settings, model=absolute_ref(str(settings.model)))
            return cls(settings, None, None, cars)
        return cls(settings, Blob.of(files[0]), Blob.of(files[1]), cars)

    @property
    def model_folder(self) -> str:
        """The cache folder of the model and its spec (<stem>.json beside it), named by both
        hashes: the same network with an edited spec must not find the old spec there."""
        assert self.model is not None and self.spec is not None
        return f"{self.model.sha256}-{self.spec.sha256}"

    def local_settings(self) -> EvalSettings:
        """The settings with every file pointing into this node's cache."""
        model = self.settings.model
        if self.model is not None and self.spec is not None:
            model = str(materialise(self.model, self.model_folder))
            materialise(self.spec, self.model_folder)   # <stem>.json: load_segmenter's spec
        space = self.settings.space
        cars = {n: dataclasses.replace(c, file=materialise(self.cars[n]))
                for n, c in space.user_cars.items()}
        return dataclasses.replace(self.settings, model=model,
                                   space=dataclasses.replace(space, user_cars=cars))

    def driver_names(self, text: str) -> str:
        """`text` with this node's cached copies named by the driver's paths."""
        copies = {str(b.cached()): b.source for b in self.cars.values()}
        for b in (self.model, self.spec):
            if b is not None:
                copies[str(b.cached(self.model_folder))] = b.source
        for copy in sorted(copies, key=len, reverse=True):
            text = text.replace(copy, copies[copy])
        return text


@dataclass(frozen=True)
class StartFailure:
    """Why an actor could not build its Evaluator, as plain data for the driver."""

    node: str
    user_input: bool    # a FalsifyError (the user's input): exit 2; else a crash
    error: str          # the exception's type, e.g. "FalsifyError"
    message: str        # one line, the driver's file names in place of the node's copies
    traceback: str

    @classmethod
    def of(cls, exc: Exception, shipment: Shipment) -> StartFailure:
        message = " ".join(line.strip() for line in str(exc).splitlines() if line.strip())
        return cls(socket.gethostname(), isinstance(exc, FalsifyError), type(exc).__name__,
                   shipment.driver_names(message or repr(exc)),
                   shipment.driver_names("".join(traceback.format_exception(exc))))

    def exception(self) -> Exception:
        """A FalsifyError for the user's input, else an ActorCrash carrying the traceback."""
        where = f"--executor ray: an actor on {self.node}"
        if self.user_input:
            return FalsifyError(f"{where} could not start: {self.message}")
        return ActorCrash(f"{where} crashed while starting: {self.error}: {self.message}\n\n"
                          f"the actor's traceback:\n{self.traceback}")


class EvalActor:
    """A Ray actor: one warm Evaluator built from a Shipment. A failure to build it is kept and
    told by `ready` rather than raised: Ray keeps only the text of a constructor's exception,
    and the driver must tell the user's input from a crash."""

    def __init__(self, shipment: Shipment):
        self.evaluator: Evaluator | None = None
        self.failure: StartFailure | None = None
        try:
            self.evaluator = self.build(shipment)
        except Exception as exc:   # any: ready() tells the driver which kind
            self.failure = StartFailure.of(exc, shipment)

    def build(self, shipment: Shipment) -> Evaluator:
        """The warm Evaluator on this node's copies of the shipped files."""
        return Evaluator(shipment.local_settings())

    def ready(self) -> str | StartFailure:
        """The model's hash once the Evaluator is built, else why it could not be."""
        return self.failure if self.evaluator is None else self.evaluator.model_hash

    def environment(self) -> dict:
        """This actor's environment (its node's versions and CPU), ray's version included."""
        assert self.evaluator is not None
        settings = self.evaluator.settings
        threads = getattr(self.evaluator.model, "threads", settings.threads)
        return environment(settings.backend, settings.device, threads, ray=True)

    def score(self, samples: list[Sample]) -> list[SampleResult]:
        if self.evaluator is None:   # the driver stops at ready(); never given a chunk
            raise RuntimeError(f"actor never started: {self.failure}")
        return self.evaluator.score_batch(samples)


@contextlib.contextmanager
def keep_stop_handlers() -> Iterator[None]:
    """Put SIGTERM's and SIGINT's handlers back after the block: ray.init installs its own,
    which ends the driver at once (exit 15) instead of stopping the run cleanly with its
    resume command."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    saved = {sig: signal.getsignal(sig) for sig in (signal.SIGTERM, signal.SIGINT)}
    try:
        yield
    finally:
        for sig, handler in saved.items():
            if handler is not None:
                signal.signal(sig, handler)


class RayExecutor:
    """`workers` EvalActors on the Ray cluster at `address` (None: the running instance, else a
    new local one); `map` scores chunks in order and re-runs a chunk whose actor died. `actor`
    is the actor class (a subclass of EvalActor, e.g. one that fails to start in a test)."""

    def __init__(self, settings: EvalSettings, workers: int, address: str | None = None,
                 max_attempts: int = MAX_ATTEMPTS, actor: type[EvalActor] = EvalActor):
        self.settings = settings
        self.workers = workers
        self.address = address
        self.max_attempts = max_attempts
        self.actor = actor
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
        self._environments: list[dict] = []   # the actors' distinct environments

    def __enter__(self) -> RayExecutor:
        """Join or start Ray and wait until every actor is warm; on any failure the actors are
        killed and a Ray instance started here is shut down before the error is raised."""
        ray = self.ray
        if not ray.is_initialized():
            # Without --address a new local instance, as documented: Ray's default would join
            # the machine's latest `ray start` cluster (and refuse num_cpus there).
            kw = {"address": self.address} if self.address else {
                "address": "local", "num_cpus": self.workers, "include_dashboard": False}
            try:
                with keep_stop_handlers():
                    ray.init(log_to_driver=False, logging_level="ERROR", **kw)
            except (ConnectionError, RuntimeError, ValueError) as exc:
                where = (f"--address {self.address}: cannot join the Ray cluster"
                         if self.address else "--executor ray: cannot start a local Ray instance")
                raise FalsifyError(f"{where} ({exc})") from None
            self._started_ray = True
        try:
            self._shipment_ref = ray.put(Shipment.of(self.settings))
            self._actor_cls = ray.remote(num_cpus=1, max_restarts=0)(self.actor)
            self.actors = [self._new_actor() for _ in range(self.workers)]
            starting = {a.ready.remote(): a for a in self.actors}
            while starting:   # the first failure stops the wait (the others are killed)
                done, _ = ray.wait(list(starting), num_returns=1)
                for ref in done:
                    starting.pop(ref)
                    try:
                        self._check_started(ref)
                    except ray.exceptions.RayActorError as exc:
                        raise self._died_starting(exc) from None
            self._idle = deque(self.actors)
            self._note_environments(self.actors)
        except BaseException:
            self.__exit__()
            raise
        return self

    def _note_environments(self, actors: list) -> None:
        """Keep the distinct environments that `actors` report."""
        for env in self.ray.get([a.environment.remote() for a in actors]):
            with self._cond:
                if env not in self._environments:
                    self._environments.append(env)

    def environments(self) -> list[dict]:
        """The distinct environments of the actors that have scored or may score (those started
        to replace dead ones too), in the order first seen."""
        with self._cond:
            return list(self._environments)

    def __exit__(self, *exc) -> None:
        with self._cond:
            self._closed = True
            actors, self.actors = self.actors, []
            self._idle.clear()
            self._cond.notify_all()
        for a in actors:
            self.ray.kill(a)
        self.in_flight = {}
        if self._started_ray:
            self.ray.shutdown()
            self._started_ray = False

    def _new_actor(self):
        return self._actor_cls.remote(self._shipment_ref)

    def _check_started(self, ref) -> None:
        """Nothing if the actor whose ready() is `ref` is warm; else the FalsifyError (the user's
        input) or ActorCrash of its StartFailure. Ray's RayActorError if its process died."""
        got = self.ray.get(ref)
        if isinstance(got, StartFailure):
            raise got.exception()

    @staticmethod
    def _died_starting(exc: Exception) -> ActorCrash:
        """An actor that could not report: its class failed to load on the node (falsify not
        installed there: the exception's line first) or its process died (killed, out of
        memory: Ray's exit detail first); Ray's whole message follows."""
        lines = [line.strip() for line in str(exc).splitlines() if line.strip()]
        detail = re.search(r"Worker exit detail: ([^.]*)", str(exc))
        if getattr(exc, "actor_init_failed", False) and lines:
            why = lines[-1]
        else:
            why = "its process died" + (f" ({detail.group(1)})" if detail else "")
        return ActorCrash(f"--executor ray: an actor died while starting: {why}\n\n{exc}")

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
        """Drop a dead actor and start one in its place (once, however many callers saw it die);
        it takes chunks once its start is checked: a failure to start stops the run, a death
        while starting is retried up to max_attempts. Any other task the dead one held is re-run
        when its error arrives."""
        with self._cond:
            self.reruns += 1
            if dead not in self.actors:
                return
            self.actors.remove(dead)
            if dead in self._idle:
                self._idle.remove(dead)
        for attempt in range(1, self.max_attempts + 1):
            fresh = self._new_actor()
            with self._cond:
                self.replaced += 1
            try:
                self._check_started(fresh.ready.remote())
                self._note_environments([fresh])
                break
            except self.ray.exceptions.RayActorError as exc:
                if attempt == self.max_attempts:
                    raise self._died_starting(exc) from None
            except BaseException:
                self.ray.kill(fresh)
                raise
        with self._cond:
            if self._closed:
                self.ray.kill(fresh)
                return
            self.actors.append(fresh)
            self._idle.append(fresh)
            self._cond.notify()
