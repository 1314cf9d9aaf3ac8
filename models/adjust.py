"""Logit adjustment: undo the class weights' bias in a trained SqueezeSeg's logits.

    falsify adjust WEIGHTS.pt --val DIR --out ADJUSTED.pt [--alphas A,B,...] [--json]

Training weighs the cross-entropy by CLASS_WEIGHTS (unknown 1/15, car 1, pedestrian and cyclist
10), which shifts the learned logit of class c by about log(w_c / w_unknown): the network calls
"car" and "pedestrian" too readily (the first new-world network: held-out car recall 0.97,
precision 0.80). Subtracting alpha * log(w_c / w_unknown) from conv14's output, before the CRF,
undoes that (alpha = 1 is the Bayes correction for pixel accuracy; Menon et al., "Long-tail
learning via logit adjustment", ICLR 2021). IoU is not accuracy, so alpha is chosen: the one with
the highest pooled car IoU on a synthetic validation folder (ties: the smaller alpha). The offset
is folded into conv14's bias, so the adjusted weights export and run exactly like any others.
Real scans must never be --val.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from falsify.checks import check_out_file
from falsify.classes import CAR
from falsify.errors import FalsifyError
from falsify.models.train import (
    CLASS_WEIGHTS,
    batch_tensors,
    check_labels,
    list_scans,
    load_scan,
)
from falsify.results.metrics import class_scores, confusion

DEFAULT_ALPHAS = tuple(round(0.05 * i, 2) for i in range(21))
BIAS_KEY = "conv14.conv.bias"
BATCH = 8


def logit_offsets(alpha: float, weights: Sequence[float] = CLASS_WEIGHTS) -> np.ndarray:
    """Per-class offset added to the logits: -alpha * log(w_c / w_0) (0 for class 0)."""
    w = np.asarray(weights, np.float64)
    return -alpha * np.log(w / w[0])


def adjust_state(state: dict, alpha: float) -> dict:
    """A copy of a SqueezeSeg state dict with the alpha offsets folded into conv14's bias."""
    import torch

    if BIAS_KEY not in state:
        raise FalsifyError(f"not SqueezeSeg weights: no {BIAS_KEY!r}")
    out = dict(state)
    bias = state[BIAS_KEY]
    off = torch.tensor(logit_offsets(alpha), dtype=bias.dtype)
    if off.shape != bias.shape:
        raise FalsifyError(f"{BIAS_KEY} has {tuple(bias.shape)} classes; the class weights "
                           f"have {len(CLASS_WEIGHTS)}")
    out[BIAS_KEY] = (bias + off).contiguous()
    return out


@dataclass
class AlphaScore:
    """Pooled scores of one alpha on the validation folder."""

    alpha: float
    car_iou: float
    car_precision: float | None
    car_recall: float
    iou: list[float | None]  # per class: unknown, car, pedestrian, cyclist (None: no such class)


@dataclass
class Adjustment:
    """What `choose_alpha` measured and chose."""

    val: str
    scans: int
    chosen: float
    scores: list[AlphaScore]


def choose_alpha(state: dict, val: str | Path, alphas: Sequence[float] = DEFAULT_ALPHAS,
                 crf_iterations: int = 3, threads: int | None = 2,
                 weights: str | Path = "the weights") -> Adjustment:
    """Score every alpha on the scans of `val` (the backbone runs once a batch, the CRF once
    per alpha; fp32) and choose the highest pooled car IoU, the smaller alpha on a tie;
    `weights` names the state's file in errors."""
    import torch

    from falsify.models.spec import DEFAULT_CHANNELS
    from falsify.models.squeezeseg import SqueezeSeg, load_weights_into

    if not alphas:
        raise FalsifyError("--alphas: give at least one value")
    if threads:
        torch.set_num_threads(int(threads))
    files = list_scans(val, "--val")
    check_labels(str(val), "kitti4", "--val", "adjust scores our four classes: name a folder "
                 "of `falsify dataset --labels kitti4` scans")
    model = SqueezeSeg(DEFAULT_CHANNELS, crf_iterations=crf_iterations)
    load_weights_into(model, state, weights)
    model.eval()
    alphas = sorted(set(float(a) for a in alphas))
    counts = np.zeros((len(alphas), 4, 3), np.int64)  # per alpha: TP, FP, FN per class
    with torch.inference_mode():
        for i in range(0, len(files), BATCH):
            scans = np.stack([load_scan(f) for f in files[i:i + BATCH]])
            x, xyz, mask, labels = batch_tensors(scans, DEFAULT_CHANNELS)
            if int(labels.max()) >= len(CLASS_WEIGHTS):
                raise FalsifyError(f"--val {val}: a scan from {files[i].name} on holds "
                                   f"label id {int(labels.max())}; adjust scores our four classes "
                                   f"(0..{len(CLASS_WEIGHTS) - 1}): name a folder of "
                                   "`falsify dataset --labels kitti4` scans")
            logits = model.backbone(x)
            invalid = scans[..., 4] <= 0
            for k, a in enumerate(alphas):
                off = torch.tensor(logit_offsets(a), dtype=logits.dtype).view(1, -1, 1, 1)
                z = logits + off
                pred = (model.crf(z, xyz, mask) if crf_iterations else z).argmax(1).numpy()
                pred[invalid] = 0
                counts[k] += confusion(pred, labels.numpy())
    if counts[0, CAR, 0] + counts[0, CAR, 2] == 0:
        raise FalsifyError(f"--val {val}: no car points, so car IoU cannot choose alpha")
    scores = []
    for a, c in zip(alphas, counts, strict=True):
        cls = class_scores(c)
        car = cls[CAR]
        scores.append(AlphaScore(a, car.iou, car.precision, car.recall, [x.iou for x in cls]))
    best = max(scores, key=lambda s: (s.car_iou, -s.alpha))
    return Adjustment(str(val), len(files), best.alpha, scores)


def adjust_weights(weights: str | Path, val: str | Path, out: str | Path,
                   alphas: Sequence[float] = DEFAULT_ALPHAS) -> Adjustment:
    """Choose alpha on the synthetic validation scans of `val` for SqueezeSeg `weights` (a
    state dict or a training checkpoint.pt) and write the adjusted state dict to `out` (.pt);
    FalsifyError, with nothing written, on bad input."""
    import torch

    from falsify.fileio import atomic_path
    from falsify.models.squeezeseg import load_state

    out = check_out_file(out, suffixes=(".pt",))
    state = load_state(weights)
    result = choose_alpha(state, val, alphas, weights=weights)
    adjusted = adjust_state(state, result.chosen)
    out.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(out) as tmp:
        torch.save(adjusted, tmp)
    return result
