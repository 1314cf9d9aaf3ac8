"""The Python plug-in runner: a `falsify.models.plugin` model (``MODULE:FACTORY``) as a
Segmenter, its answers checked and mapped back onto the scan's pixels."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np

from falsify.errors import FalsifyError
from falsify.models.plugin import cuda_hint, open_plugin
from falsify.models.runners.base import Prediction, check_scans, points_of, scatter, to_prediction
from falsify.models.spec import ModelSpec


class PluginSegmenter:
    """A Python plug-in (`falsify.models.plugin`) as a Segmenter. A points plug-in gets each
    scan's valid pixels as its points, in row-major order, and its per-point answers go back to
    those pixels (`falsify predict --score points` lays a scan's points out as one row of
    pixels, `point_rows`, so it gets every point); integer answers read as certain."""

    def __init__(self, ref: str, threads: int | None = None, device: str = "cpu") -> None:
        self.path = ref
        self.device = device
        self.threads = threads   # what the plug-in is given (None: its library's default)
        self.plugin, self.spec, self.model_hash = open_plugin(ref, threads, device)

    def predict(self, scans: np.ndarray) -> Prediction:
        a = check_scans(scans, self.spec, Path(self.path))
        valid = a[..., 4] > 0
        raw, spec = self._run(a, valid)
        return to_prediction(raw, spec, valid)

    def run_raw(self, scans: np.ndarray) -> np.ndarray:
        """The plug-in's answers as (B,K,H,W) scores (one-hot for integer answers)."""
        a = check_scans(scans, self.spec, Path(self.path))
        return self._run(a, a[..., 4] > 0)[0]

    def _run(self, a: np.ndarray, valid: np.ndarray) -> tuple[np.ndarray, ModelSpec]:
        s, points = self.spec, self.spec.input_kind == "points"
        if points:
            sent = [b for b in range(len(a)) if valid[b].any()]
            batch = [points_of(a[b], valid[b], s) for b in sent]
        else:
            sent = list(range(len(a)))
            batch = []
            for b in sent:
                scan = a[b, ..., :6].copy()
                scan[..., 5:] = 0   # the label: a network must not see the answer
                batch.append(scan)
        answers = [_numpy(x) for x in self._predict(batch)] if batch else []
        if len(answers) != len(batch):
            raise FalsifyError(f"plug-in {self.path}: predict returned {len(answers)} answers "
                               f"for {len(batch)} scans")
        for x in answers:
            if not (np.issubdtype(x.dtype, np.number) or x.dtype == bool) or np.iscomplexobj(x):
                raise FalsifyError(f"plug-in {self.path}: predict returned an answer of dtype "
                                   f"{x.dtype}; allowed: integer output indices or float scores")
            if not np.isfinite(x).all():
                raise FalsifyError(f"plug-in {self.path}: predict returned NaN or inf scores "
                                   f"for a scan; refusing to score them")
        ints = {np.issubdtype(x.dtype, np.integer) or x.dtype == bool for x in answers}
        if len(ints) > 1:
            raise FalsifyError(f"plug-in {self.path}: predict returned integer classes for "
                               "some scans and float scores for others")
        onehot = ints == {True}
        k = s.num_classes
        per_scan: list[np.ndarray | None] = [None] * len(a)
        for b, x in zip(sent, answers, strict=True):
            n = int(valid[b].sum()) if points else None
            want = ((n,) if onehot else (n, k)) if points else (
                a.shape[1:3] if onehot else (k, *a.shape[1:3]))
            if tuple(x.shape) != tuple(want):
                what = "classes" if onehot else "scores"
                raise FalsifyError(f"plug-in {self.path}: predict returned {what} of shape "
                                   f"{tuple(x.shape)} for a scan, expected {tuple(want)}")
            if onehot:
                if x.size and (x.min() < 0 or x.max() >= k):
                    raise FalsifyError(f"plug-in {self.path}: predict returned class index "
                                       f"{int(x.min() if x.min() < 0 else x.max())}; the spec "
                                       f"has {k} outputs (0..{k - 1})")
                x = np.eye(k, dtype=np.float32)[x.astype(np.int64)]   # (N, K) or (H, W, K)
                if not points:
                    x = np.moveaxis(x, -1, 0)
            per_scan[b] = x.astype(np.float32, copy=False)
        if points:
            raw = scatter(per_scan, valid, k)
        else:
            raw = np.stack(per_scan) if len(a) else np.zeros((0, k, *a.shape[1:3]), np.float32)
        return raw, dataclasses.replace(s, output_kind="probabilities") if onehot else s

    def _predict(self, batch: list[np.ndarray]) -> list[Any]:
        """The plug-in's answers as a list; its own exceptions as a FalsifyError naming it, so
        a failing network is one line, not a traceback."""
        try:
            return list(self.plugin.predict(batch))
        except FalsifyError:
            raise
        except Exception as e:
            raise FalsifyError(f"plug-in {self.path}: predict failed: {type(e).__name__}: {e}"
                               f"{cuda_hint(self.device)}") from e


def _numpy(x: Any) -> np.ndarray:
    """A plug-in's answer (numpy array or torch tensor, any device) as a numpy array."""
    if hasattr(x, "detach"):
        x = x.detach().cpu().numpy()
    return np.asarray(x)
