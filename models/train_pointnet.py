"""Train the reference PointNet (falsify.models.pointnet) on ``*.npy`` scans whose label channel
holds SemanticKITTI train ids, resumable exactly.

    falsify train-pointnet --data DIR --out DIR [--epochs N] [--batch B] [--points P] [--lr LR]
        [--seed S] [--val-data DIR] [--time-limit-min M] [--device cpu|cuda] [--resume]

Writes into --out: ``checkpoint.pt`` after every epoch (model, optimiser, epoch, the numpy
generator that draws the points, the log so far, the run's options; written atomically),
``train_log.jsonl`` (one line per finished epoch, rewritten from the checkpoint) and at the end
``pointnet.pt`` (weights only), ``pointnet.onnx`` + ``pointnet.json``. An --out holding a run is
continued only with --resume and only with the options in RESUME_KEYS unchanged (--epochs may
grow), as `falsify train` does; a resumed run draws the same points as one never stopped, so its
weights are the same bit for bit. Held-out scans (split manifests) are refused.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from falsify.checks import check_out_dir, check_range
from falsify.errors import FalsifyError
from falsify.models.spec import ModelSpec

CHECKPOINT = "checkpoint.pt"
LOG = "train_log.jsonl"
WEIGHTS = "pointnet.pt"
ONNX = "pointnet.onnx"
RUN_FILES = (CHECKPOINT, LOG, WEIGHTS, ONNX)   # what a run leaves in --out
# the options a resumed run must keep: they decide its weights (--epochs may grow)
RESUME_KEYS = ("data", "batch", "points", "lr", "seed")
LABELS_FIX = "write it with `falsify dataset --labels semantickitti`"


@dataclass
class PointNetTrainConfig:
    """Everything that decides a PointNet training run (saved in the checkpoint)."""

    data: str
    out: str
    epochs: int = 20
    batch: int = 16
    points: int = 16384   # points drawn from each scan a step
    lr: float = 1e-3
    seed: int = 0
    device: str = "cpu"   # cpu | cuda
    time_limit_min: float | None = None   # stop after the epoch that passes it
    val_data: str | None = None
    resume: bool = False
    holdout: tuple[str, ...] = ()   # split manifests: their held-out scans are refused


def train(cfg: PointNetTrainConfig, on_epoch: Callable[[dict], None] | None = None) -> dict:
    """Run (or resume) training; `on_epoch(record)` after each epoch's checkpoint; returns the
    run's summary. Every input is checked before --out is made; a non-finite loss stops the run
    (FalsifyError) before it is checkpointed."""
    import torch

    from falsify.models.pointnet import PointNetSeg, export_onnx, pointnet_spec
    from falsify.models.train import _load, _save_atomic, load_scan, semantic_weights

    t_start = time.monotonic()
    files, val_files = _checked_inputs(cfg, torch)
    out = Path(cfg.out)
    shape = load_scan(files[0]).shape[:2]
    spec = pointnet_spec()
    rng = np.random.default_rng(cfg.seed)
    torch.manual_seed(cfg.seed)
    model = PointNetSeg().to(cfg.device)
    opt = torch.optim.Adam(model.parameters(), lr=cfg.lr)
    weights = torch.tensor(semantic_weights(files, shape), dtype=torch.float32,
                           device=cfg.device)
    epoch, log = 0, []
    if cfg.resume:   # the checkpoint is there and of this run (_checked_inputs)
        ck = _load(out / CHECKPOINT, "--resume", torch)
        try:
            model.load_state_dict(ck["model"])
            opt.load_state_dict(ck["optim"])
            epoch, log = int(ck["epoch"]), json.loads(ck["log"])
            rng.bit_generator.state = json.loads(ck["rng"])
        except (KeyError, RuntimeError, TypeError, ValueError) as exc:
            what = f"no {exc}" if isinstance(exc, KeyError) else str(exc).splitlines()[0]
            raise FalsifyError(f"--resume {out / CHECKPOINT}: not a whole training checkpoint "
                               f"of this run ({what}); train again into another --out") from None
        _write_log(out, log)   # a stop between checkpoint and log left the log behind
    seconds = log[-1]["seconds"] if log else 0.0
    limit = 60.0 * cfg.time_limit_min if cfg.time_limit_min else None
    stopped = "done"
    while epoch < cfg.epochs and stopped == "done":
        t_epoch = time.monotonic()
        loss = _train_epoch(cfg, model, opt, weights, files, shape, spec, rng, epoch + 1)
        epoch += 1
        seconds += time.monotonic() - t_epoch
        record = {"epoch": epoch, "loss": loss, "seconds": round(seconds, 1)}
        if val_files:
            record.update(_validate(model, val_files, spec, cfg.device))
        log.append(record)
        _save_atomic({"model": model.state_dict(), "optim": opt.state_dict(), "epoch": epoch,
                      "rng": json.dumps(rng.bit_generator.state), "log": json.dumps(log),
                      "config": json.dumps(asdict(cfg)),
                      "data_path": str(Path(cfg.data).resolve())}, _made(out) / CHECKPOINT)
        _write_log(out, log)
        if on_epoch is not None:
            on_epoch(record)
        if limit is not None and time.monotonic() - t_start > limit:
            stopped = "time_limit"
    final = model.cpu().eval()
    _save_atomic({k: v.contiguous() for k, v in final.state_dict().items()}, out / WEIGHTS)
    export_onnx(final, out / ONNX)
    last = log[-1]
    return {"stopped": stopped, "epoch": epoch, "epochs": cfg.epochs, "loss": last["loss"],
            "val_car_iou": last.get("val_car_iou"), "val_miou": last.get("val_miou"),
            "seconds": last["seconds"], "weights": str(out / WEIGHTS), "onnx": str(out / ONNX),
            "log": str(out / LOG)}


def _checked_inputs(cfg: PointNetTrainConfig, torch) -> tuple[list[Path], list[Path]]:
    """The training and validation scans once every option has been checked (numbers, --out,
    the scans and their labels, held-out scans, the device, a run already in --out): a bad
    value fails here, as one line, before anything is written."""
    from falsify.data.holdout import check_apart, check_not_held_out
    from falsify.models.plugin import torch_device
    from falsify.models.train import _check_out, check_labels, check_run_numbers, list_scans

    check_run_numbers(cfg)
    check_range(cfg.points, "--points", 1)
    check_out_dir(cfg.out)
    files = list_scans(cfg.data)
    val_files = list_scans(cfg.val_data, "--val-data") if cfg.val_data else []
    check_not_held_out(files, cfg.holdout, "--data (trained on)")
    check_not_held_out(val_files, cfg.holdout, "--val-data (watched while training)")
    check_apart(files, val_files, "--val-data")
    check_labels(cfg.data, "semantickitti", "--data", LABELS_FIX)
    if cfg.val_data:
        check_labels(cfg.val_data, "semantickitti", "--val-data", LABELS_FIX)
    torch_device(cfg.device)
    _check_out(cfg, torch, RESUME_KEYS, RUN_FILES)
    return files, val_files


def _made(out: Path) -> Path:
    """--out, made when the first epoch is saved (so a run stopped before has left nothing)."""
    out.mkdir(parents=True, exist_ok=True)
    return out


def _write_log(out: Path, log: list[dict]) -> None:
    """train_log.jsonl, one line per finished epoch, written whole and atomically."""
    from falsify.fileio import write_text

    write_text(out / LOG, "".join(json.dumps(r) + "\n" for r in log))


def _train_epoch(cfg: PointNetTrainConfig, model, opt, weights, files: list[Path], shape,
                 spec: ModelSpec, rng: np.random.Generator, epoch: int) -> float:
    """One epoch: each step takes `cfg.points` valid points of each of `cfg.batch` scans (drawn
    with replacement where a scan has fewer), cross-entropy weighted as SqueezeSeg's (1 /
    sqrt(frequency), unlabeled ignored); a step that drew no labelled point (of a weighted
    class) is skipped; returns the mean loss. FalsifyError on a loss that is not finite: the
    weights have diverged and would be saved as NaN."""
    import torch
    from torch import nn

    from falsify.models.runners import points_of
    from falsify.models.train import diverged, load_scan

    def draw(f: Path) -> tuple[np.ndarray, np.ndarray]:
        scan = load_scan(f, shape)
        valid = scan[..., 4] > 0
        pts, lab = points_of(scan, valid, spec), scan[valid][:, 5].astype(np.int64)
        if lab.size and not 0 <= lab.min() <= lab.max() < spec.num_classes:
            raise FalsifyError(f"scan {f}: labels {lab.min()}..{lab.max()}, not SemanticKITTI's "
                               f"train ids 0..{spec.num_classes - 1}; {LABELS_FIX}")
        if not len(pts):
            raise FalsifyError(f"scan {f}: no valid point (channel 4 is 0 everywhere); "
                               "nothing to train on")
        pick = rng.choice(len(pts), cfg.points, replace=len(pts) < cfg.points)
        return pts[pick], lab[pick]

    perm = rng.permutation(len(files))
    losses = []
    for i in range(0, len(perm), cfg.batch):
        drawn = [draw(files[j]) for j in perm[i:i + cfg.batch]]
        x = torch.from_numpy(np.stack([d[0] for d in drawn])).to(cfg.device)
        y = torch.from_numpy(np.stack([d[1] for d in drawn])).to(cfg.device)
        if not bool((weights[y] > 0).any()):   # no labelled point of a weighted class drawn:
            continue                           # the mean loss would be 0 / 0, so no step
        loss = nn.functional.cross_entropy(model(x).transpose(1, 2), y, weight=weights,
                                           ignore_index=0)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        losses.append(float(loss.detach()))
        if not math.isfinite(losses[-1]):
            raise diverged(cfg.out, cfg.lr, epoch, f"the loss is {losses[-1]}")
    if not losses:
        raise FalsifyError(f"epoch {epoch}: no step drew a labelled point of a class seen in "
                           f"the first scans of --data {Path(cfg.data)}; nothing to train on "
                           "(more --points may draw some)")
    if not all(bool(torch.isfinite(p).all()) for p in model.parameters()):
        raise diverged(cfg.out, cfg.lr, epoch, "the weights are not finite")
    return float(np.mean(losses))


def _validate(model, files: list[Path], spec: ModelSpec, device: str) -> dict:
    """Pooled per-class IoU over every valid point of the validation scans (unlabeled
    ignored): val_car_iou and val_miou over the classes present."""
    import torch

    from falsify.models.runners import points_of
    from falsify.models.train import load_scan
    from falsify.semantic import TRAIN_CLASSES

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
