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
``falsify train-pointnet`` trains it (`train`).
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
    from falsify.models.runners import WEIGHTS_DIR

    return factory(WEIGHTS_DIR / "pointnet20.pt", device=device, threads=threads)


def export_onnx(model: PointNetSeg, path: str | PathLike, name: str | None = None
                ) -> tuple[Path, ModelSpec]:
    """Write `model` as a points-in ONNX graph (the number of points dynamic) and its spec
    beside it (<path>.json); the legacy TorchScript exporter, opset 17."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    spec = pointnet_spec(name or path.stem)
    m = copy.deepcopy(model).float().cpu().eval()
    with warnings.catch_warnings(), torch.no_grad():
        warnings.simplefilter("ignore")
        torch.onnx.export(m, (torch.zeros(1, 64, 4),), str(path), dynamo=False,
                          opset_version=OPSET, input_names=[spec.input_name],
                          output_names=[spec.output_name],
                          dynamic_axes={spec.input_name: {1: "points"},
                                        spec.output_name: {1: "points"}},
                          do_constant_folding=True)
    save_spec(spec, spec_path_for(path))
    return path, spec


def train(data: str | PathLike, out: str | PathLike, epochs: int = 20, batch: int = 16,
          points: int = 16384, lr: float = 1e-3, seed: int = 0, device: str = "cpu",
          time_limit_min: float | None = None, val_data: str | PathLike | None = None) -> dict:
    """Train on npy scans whose label channel holds SemanticKITTI train ids (`falsify dataset
    --labels semantickitti`): each step takes `points` valid points of each of `batch` scans
    (drawn with replacement where a scan has fewer), cross-entropy weighted as SqueezeSeg's
    (1 / sqrt(frequency), unlabeled ignored). Writes pointnet.pt, pointnet.onnx + .json and
    train_log.jsonl into `out`; returns the last log line."""
    import json
    import time

    from falsify.models.runners import points_of
    from falsify.models.train import list_scans, load_scan, semantic_weights

    t0 = time.monotonic()
    device = torch_device(device)
    files = list_scans(data)
    shape = load_scan(files[0]).shape[:2]
    spec = pointnet_spec()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    torch.manual_seed(seed)
    model = PointNetSeg().to(device)
    opt = torch.optim.Adam(model.parameters(), lr=lr)
    weights = torch.tensor(semantic_weights(files, shape), dtype=torch.float32, device=device)
    last: dict = {}

    def draw(f: Path) -> tuple[np.ndarray, np.ndarray]:
        scan = load_scan(f, shape)
        valid = scan[..., 4] > 0
        pts, lab = points_of(scan, valid, spec), scan[valid][:, 5].astype(np.int64)
        pick = rng.choice(len(pts), points, replace=len(pts) < points)
        return pts[pick], lab[pick]

    for epoch in range(epochs):
        perm = rng.permutation(len(files))
        losses = []
        for i in range(0, len(perm), batch):
            drawn = [draw(files[j]) for j in perm[i:i + batch]]
            x = torch.from_numpy(np.stack([d[0] for d in drawn])).to(device)
            y = torch.from_numpy(np.stack([d[1] for d in drawn])).to(device)
            loss = nn.functional.cross_entropy(model(x).transpose(1, 2), y, weight=weights,
                                               ignore_index=0)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            losses.append(float(loss.detach()))
        last = {"epoch": epoch + 1, "loss": float(np.mean(losses)),
                "seconds": round(time.monotonic() - t0, 1)}
        if val_data is not None:
            last.update(_validate(model, list_scans(val_data, "--val-data"), spec, device))
        with open(out / "train_log.jsonl", "a", encoding="utf-8") as fh:
            fh.write(json.dumps(last) + "\n")
        print(json.dumps(last), flush=True)
        if time_limit_min is not None and time.monotonic() - t0 > 60 * time_limit_min:
            last["stopped"] = "time_limit"
            break
    model = model.cpu().eval()
    torch.save({k: v.contiguous() for k, v in model.state_dict().items()}, out / "pointnet.pt")
    export_onnx(model, out / "pointnet.onnx")
    return last


def _validate(model: PointNetSeg, files: list[Path], spec: ModelSpec, device: str) -> dict:
    """Pooled per-class IoU over every valid point of the validation scans (unlabeled
    ignored): val_car_iou and val_miou over the classes present."""
    from falsify.models.runners import points_of
    from falsify.models.train import load_scan

    n = len(TRAIN_CLASSES)
    conf = np.zeros((n, n), np.int64)
    model.eval()
    with torch.inference_mode():
        for f in files:
            scan = load_scan(f)
            valid = scan[..., 4] > 0
            x = torch.from_numpy(points_of(scan, valid, spec)).to(device)
            pred = model(x[None])[0].argmax(-1).cpu().numpy()
            lab = scan[valid][:, 5].astype(np.int64)
            keep = lab != 0
            conf += np.bincount(lab[keep] * n + pred[keep], minlength=n * n).reshape(n, n)
    model.train()
    tp = np.diag(conf)
    denom = conf.sum(0) + conf.sum(1) - tp
    iou = [float(tp[c] / denom[c]) if denom[c] else None for c in range(n)]
    present = [v for c, v in enumerate(iou) if c and conf[c].sum()]
    return {"val_car_iou": iou[1], "val_miou": float(np.mean(present)) if present else None}
