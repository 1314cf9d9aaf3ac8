"""What the machine itself gives, measured beside the pipeline so that ratios come from one run:
ONNX Runtime's fp32 matrix product on one core and per core with every worker busy, the
network's inference-only rate in 1 and N processes at once, and the resident memory of a
process tree sampled from /proc.

Each multi-process figure runs in spawned processes that wait at a shared barrier, so "N at
once" is measured together, never N x one.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import platform
import queue as queue_module
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np

from falsify.cpu import BF16_UNITS, cpu_flags, cpu_name
from falsify.errors import FalsifyError

# The product the ratio goals use, then a 3x3 convolution's as ONNX Runtime runs it (fire4's
# expand3x3 of SqueezeSeg: 4096 pixels x 32*9 inputs x 128 outputs).
MATMUL_SHAPES: tuple[tuple[int, int, int], ...] = ((1024, 1024, 1024), (4096, 288, 128))
MATMUL_REPEATS = 10
_WAIT = 600.0   # s a process waits at the barrier before it gives up on its siblings


def _child(target: Callable, rank: int, n: int, barrier, results, args: tuple) -> None:
    """Body of each spawned process: its result or its error goes back on the queue."""
    try:
        results.put((rank, "ok", target(rank, n, barrier, *args)))
    except threading.BrokenBarrierError:   # a sibling failed first: its error is the one to tell
        results.put((rank, "broken", "a sibling process failed"))
    except BaseException as exc:   # reported to the parent, which raises
        barrier.abort()
        results.put((rank, "error", f"{type(exc).__name__}: {exc}"))


def in_processes(target: Callable, n: int, args: tuple = (), timeout: float = 1800.0) -> list:
    """target(rank, n, barrier, *args) in `n` spawned processes at once (target must live in a
    module); their results by rank. An error or a dead process raises FalsifyError."""
    ctx = mp.get_context("spawn")
    barrier = ctx.Barrier(n)
    results = ctx.Queue()
    procs = [ctx.Process(target=_child, args=(target, rank, n, barrier, results, args),
                         daemon=True) for rank in range(n)]
    for p in procs:
        p.start()
    got: dict[int, object] = {}
    broken: list[int] = []
    deadline = time.monotonic() + timeout
    try:
        while len(got) + len(broken) < n:
            try:
                rank, status, value = results.get(timeout=1.0)
            except queue_module.Empty:
                dead = [p.exitcode for p in procs if p.exitcode not in (None, 0)]
                if dead:
                    raise FalsifyError(f"a benchmark process died (exit code {dead[0]})") from None
                if time.monotonic() > deadline:
                    raise FalsifyError(f"benchmark processes took over {timeout:.0f} s") from None
                continue
            if status == "error":
                raise FalsifyError(f"benchmark process {rank}: {value}")
            if status == "broken":
                broken.append(rank)
            else:
                got[rank] = value
        if broken:
            raise FalsifyError(f"benchmark process {broken[0]}: a sibling process failed")
    finally:
        for p in procs:
            p.join(timeout=10)
            if p.is_alive():
                p.terminate()
                p.join()
    return [got[r] for r in range(n)]


# -- the machine's matrix product ---------------------------------------------------------------

def _matmul_session(m: int, k: int, n: int, kind: str = "fp32"):
    """The product graph on one ORT thread, and its input A."""
    from falsify.models.runners import cpu_session

    model, a, _ = matmul_graph(m, k, n, kind)
    return cpu_session(model, threads=1), a


def matmul_graph(m: int, k: int, n: int, kind: str = "fp32"
                 ) -> tuple[bytes, np.ndarray, np.ndarray]:
    """A one-node product graph with B a constant (as a network's weights are), an input A, and
    B: fp32 MatMul, or for "int8" MatMulInteger of uint8 A (zero point 128) by int8 B into
    int32, MLAS's integer GEMM (the u8 x s8 path VNNI and AMX speed up, as the int8 network's
    convs use)."""
    from onnx import TensorProto, helper, numpy_helper

    rng = np.random.default_rng(0)
    if kind == "int8":
        # 7-bit weights, as quantisers use for u8 x s8 without VNNI: AVX2's pairwise 16-bit
        # sums saturate on full-range s8 (wrong products on an AMD EPYC), 7 bits never do.
        bb = rng.integers(-64, 64, (k, n), dtype=np.int8)
        b = numpy_helper.from_array(bb, "B")
        zero = [numpy_helper.from_array(np.array(128, np.uint8), "za"),
                numpy_helper.from_array(np.array(0, np.int8), "zb")]
        node = helper.make_node("MatMulInteger", ["A", "B", "za", "zb"], ["Y"])
        types, a = (TensorProto.UINT8, TensorProto.INT32), rng.integers(0, 256, (m, k),
                                                                          dtype=np.uint8)
    else:
        bb = rng.standard_normal((k, n), dtype=np.float32)
        b, zero = numpy_helper.from_array(bb, "B"), []
        node = helper.make_node("MatMul", ["A", "B"], ["Y"])
        types, a = (TensorProto.FLOAT, TensorProto.FLOAT), rng.standard_normal(
            (m, k), dtype=np.float32)
    graph = helper.make_graph(
        [node], "matmul", [helper.make_tensor_value_info("A", types[0], [m, k])],
        [helper.make_tensor_value_info("Y", types[1], [m, n])], [b, *zero])
    # IR 8 is opset 17's own: onnx writes its newest IR by default, which an older
    # onnxruntime beside it refuses (onnx 1.23 writes 14; onnxruntime 1.30 reads up to 13).
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)], ir_version=8)
    return model.SerializeToString(), a, bb


def _best_run(session, a: np.ndarray, repeats: int, barrier=None) -> float:
    """Best seconds of `repeats` products; with a barrier, every repeat starts with the others'."""
    best = float("inf")
    for _ in range(repeats):
        if barrier is not None:
            barrier.wait(_WAIT)
        t0 = time.perf_counter()
        session.run(None, {"A": a})
        best = min(best, time.perf_counter() - t0)
    return best


def _matmul_worker(rank: int, n: int, barrier, shapes, repeats: int, kind: str = "fp32"
                   ) -> tuple[list[float], list[float]]:
    """Rank 0 alone first (the others wait), then all `n` together, repeat by repeat."""
    runs = [_matmul_session(*s, kind=kind) for s in shapes]
    for session, a in runs:
        session.run(None, {"A": a})
    barrier.wait(_WAIT)
    alone = [_best_run(s, a, repeats) for s, a in runs] if rank == 0 else []
    barrier.wait(_WAIT)
    together = [_best_run(s, a, repeats, barrier) for s, a in runs]
    return alone, together


@dataclass(frozen=True)
class MatmulRate:
    """Giga-ops/s (2 per multiply-add) of ONNX Runtime's matrix product on one thread, fp32 or
    int8: one process alone, and each of `processes` processes when all run at once (best of
    `repeats`; products start together)."""

    shapes: tuple[tuple[int, int, int], ...]      # (M, K, N)
    alone_s: tuple[float, ...]                    # best s per product, one process alone
    together_s: tuple[tuple[float, ...], ...]     # [process][shape]: best s, all at once
    processes: int
    repeats: int
    library: str
    kind: str = "fp32"

    def gflops_1_core(self, k: int = 0) -> float:
        m, kk, n = self.shapes[k]
        return 2 * m * kk * n / self.alone_s[k] / 1e9

    def gflops_per_core(self, k: int = 0) -> float:
        """Mean over the processes of each one's rate while all ran."""
        m, kk, n = self.shapes[k]
        return float(np.mean([2 * m * kk * n / t[k] / 1e9 for t in self.together_s]))

    def to_json(self) -> dict:
        names = [f"{m}x{k}x{n}" for m, k, n in self.shapes]
        unit = "gflops" if self.kind == "fp32" else "gops"   # integer ops are no FLOPs
        return {
            "library": self.library, "kind": self.kind, "threads_per_process": 1,
            "repeats": self.repeats, "shape": names[0],
            f"{unit}_1_core": round(self.gflops_1_core(), 2),
            f"{unit}_per_core_all_at_once": round(self.gflops_per_core(), 2),
            "processes": self.processes, "processes_from": "--workers",
            "cpus": os.cpu_count(),
            "shapes": {name: {f"{unit}_1_core": round(self.gflops_1_core(k), 2),
                              f"{unit}_per_core_all_at_once": round(self.gflops_per_core(k), 2)}
                       for k, name in enumerate(names)},
        }


def matmul_rate(processes: int, shapes=MATMUL_SHAPES, repeats: int = MATMUL_REPEATS,
                kind: str = "fp32") -> MatmulRate:
    """The machine's fp32 (or int8) matrix product through ONNX Runtime's own kernels (the
    library the network runs on), one core alone and `processes` cores at once."""
    import onnxruntime

    out = in_processes(_matmul_worker, processes, (tuple(shapes), repeats, kind))
    return MatmulRate(tuple(shapes), tuple(out[0][0]), tuple(tuple(t) for _, t in out),
                      processes, repeats, f"onnxruntime {onnxruntime.__version__} (MLAS)", kind)




def _bf16_worker(rank: int, n: int, barrier, shape, repeats: int) -> float:
    import torch
    torch.set_num_threads(1)
    m, k, nn = shape
    g = torch.Generator().manual_seed(0)
    a = torch.randn(m, k, generator=g).to(torch.bfloat16)
    b = torch.randn(k, nn, generator=g).to(torch.bfloat16)
    torch.matmul(a, b)
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        torch.matmul(a, b)
        best = min(best, time.perf_counter() - t0)
    return 2 * m * k * nn / best / 1e9


def bf16_matmul_rate(shape: tuple[int, int, int] = MATMUL_SHAPES[0],
                     repeats: int = MATMUL_REPEATS) -> dict:
    """GFLOP/s of a bf16 product on one thread through torch (oneDNN: AVX512-BF16 or AMX where
    the CPU has them), in a process of its own; where the CPU has no bf16 units or torch is not
    installed, says so instead of a figure (bf16 emulated in fp32 units is no peak)."""
    units = sorted(cpu_flags() & set(BF16_UNITS))
    m, k, n = shape
    out: dict = {"kind": "bf16", "shape": f"{m}x{k}x{n}", "threads_per_process": 1,
                 "cpu_units": units, "gflops_1_core": None}
    if not units:
        return {**out, "note": "no bf16 units in this CPU's flags (" + ", ".join(BF16_UNITS)
                + ")"}
    try:
        import torch
    except ImportError:
        return {**out, "note": "torch is not installed (pip install \"falsify[torch]\")"}
    rate = in_processes(_bf16_worker, 1, (shape, repeats))[0]
    return {**out, "gflops_1_core": round(rate, 2), "library": f"torch {torch.__version__}"}


# -- the network's inference alone --------------------------------------------------------------

def _predict_all(seg, frames: np.ndarray, batch: int) -> tuple[int, float, float]:
    """Frames predicted and the perf_counter at start and end (comparable across processes)."""
    t0 = time.perf_counter()
    for i in range(0, len(frames), batch):
        seg.predict(frames[i:i + batch])
    return len(frames), t0, time.perf_counter()


def _inference_worker(rank: int, n: int, barrier, model: str | None, frames_path: str,
                      batch: int) -> tuple[tuple | None, tuple]:
    """Rank 0 predicts every frame alone (the others wait), then each its share, all at once."""
    from falsify.models.runners import load_segmenter

    seg = load_segmenter(model, threads=1)
    frames = np.load(frames_path, mmap_mode="r" if rank else None)
    mine = np.ascontiguousarray(frames[rank::n])
    seg.predict(mine[:1])
    barrier.wait(_WAIT)
    alone = _predict_all(seg, frames, batch) if rank == 0 else None
    del frames
    barrier.wait(_WAIT)
    return alone, _predict_all(seg, mine, batch)


@dataclass(frozen=True)
class InferenceRates:
    """Inference alone (one ORT thread a process, as a grid worker runs it): one process, and
    `processes` processes at once on shares of the same frames."""

    frames_1: int
    seconds_1: float
    processes: int
    frames_n: int
    seconds_n: float      # first start to last end over the processes

    @property
    def rate_1(self) -> float:
        return self.frames_1 / self.seconds_1

    @property
    def rate_n(self) -> float:
        return self.frames_n / self.seconds_n


def inference_rates(model: str | None, frames: np.ndarray, processes: int, batch: int,
                    tmp: Path) -> InferenceRates:
    """Frames/s of the network alone in 1 and in `processes` spawned processes at once."""
    path = tmp / "frames.npy"
    np.save(path, np.asarray(frames, np.float32))
    out = in_processes(_inference_worker, processes, (model, str(path), batch))
    path.unlink()
    n1, a, b = out[0][0]
    parts = [t for _, t in out]
    return InferenceRates(n1, b - a, processes, sum(p[0] for p in parts),
                          max(p[2] for p in parts) - min(p[1] for p in parts))


# -- resident memory of a process tree ----------------------------------------------------------

_PAGE = os.sysconf("SC_PAGE_SIZE") if hasattr(os, "sysconf") else 4096


def _children(pid: int) -> list[int]:
    """Direct children of a process from /proc (its threads' children files, else a scan)."""
    try:
        tasks = list(Path(f"/proc/{pid}/task").iterdir())
    except OSError:
        return []   # gone meanwhile
    if Path(f"/proc/{pid}/task/{pid}/children").exists():
        out = []
        for t in tasks:
            try:
                out += [int(c) for c in (t / "children").read_text().split()]
            except OSError:
                continue   # a thread that ended meanwhile
        return out
    out = []   # a kernel without children files: every process's parent
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except (OSError, IndexError):
            continue
        if int(fields[1]) == pid:
            out.append(int(stat.parent.name))
    return out


class MemorySample(NamedTuple):
    """One look at a process tree."""

    t: float                # perf_counter
    rss: int                # bytes, RSS summed over the processes
    processes: int
    pss: int | None         # bytes, PSS summed (shared pages split among their users); None
    # when not read this time
    root_rss: int           # bytes, RSS of the tree's root (the driver) alone
    child_rss: int = 0      # bytes, RSS of the largest descendant (a worker) alone


def _pss(pid: int) -> int | None:
    """Proportional set size in bytes (None without /proc/PID/smaps_rollup)."""
    try:
        for line in Path(f"/proc/{pid}/smaps_rollup").read_text().splitlines():
            if line.startswith("Pss:"):
                return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        return None
    return None


def tree_memory(pid: int | None = None, pss: bool = True) -> MemorySample:
    """A process and all its descendants: RSS summed (pages shared between them count once per
    process: an upper bound), PSS summed (each shared page split among its users; about 1 ms a
    500 MB process, so optional) and how many processes that is."""
    root = pid or os.getpid()
    todo, rss, pss_sum, count, root_rss, child_rss = [root], 0, 0, 0, 0, 0
    for_all_pss = pss
    while todo:
        p = todo.pop()
        try:
            r = int(Path(f"/proc/{p}/statm").read_text().split()[1]) * _PAGE
        except (OSError, IndexError, ValueError):
            continue   # gone meanwhile
        rss += r
        root_rss = r if p == root else root_rss
        child_rss = max(child_rss, r) if p != root else child_rss
        q = _pss(p) if for_all_pss else None
        for_all_pss = for_all_pss and q is not None
        pss_sum += q or 0
        count += 1
        todo += _children(p)
    return MemorySample(time.perf_counter(), rss, count, pss_sum if for_all_pss else None,
                        root_rss, child_rss)


@dataclass(frozen=True)
class MemoryUse:
    """Summed RSS of a process tree: the peak over all samples, and the means over the first and
    last quarter of the samples in the steady window (so growth with run length shows; None
    when the window holds fewer than 4 samples); beside it the summed PSS's peak."""

    peak_bytes: int         # over every sample
    window_peak_bytes: int | None
    early_bytes: float | None
    late_bytes: float | None
    samples: int            # in the steady window
    interval_s: float
    seconds: float          # length of the steady window
    max_processes: int
    peak_pss_bytes: int | None = None       # over the samples that read PSS
    pss_interval_s: float | None = None
    root_at_peak_bytes: int | None = None   # the driver's own RSS in the peak sample
    worker_peak_bytes: int | None = None    # the largest single worker's RSS, over every sample

    def to_json(self) -> dict:
        def mb(b: float | None) -> float | None:
            return None if b is None else round(b / (1 << 20), 1)
        return {"peak_rss_mb": mb(self.peak_bytes),
                "window_peak_rss_mb": mb(self.window_peak_bytes),
                "early_rss_mb": mb(self.early_bytes),
                "late_rss_mb": mb(self.late_bytes),
                "late_over_early": None if self.early_bytes is None or self.late_bytes is None
                else round(self.late_bytes / self.early_bytes, 3),
                "peak_pss_mb": mb(self.peak_pss_bytes), "pss_interval_s": self.pss_interval_s,
                "driver_rss_mb_at_peak": mb(self.root_at_peak_bytes),
                "worker_peak_rss_mb": mb(self.worker_peak_bytes),
                "samples": self.samples, "interval_s": self.interval_s,
                "window_s": round(self.seconds, 2), "max_processes": self.max_processes,
                "what": "sum of RSS of this process and all its descendants, sampled from "
                        "/proc; early/late: mean over the first/last quarter of the window; "
                        "PSS splits pages shared between processes (libraries) among them"}


class RssSampler:
    """Samples `tree_memory` of this process every `interval` s in a thread while in the `with`
    block, PSS every `pss_every`-th time (Linux /proc; elsewhere it records nothing and
    `summary` is None)."""

    def __init__(self, interval: float = 0.05, pss_every: int = 10):
        self.interval = interval
        self.pss_every = pss_every
        self.samples: list[MemorySample] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True, name="rss-sampler")
        self.available = Path(f"/proc/{os.getpid()}/statm").exists()

    def _run(self) -> None:
        k = 0
        while True:
            self.samples.append(tree_memory(pss=k % self.pss_every == 0))
            k += 1
            if self._stop.wait(self.interval):
                return

    def __enter__(self) -> RssSampler:
        if self.available:
            self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join()

    def summary(self, start: float | None = None, stop: float | None = None
                ) -> MemoryUse | None:
        """Peak over every sample; early and late means over the samples in [start, stop]."""
        if not self.samples:
            return None
        lo = -np.inf if start is None else start
        hi = np.inf if stop is None else stop
        window = [s for s in self.samples if lo <= s.t <= hi]
        q = len(window) // 4
        peak = max(self.samples, key=lambda s: s.rss)
        pss = [s.pss for s in self.samples if s.pss is not None]
        return MemoryUse(
            peak_bytes=peak.rss,
            window_peak_bytes=max((s.rss for s in window), default=None),
            early_bytes=float(np.mean([s.rss for s in window[:q]])) if q else None,
            late_bytes=float(np.mean([s.rss for s in window[-q:]])) if q else None,
            samples=len(window), interval_s=self.interval,
            seconds=window[-1].t - window[0].t if window else 0.0,
            max_processes=max(s.processes for s in self.samples),
            peak_pss_bytes=max(pss, default=None),
            pss_interval_s=round(self.interval * self.pss_every, 3),
            root_at_peak_bytes=peak.root_rss,
            worker_peak_bytes=max((s.child_rss for s in self.samples), default=None) or None)


def machine() -> dict:
    """The CPU by name (figures differ 2x between CPUs), its core count and Python."""
    return {"cpus": os.cpu_count(), "python": platform.python_version(),
            "processor": platform.processor() or platform.machine(), "cpu": cpu_name()}
