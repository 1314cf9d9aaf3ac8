"""Speed and agreement of the model variants (torch fp32, ORT fp32, ORT int8, ORT fp16)."""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np

from falsify.errors import FalsifyError
from falsify.models.runners import OnnxSegmenter, Prediction, TorchSegmenter
from falsify.models.spec import spec_path_for


def car_iou(pred: np.ndarray, truth: np.ndarray) -> float:
    """Pooled car IoU (class 1) over all pixels; nan if neither has a car."""
    p, t = pred == 1, truth == 1
    union = int((p | t).sum())
    return float((p & t).sum() / union) if union else float("nan")


def _time(run, scans: np.ndarray, repeats: int, timed: int) -> tuple[float, Prediction]:
    """Best seconds per frame over `repeats` runs of the first `timed` frames, and the
    predictions of every frame (one pass): the time needs a few frames, the agreement all."""
    run(scans[:1])  # warm-up
    best = float("inf")
    for _ in range(max(1, repeats)):
        t0 = time.perf_counter()
        run(scans[:timed])
        best = min(best, time.perf_counter() - t0)
    return best / len(scans[:timed]), run(scans)


VARIANTS = ("torch-fp32", "torch-bf16", "onnx-fp32", "onnx-fp32-batch8", "onnx-int8",
            "onnx-fp16")
# Frames each variant is timed on (best of the repeats); agreement is measured on every frame.
TIMED_FRAMES = 32
# What each variant computes in, for its share of the machine's matrix rate of that precision.
PRECISION = {"torch-fp32": "fp32", "torch-bf16": "bf16", "onnx-fp32": "fp32",
             "onnx-fp32-batch8": "fp32", "onnx-int8": "int8", "onnx-fp16": "fp16"}


def bench_models(scans: np.ndarray, onnx_path: str | Path, pt_path: str | Path | None = None,
                 repeats: int = 3, threads: int = 2, variants: tuple[str, ...] = VARIANTS,
                 calibration: np.ndarray | None = None, timed: int = TIMED_FRAMES,
                 on_progress=None, int8_path: str | Path | None = None) -> list[dict]:
    """One dict per variant: ms/frame, fps, car IoU vs labels, and agreement with ONNX fp32.

    ``car_iou_diff`` is the variant's car IoU minus ONNX fp32's (against the labels in channel 5);
    ``car_agreement_iou`` is the car IoU of the variant's predictions against ONNX fp32's.
    ``onnx-fp32-batch8`` feeds the network 8 frames a run instead of one, the batching the
    runners do not use; int8 is ``int8_path`` where given (the shipped int8 copy of the bundled
    network), else calibrated on ``calibration`` (never the scans measured: two minutes).
    Times are the best of ``repeats`` runs over the first ``timed`` frames; ``on_progress(line)``
    hears each step, since a slow variant on one thread takes minutes.
    """
    from falsify.models.export import convert_fp16, quantize_int8

    scans = np.asarray(scans, np.float32)
    if scans.ndim == 3:
        scans = scans[None]
    onnx_path = Path(onnx_path)
    labels = np.where(scans[..., 4] > 0, scans[..., 5], 0).astype(np.uint8)
    rows: list[dict] = []
    ref: Prediction | None = None
    with tempfile.TemporaryDirectory() as tmp:
        makers = {
            "onnx-fp32": lambda: OnnxSegmenter(onnx_path, threads),
            "onnx-fp32-batch8": lambda: OnnxSegmenter(onnx_path, threads, batch=8),
            "torch-fp32": lambda: TorchSegmenter(
                pt_path if pt_path else onnx_path.with_suffix(".pt"), threads,
                spec_path=spec_path_for(onnx_path)),
            "torch-bf16": lambda: TorchSegmenter(
                pt_path if pt_path else onnx_path.with_suffix(".pt"), threads,
                spec_path=spec_path_for(onnx_path), precision="bf16"),
            "onnx-int8": lambda: OnnxSegmenter(
                int8_path or quantize_int8(onnx_path, Path(tmp) / "int8.onnx", scans=calibration),
                threads),
            "onnx-fp16": lambda: OnnxSegmenter(
                convert_fp16(onnx_path, Path(tmp) / "fp16.onnx"), threads),
        }
        order = ["onnx-fp32"] + [v for v in variants if v != "onnx-fp32"]
        for name in order:
            if name not in makers:
                raise FalsifyError(f"unknown bench variant {name!r}; choose from {list(makers)}")
            row: dict = {"variant": name, "precision": PRECISION[name]}
            if on_progress is not None:
                on_progress(f"bench model: {name} ({len(scans)} frames, {threads} thread(s))")
            try:
                seg = makers[name]()
                sec, pred = _time(seg.predict, scans, repeats, timed)
            except FalsifyError:
                raise
            except Exception as e:  # a variant that does not run here is reported, not fatal
                row["error"] = f"{type(e).__name__}: {e}"
                rows.append(row)
                continue
            if ref is None:
                ref = pred
            iou = car_iou(pred.classes, labels)
            row.update(
                ms_per_frame=round(sec * 1e3, 2), fps=round(1.0 / sec, 2), frames=len(scans),
                timed_frames=len(scans[:timed]),
                threads=threads, batch=seg.batch, car_iou=iou,
                car_iou_diff=iou - car_iou(ref.classes, labels),
                car_agreement_iou=car_iou(pred.classes, ref.classes),
                pixel_agreement=float((pred.classes == ref.classes).mean()),
                model_hash=seg.model_hash[:12])
            if name in variants:
                rows.append(row)
    return rows
