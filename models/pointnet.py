"""A small PointNet-style per-point segmentation network: the reference Python plug-in.

PointNet (Qi, Su, Mo and Guibas, "PointNet: Deep Learning on Point Sets for 3D Classification
and Segmentation", CVPR 2017): a shared MLP lifts every point to a local feature, a max pool
over the points gives one global feature, and a per-point head classifies each local feature
concatenated with the global one. This one keeps that structure at a small width and leaves
out the paper's input and feature transform nets and its batch norm (scans arrive one at a
time, with any number of points). It predicts SemanticKITTI's 19 train classes (output i is
train id i; output 0, unlabeled, reads as unknown).

``--model falsify.models.pointnet:factory`` runs it with seeded random weights: plumbing, not a
trained network. For trained weights, a file plug-in calls ``factory("net.pt", device=device)``.
`export_onnx` writes it as a points-in ONNX model ((1, N, 4) in, (1, N, 20) logits out);
``falsify train-pointnet`` trains it (falsify.models.train_pointnet).
Importing this module imports torch.
"""

from __future__ import annotations

import copy
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from os import PathLike
from pathlib import Path

import numpy as np
import torch
from torch import nn

from falsify.errors import FalsifyError
from falsify.models.plugin import torch_device
from falsify.models.spec import (
    INPUT_MEAN,
    INPUT_STD,
    POINT_CHANNELS,
    SCAN_INDEX,
    ModelSpec,
    save_spec,
    spec_path_for,
)
from falsify.semantic import TRAIN_CLASSES

OPSET = 17
POINTS_NOTE = ("points (1, N, 4) float32: x, y, z, intensity of a scan's valid pixels, each "
               "(value - mean) / std; logits (1, N, 20): output i is SemanticKITTI train id i")


def pointnet_spec(name: str = "pointnet") -> ModelSpec:
    """The spec of `PointNetSeg`: points in, SemanticKITTI's train classes out."""
    return ModelSpec(
        name=name, channels=POINT_CHANNELS,
        mean=tuple(INPUT_MEAN[SCAN_INDEX[c]] for c in POINT_CHANNELS),
        std=tuple(INPUT_STD[SCAN_INDEX[c]] for c in POINT_CHANNELS),
        height=0, width=0, input_name="points", output_name="logits", output_kind="logits",
        num_classes=len(TRAIN_CLASSES),
        classes={c: (i,) for i, c in enumerate(TRAIN_CLASSES) if i},
        architecture="pointnet", notes=POINTS_NOTE, input_kind="points")


def _mlp(*widths: int) -> nn.Sequential:
    """Linear + ReLU layers shared by every point (a 1x1 convolution over the points)."""
    layers: list[nn.Module] = []
    for a, b in zip(widths[:-1], widths[1:], strict=True):
        layers += [nn.Linear(a, b), nn.ReLU()]
    return nn.Sequential(*layers)


class PointNetSeg(nn.Module):
    """(B, N, 4) points -> (B, N, num_classes) logits: local features, a max-pooled global
    feature concatenated back onto each point, a per-point head."""

    def __init__(self, num_classes: int = len(TRAIN_CLASSES), in_channels: int = 4,
                 local: int = 64, global_: int = 256) -> None:
        super().__init__()
        self.local = _mlp(in_channels, 64, local)
        self.lift = _mlp(local, 128, global_)
        self.head = nn.Sequential(_mlp(local + global_, 256, 128), nn.Linear(128, num_classes))

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        f = self.local(points)                                   # (B, N, local)
        g = self.lift(f).amax(dim=1, keepdim=True)               # (B, 1, global)
        g = g.expand(f.shape[0], f.shape[1], g.shape[2])         # onto every point
        return self.head(torch.cat([f, g], dim=-1))


@dataclass
class PointNetPlugin:
    """The plug-in object: `spec`, `files` (the weights, if any) and `predict`."""

    model: PointNetSeg
    spec: ModelSpec
    device: str = "cpu"
    files: tuple[str, ...] = ()

    def predict(self, batch: Sequence[np.ndarray]) -> list[np.ndarray]:
        """Per scan: (N, 4) float32 points -> (N, 20) float32 logits; one scan per forward
        pass (the scans have different numbers of points)."""
        out = []
        with torch.inference_mode():
            for pts in batch:
                x = torch.from_numpy(np.ascontiguousarray(pts, np.float32)).to(self.device)
                out.append(self.model(x[None])[0].float().cpu().numpy())
        return out


def build(weights: str | PathLike | None = None, seed: int = 0) -> PointNetSeg:
    """The network in eval mode: seeded random weights (the global torch RNG untouched), or a
    state dict loaded (weights_only) from `weights`."""
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        model = PointNetSeg()
    if weights is not None:
        try:
            state = torch.load(str(weights), map_location="cpu", weights_only=True)
            model.load_state_dict(state)
        except Exception as e:
            raise FalsifyError(f"cannot load PointNet weights {weights}: {e}") from e
    return model.eval()


def factory(weights: str | PathLike | None = None, device: str = "cpu",
            threads: int | None = None, seed: int = 0) -> PointNetPlugin:
    """The plug-in: `build(weights, seed)` on `device` ("cpu" or "cuda"; FalsifyError for cuda
    where torch sees no GPU), with `threads` torch CPU threads when given."""
    device = torch_device(device)
    if threads:
        torch.set_num_threads(int(threads))
    model = build(weights, seed).to(device)
    files = (str(Path(weights)),) if weights is not None else ()
    return PointNetPlugin(model, pointnet_spec(), device, files)


def reference(device: str = "cpu", threads: int | None = None) -> PointNetPlugin:
    """The shipped PointNet trained on the world's scans (models/weights/pointnet20.pt; its
    card: models/cards/pointnet20.md): ``--model falsify.models.pointnet:reference``."""
    from falsify.models.runners import WEIGHTS_DIR, not_installed

    weights = WEIGHTS_DIR / "pointnet20.pt"
    if not weights.is_file():   # a wheel leaves it out
        raise FalsifyError(not_installed("pointnet20", "--model falsify.models.pointnet:reference"))
    return factory(weights, device=device, threads=threads)


def export_onnx(model: PointNetSeg, path: str | PathLike, name: str | None = None
                ) -> tuple[Path, ModelSpec]:
    """Write `model` as a points-in ONNX graph (the number of points dynamic) and its spec
    beside it (<path>.json); the legacy TorchScript exporter, opset 17."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    spec = pointnet_spec(name or path.stem)
    m = copy.deepcopy(model).float().cpu().eval()
    from falsify.fileio import atomic_path

    with warnings.catch_warnings(), torch.no_grad(), atomic_path(path) as tmp:
        warnings.simplefilter("ignore")
        torch.onnx.export(m, (torch.zeros(1, 64, 4),), str(tmp), dynamo=False,
                          opset_version=OPSET, input_names=[spec.input_name],
                          output_names=[spec.output_name],
                          dynamic_axes={spec.input_name: {1: "points"},
                                        spec.output_name: {1: "points"}},
                          do_constant_folding=True)
    save_spec(spec, spec_path_for(path))
    return path, spec
