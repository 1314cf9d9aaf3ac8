"""One inference process for all workers: they cast scans on the CPUs and send them here; this
process owns the network (on the GPU, where one is asked for) and runs what arrives in batches.

Why: a heavy network on a GPU wants large batches and one CUDA context, while ray casting wants
every CPU core. With the network in each worker, N workers hold N contexts and send batches of
8; here the device sees up to `max_batch` frames at once from all workers together.

- Each worker holds a `RemoteSegmenter` (the Segmenter protocol: spec, model hash, predict)
  whose `predict` puts its scans on the shared request queue and waits on its own reply queue.
- The server takes a request, then whatever else arrives within `wait_s`, up to `max_batch`
  frames, and runs them as one call. On a GPU the call is padded to `max_batch` frames, so
  every frame is computed in a batch of the same size whatever arrived with it (the rows stay
  the same bytes run after run); on the CPU frames run one at a time as in a worker (the
  fastest there, `models/runners/`), so the rows equal the in-worker path's.
- A failure in the network is sent back to the requester and raised there, as in a worker.
"""

from __future__ import annotations

import itertools
import multiprocessing as mp
import queue
import signal
import time
import traceback
from dataclasses import dataclass

import numpy as np

from falsify.errors import FalsifyError
from falsify.executors.evaluator import EvalSettings
from falsify.models.runners import MAX_DEFAULT_THREADS, load_segmenter
from falsify.models.spec import ModelSpec

MAX_BATCH = 32      # frames a device call takes at most (a GPU's batch)
WAIT_S = 0.005      # how long the server waits for more frames after the first request
START_S = 600.0     # how long the executor waits for the server to load the network


@dataclass(frozen=True)
class Answer:
    """The network's answer for one request: classes (B,H,W) and, when asked, train ids."""

    classes: np.ndarray
    train_ids: np.ndarray | None = None


class RemoteSegmenter:
    """The Segmenter a worker holds when the network runs in the inference process."""

    def __init__(self, spec: ModelSpec, model_hash: str, requests, replies, slot: int,
                 train_ids: bool):
        self.spec = spec
        self.model_hash = model_hash
        self._requests, self._replies, self._slot = requests, replies, slot
        self._train_ids = train_ids
        self._ids = itertools.count()

    def predict(self, scans: np.ndarray) -> Answer:
        """Classes (and train ids, for SemanticKITTI scoring) of a batch of scans, from the
        inference process."""
        rid = next(self._ids)
        self._requests.put((self._slot, rid, np.ascontiguousarray(scans, np.float32),
                            self._train_ids))
        got_rid, answer, error = self._replies.get()
        if error is not None:
            raise FalsifyError(f"the inference process failed: {error}")
        if got_rid != rid:   # one request in flight per worker: a mismatch is a bug
            raise RuntimeError(f"inference reply {got_rid} for request {rid}")
        return answer


def serve(settings: EvalSettings, requests, replies: list, ready, max_batch: int,
          wait_s: float) -> None:
    """The inference process: load the network on its device, tell `ready` its spec and hash
    (or the error), then answer requests until a None arrives. On the CPU it takes a thread
    per worker, up to MAX_DEFAULT_THREADS: it is the only process that runs the network."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)   # Ctrl-C is the driver's to handle
    threads = server_threads(settings, len(replies))
    try:
        model = load_segmenter(settings.model, backend=settings.backend, threads=threads,
                               device=settings.device)
    except BaseException as exc:  # noqa: BLE001 - any failure to load is reported, not lost
        ready.put(("error", f"{type(exc).__name__}: {exc}"))
        return
    pad = settings.device == "cuda"
    if pad and hasattr(model, "batch"):
        model.batch = max_batch
    ready.put(("ok", (model.spec, model.model_hash)))
    stop = False
    while not stop:
        first = requests.get()
        if first is None:
            break
        batch = [first]
        frames = len(first[2])
        deadline = time.perf_counter() + wait_s
        while frames < max_batch:
            try:
                nxt = requests.get(timeout=max(deadline - time.perf_counter(), 0.0))
            except queue.Empty:
                break
            if nxt is None:
                stop = True
                break
            batch.append(nxt)
            frames += len(nxt[2])
        _answer(model, batch, replies, max_batch if pad else None)


def server_threads(settings: EvalSettings, workers: int) -> int:
    """The inference process's threads: the settings' on cuda, and for torch and plug-ins on
    the CPU (held at a worker's one thread: torch's kernels sum in another order on two); for
    ONNX Runtime on the CPU one per worker, at most MAX_DEFAULT_THREADS, where it still computes
    the logits of 1 or 2 threads (a worker's). Either way the rows do not depend on --workers."""
    if settings.device == "cuda" or settings.backend != "onnx":
        return settings.threads
    return max(1, min(workers, MAX_DEFAULT_THREADS))


def _answer(model, batch: list, replies: list, pad_to: int | None) -> None:
    """Run the gathered requests as one call (in calls of `pad_to` frames, zero-padded, where
    given) and send each requester its part."""
    scans = np.concatenate([r[2] for r in batch])
    want_ids = any(r[3] for r in batch)
    try:
        classes, train_ids = [], []
        step = pad_to or len(scans)
        for i in range(0, len(scans), step):
            part = scans[i:i + step]
            n = len(part)
            if pad_to and n < pad_to:
                part = np.concatenate([part, np.zeros((pad_to - n, *part.shape[1:]),
                                                      part.dtype)])
            pred = model.predict(part)
            classes.append(np.asarray(pred.classes)[:n])
            if want_ids:
                train_ids.append(np.asarray(pred.train_ids)[:n])
        all_classes = np.concatenate(classes)
        all_ids = np.concatenate(train_ids) if want_ids else None
    except BaseException as exc:  # noqa: BLE001 - sent back to every requester, raised there
        why = f"{type(exc).__name__}: {exc}\n{traceback.format_exc(limit=3)}"
        for slot, rid, _, _ in batch:
            replies[slot].put((rid, None, why))
        return
    start = 0
    for slot, rid, part, wants in batch:
        n = len(part)
        ids = all_ids[start:start + n] if wants and all_ids is not None else None
        replies[slot].put((rid, Answer(all_classes[start:start + n], ids), None))
        start += n


class InferenceServer:
    """Starts the inference process and the queues the workers talk to it through."""

    def __init__(self, settings: EvalSettings, workers: int, max_batch: int = MAX_BATCH,
                 wait_s: float = WAIT_S):
        ctx = mp.get_context("spawn")
        self.requests = ctx.Queue()
        self.replies = [ctx.Queue() for _ in range(workers)]
        self.slots = ctx.Queue()
        for k in range(workers):
            self.slots.put(k)
        self._ready = ctx.Queue()
        self._process = ctx.Process(target=serve, name="falsify-inference", daemon=True,
                                    args=(settings, self.requests, self.replies, self._ready,
                                          max_batch, wait_s))
        self.spec: ModelSpec | None = None
        self.model_hash = ""
        self.threads = server_threads(settings, workers)   # what the process's network runs on

    def start(self) -> None:
        """Start the process and wait until its network is loaded (FalsifyError if it fails)."""
        self._process.start()
        deadline = time.monotonic() + START_S
        while True:
            try:
                status, what = self._ready.get(timeout=1.0)
                break
            except queue.Empty:
                if not self._process.is_alive():
                    raise FalsifyError("the inference process died while loading the network "
                                       f"(exit code {self._process.exitcode})") from None
                if time.monotonic() > deadline:
                    raise FalsifyError("the inference process did not load the network in "
                                       f"{START_S:.0f} s") from None
        if status != "ok":
            self.stop()
            raise FalsifyError(f"the inference process could not load the network: {what}")
        self.spec, self.model_hash = what

    def stop(self) -> None:
        """Tell the process to end and join it (terminate it if it does not)."""
        if self._process.is_alive():
            try:
                self.requests.put(None)
            except (OSError, ValueError):
                pass
            self._process.join(5.0)
            if self._process.is_alive():
                self._process.terminate()
                self._process.join()
        # A worker terminated mid-put may hold a queue's write lock for ever: waiting for our
        # own feeder thread to flush (join_thread) could then hang. Nothing left in the queues
        # is needed once the process has ended, so do not wait for it.
        for q in (self.requests, self.slots, self._ready, *self.replies):
            q.cancel_join_thread()
            q.close()

    def client_args(self) -> tuple:
        """What a worker needs to build its RemoteSegmenter (passed at the worker's start)."""
        return (self.spec, self.model_hash, self.requests, self.replies, self.slots)


def remote_segmenter(settings: EvalSettings, spec: ModelSpec, model_hash: str, requests,
                     replies: list, slots) -> RemoteSegmenter:
    """A worker's RemoteSegmenter on a free reply slot."""
    slot = slots.get()
    return RemoteSegmenter(spec, model_hash, requests, replies[slot], slot,
                           settings.scoring.semantic)
