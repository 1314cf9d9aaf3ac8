"""Recurrent CRF of SqueezeSeg (arXiv 1710.07368, section 3.2) in torch, ONNX-friendly.

The windowed messages use fixed convolutions, so the exported graph holds only Conv, Exp, Mul,
Add, Sub, ReduceSum/Max, Div and Reshape: a depthwise 3x5 gaussian for the angular message, and
for the bilateral one a grouped conv with one-hot kernels that gathers the 14 neighbours of each
class. The bilateral weights are computed once per frame, with as few full-size tensors as the
math allows (measured in ONNX Runtime, 1 thread, 3 iterations: 8.8 -> 6.1 ms/frame, same output
to 1e-6): the coordinate differences come from one conv with +1/-1 kernels, the squared distance
times -1/(2 theta_r^2) plus log(angular gaussian) from one 1x1 conv, and classes that share
(theta_a, theta_r) share their weights (the official thetas: two groups, not four). The
neighbours' validity needs no factor of its own: invalid neighbours hold q = 0.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import nn

from falsify.classes import CLASSES

NUM_CLASSES = len(CLASSES)
WINDOW = (3, 5)
THETA_A = (0.9, 0.9, 0.6, 0.6)
THETA_R = (0.015, 0.015, 0.01, 0.01)
BILATERAL_COEF = 0.1
ANGULAR_COEF = 0.02


def angular_kernel(thetas: Sequence[float], window: tuple[int, int] = WINDOW) -> torch.Tensor:
    """Per-class gaussian on the (row, column) pixel offset, centre set to 0: (C, wh*ww - 1)."""
    wh, ww = window
    rows = []
    for theta in thetas:
        k = []
        for i in range(wh):
            for j in range(ww):
                if i == wh // 2 and j == ww // 2:
                    continue
                d2 = (i - wh // 2) ** 2 + (j - ww // 2) ** 2
                k.append(math.exp(-d2 / 2.0 / theta**2))
        rows.append(k)
    return torch.tensor(rows, dtype=torch.float32)


def neighbour_kernel(channels: int, window: tuple[int, int] = WINDOW) -> torch.Tensor:
    """One-hot grouped-conv weights that copy each of the wh*ww - 1 neighbours to a channel.

    Shape (channels * n, 1, wh, ww); output channel c*n + k is neighbour k of input channel c.
    """
    wh, ww = window
    n = wh * ww - 1
    w = torch.zeros(channels * n, 1, wh, ww)
    for c in range(channels):
        k = 0
        for i in range(wh):
            for j in range(ww):
                if i == wh // 2 and j == ww // 2:
                    continue
                w[c * n + k, 0, i, j] = 1.0
                k += 1
    return w


def difference_kernel(channels: int, window: tuple[int, int] = WINDOW) -> torch.Tensor:
    """Like `neighbour_kernel`, minus the centre: output c*n + k is neighbour k - centre."""
    w = neighbour_kernel(channels, window)
    w[:, 0, window[0] // 2, window[1] // 2] = -1.0
    return w


def theta_groups(theta_a: Sequence[float], theta_r: Sequence[float]
                 ) -> tuple[list[tuple[float, float]], list[int]]:
    """The distinct (theta_a, theta_r) pairs in order of first use, and each class's index."""
    pairs = list(zip(theta_a, theta_r, strict=True))
    distinct = list(dict.fromkeys(pairs))
    return distinct, [distinct.index(p) for p in pairs]


class RecurrentCRF(nn.Module):
    """Mean-field CRF as an RNN over a 3x5 window of the range image.

    Each iteration: q = softmax(energy); angular message = fixed gaussian on pixel offsets of the
    masked q; bilateral message = sum over neighbours of gaussian(xyz distance) x angular gaussian
    x masked q; learned 1x1 compatibility per message; energy = logits - both transformed
    messages (mean field with a Potts-like penalty, CRF-as-RNN). The official TF code used
    softmax(energy) as the unary and added the messages: with its (1 - I) initialisation that
    rewards disagreeing with the neighbours and flattens the scores each iteration (measured on
    our backbone: car IoU 0.15 against 0.86 with this form). ``iterations=0`` returns the logits.
    """

    def __init__(
        self,
        iterations: int = 3,
        num_classes: int = NUM_CLASSES,
        theta_a: Sequence[float] = THETA_A,
        theta_r: Sequence[float] = THETA_R,
        bilateral_coef: float = BILATERAL_COEF,
        angular_coef: float = ANGULAR_COEF,
        window: tuple[int, int] = WINDOW,
    ) -> None:
        super().__init__()
        if not 0 <= iterations <= 3:
            raise ValueError(f"CRF iterations must be 0..3, got {iterations}")
        if len(theta_a) != num_classes or len(theta_r) != num_classes:
            raise ValueError("theta_a and theta_r need one value per class")
        self.iterations = iterations
        self.num_classes = num_classes
        self.window = window
        self.n = n = window[0] * window[1] - 1
        self.pad = (window[0] // 2, window[1] // 2)  # inside the Conv: no Pad node in ONNX
        ang = angular_kernel(theta_a, window)  # same theta_a for both messages (official config)
        full = torch.zeros(num_classes, 1, window[0] * window[1])
        centre = (window[0] * window[1]) // 2
        full[:, 0, :centre] = ang[:, :centre]
        full[:, 0, centre + 1 :] = ang[:, centre:]
        self.register_buffer("angular_filter", full.view(num_classes, 1, *window), persistent=False)
        distinct, group = theta_groups(theta_a, theta_r)
        self.groups = len(distinct)
        # classes of a group side by side and groups of equal size: the weights broadcast over
        # the classes of a group; otherwise they are expanded to one set per class once a frame
        self.broadcast = group == sorted(group) and num_classes % self.groups == 0 and all(
            group.count(g) == num_classes // self.groups for g in range(self.groups))
        self.register_buffer("class_group", torch.tensor(group), persistent=False)
        # exponent of the bilateral weight, group g neighbour k: -|d|^2 / (2 theta_r^2) + log a_k
        g_ang = angular_kernel([a for a, _ in distinct], window)
        expo_w = torch.zeros(self.groups * n, 3 * n, 1, 1)
        for g, (_, r) in enumerate(distinct):
            for k in range(n):
                for c in range(3):
                    expo_w[g * n + k, c * n + k] = -1.0 / (2.0 * r * r)
        self.register_buffer("exponent_weight", expo_w, persistent=False)
        self.register_buffer("exponent_bias", g_ang.log().flatten(), persistent=False)
        self.register_buffer("xyz_difference", difference_kernel(3, window), persistent=False)
        self.register_buffer("gather_q", neighbour_kernel(num_classes, window), persistent=False)
        compat = 1.0 - torch.eye(num_classes)
        self.angular_compat = nn.Conv2d(num_classes, num_classes, 1, bias=False)
        self.bilateral_compat = nn.Conv2d(num_classes, num_classes, 1, bias=False)
        with torch.no_grad():
            self.angular_compat.weight.copy_((compat * angular_coef).view(*compat.shape, 1, 1))
            self.bilateral_compat.weight.copy_((compat * bilateral_coef).view(*compat.shape, 1, 1))

    def bilateral_weights(self, xyz: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """Neighbour weights from raw xyz (B,3,H,W) and mask (B,1,H,W), zero at invalid pixels:
        (B, G, 1, n, H, W) per theta group when they broadcast, else (B, C, n, H, W)."""
        h, w = int(xyz.shape[-2]), int(xyz.shape[-1])  # static at export: no Shape nodes
        d = F.conv2d(xyz, self.xyz_difference, padding=self.pad, groups=3)  # (B, 3n, H, W)
        wts = torch.exp(F.conv2d(d * d, self.exponent_weight, self.exponent_bias)) * mask
        if self.broadcast:
            return wts.view(-1, self.groups, 1, self.n, h, w)
        return wts.view(-1, self.groups, self.n, h, w).index_select(1, self.class_group)

    def forward(self, logits: torch.Tensor, xyz: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """Refine logits (B, C, H, W); returns energies of the same shape (softmax them)."""
        if self.iterations == 0:
            return logits
        with torch.autocast(device_type="cpu", enabled=False):  # the CRF always runs in fp32
            return self._iterate(logits.float(), xyz.float(), mask.float())

    def _iterate(self, logits: torch.Tensor, xyz: torch.Tensor, mask: torch.Tensor
                 ) -> torch.Tensor:
        c, n = self.num_classes, self.n
        h, w = int(logits.shape[-2]), int(logits.shape[-1])
        bi_w = self.bilateral_weights(xyz, mask)
        energy = logits
        for _ in range(self.iterations):
            # Softmax written out: ONNX Runtime's Softmax on axis 1 transposes NCHW to the last
            # axis and back (1.2 ms/frame per iteration at batch 8); these five ops cost less.
            e = torch.exp(energy - energy.amax(dim=1, keepdim=True))
            q = e / e.sum(dim=1, keepdim=True)
            qm = q * mask
            ang = F.conv2d(qm, self.angular_filter, padding=self.pad, groups=c)
            nb = F.conv2d(qm, self.gather_q, padding=self.pad, groups=c)  # (B, C*n, H, W)
            if self.broadcast:
                nb = nb.view(-1, self.groups, c // self.groups, n, h, w)
                bi = (nb * bi_w).sum(dim=3).view(-1, c, h, w)
            else:
                bi = (nb.view(-1, c, n, h, w) * bi_w).sum(dim=2)
            # Mean-field update: the unary is the network's logits, and the Potts penalty
            # (compatibility (1 - I)·coef) of neighbours holding other classes is subtracted.
            energy = logits - self.angular_compat(ang) - self.bilateral_compat(bi)
        return energy
