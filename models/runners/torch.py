"""The PyTorch runner: SqueezeSeg from a state dict, on the CPU or a CUDA GPU. torch is
imported when a runner is made, not with this module."""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np

from falsify.errors import FalsifyError
from falsify.models.plugin import torch_device
from falsify.models.runners.base import (
    BATCH,
    Prediction,
    check_finite,
    check_scans,
    feeds,
    open_model,
    to_prediction,
)


class TorchSegmenter:
    """PyTorch eager channels_last on the CPU or a CUDA GPU from a state dict (weights_only
    load): fp32, or with precision "bf16" under torch's autocast (oneDNN's bf16 kernels on CPUs
    with bf16 units; the model hash then says bf16, since the logits differ)."""

    def __init__(self, path: str | Path, threads: int | None = None,
                 spec_path: str | Path | None = None, batch: int = BATCH,
                 device: str = "cpu", precision: str = "fp32") -> None:
        self.path, spec_path, self.spec, self.model_hash = open_model(path, spec_path,
                                                                          "pt")
        if precision not in ("fp32", "bf16"):
            raise FalsifyError(f"torch precision {precision!r}; allowed: fp32, bf16")
        self.precision = precision
        if precision != "fp32":
            self.model_hash = hashlib.sha256(
                f"{self.model_hash}:{precision}".encode()).hexdigest()
        self.batch = max(1, int(batch))
        if self.spec.input_kind != "range":
            raise FalsifyError(f"torch backend builds SqueezeSeg (range images) only; {spec_path} "
                               f"says input_kind {self.spec.input_kind!r}: run it as a plug-in "
                               "(--model MODULE:FACTORY) or as ONNX")
        if self.spec.architecture != "squeezeseg":
            raise FalsifyError(f"torch backend builds SqueezeSeg only; {spec_path} says "
                               f"architecture {self.spec.architecture!r}")
        self.device = torch_device(device)
        import torch

        from falsify.models.squeezeseg import SqueezeSeg

        if threads:
            torch.set_num_threads(int(threads))
        self.threads = torch.get_num_threads()   # torch's, process-wide (a run records them)
        self.torch = torch
        self.model = SqueezeSeg([c for c in self.spec.channels if c != "mask"],
                                crf_iterations=self.spec.crf_iterations,
                                num_classes=self.spec.num_classes)
        if self.spec.channels[-1] != "mask":
            raise FalsifyError(f"model spec {spec_path}: key 'channels' must end with 'mask' "
                               "for the torch SqueezeSeg")
        try:
            state = torch.load(str(self.path), map_location="cpu", weights_only=True)
        except Exception as e:
            raise FalsifyError(f"cannot load torch weights {self.path}: not a state dict that "
                               "torch.load(weights_only=True) reads (save one with "
                               f"torch.save(model.state_dict(), PATH); {type(e).__name__})"
                               ) from e
        try:
            self.model.load_state_dict(state)
        except Exception as e:
            raise FalsifyError(f"cannot load torch weights {self.path} into the SqueezeSeg "
                               f"{spec_path} describes ({self.spec.num_classes} classes, "
                               f"channels {list(self.spec.channels)}, crf_iterations "
                               f"{self.spec.crf_iterations}): {_one_line(e)}") from e
        # channels_last: about 2x faster than channels-first eager on this CPU (measured)
        self.model = self.model.to(self.device, memory_format=torch.channels_last).eval()

    def run_raw(self, scans: np.ndarray) -> np.ndarray:
        """Raw model output (B,K,H,W) for checked scans."""
        return self._run(check_scans(scans, self.spec, self.path))

    def _run(self, a: np.ndarray) -> np.ndarray:
        outs = []
        # fp32 convolutions on the GPU too: cuDNN's default TF32 moved the bundled network's
        # logits by up to 0.02 from the CPU's on an H100 (3 % of them by more than 1e-3)
        with self.torch.inference_mode(), self.torch.backends.cudnn.flags(
                enabled=True, allow_tf32=False), self.torch.autocast(
                self.device, dtype=self.torch.bfloat16,
                enabled=self.precision == "bf16"):
            for i in range(0, len(a), self.batch):
                f = feeds(self.spec, a[i:i + self.batch])
                t = {k: self.torch.from_numpy(v).to(self.device) for k, v in f.items()}
                x = t[self.spec.input_name].contiguous(memory_format=self.torch.channels_last)
                y = self.model(x, t.get(self.spec.xyz_input or ""),
                               t.get(self.spec.mask_input or ""))
                outs.append(y.float().cpu().numpy())
        return np.concatenate(outs)

    def predict(self, scans: np.ndarray) -> Prediction:
        a = check_scans(scans, self.spec, self.path)
        valid = a[..., 4] > 0
        return to_prediction(check_finite(self._run(a), valid, self.path), self.spec, valid)


def _one_line(e: Exception) -> str:
    """torch's error as one line: its first problem, and how many more it lists."""
    lines = [x.strip() for x in str(e).splitlines() if x.strip()]
    if not lines:
        return type(e).__name__
    head = lines[0] if len(lines) == 1 or not lines[0].endswith(":") else lines[1]
    more = len(lines) - (1 if head == lines[0] else 2)
    return head + (f" (and {more} more)" if more > 0 else "")
