"""Recurrent CRF of SqueezeSeg (arXiv 1710.07368, section 3.2) in torch, ONNX-friendly.

The windowed messages use fixed convolutions: a depthwise 3x5 gaussian for the angular message and
a grouped conv with one-hot neighbour kernels to gather the 14 neighbours for the bilateral one, so
the exported graph contains only Conv, Exp, Mul, Add, Softmax and Reshape.
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
        self.n = window[0] * window[1] - 1
        self.pad = (window[0] // 2, window[1] // 2)  # inside the Conv: no Pad node in ONNX
        ang = angular_kernel(theta_a, window)  # same theta_a for both messages (official config)
        full = torch.zeros(num_classes, 1, window[0] * window[1])
        centre = (window[0] * window[1]) // 2
        full[:, 0, :centre] = ang[:, :centre]
        full[:, 0, centre + 1 :] = ang[:, centre:]
        self.register_buffer("angular_filter", full.view(num_classes, 1, *window), persistent=False)
        self.register_buffer("bi_angular", ang, persistent=False)  # (C, n)
        inv = torch.tensor([1.0 / (2.0 * t**2) for t in theta_r], dtype=torch.float32)
        self.register_buffer("inv_two_theta_r2", inv, persistent=False)  # (C,)
        self.register_buffer("gather_xyz", neighbour_kernel(3, window), persistent=False)
        self.register_buffer("gather_1", neighbour_kernel(1, window), persistent=False)
        self.register_buffer("gather_q", neighbour_kernel(num_classes, window), persistent=False)
        compat = 1.0 - torch.eye(num_classes)
        self.angular_compat = nn.Conv2d(num_classes, num_classes, 1, bias=False)
        self.bilateral_compat = nn.Conv2d(num_classes, num_classes, 1, bias=False)
        with torch.no_grad():
            self.angular_compat.weight.copy_((compat * angular_coef).view(*compat.shape, 1, 1))
            self.bilateral_compat.weight.copy_((compat * bilateral_coef).view(*compat.shape, 1, 1))

    def _neighbours(self, x: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
        """(B, C, H, W) -> (B, C, n, H, W): the n window neighbours, zero outside the image."""
        c = int(x.shape[1])
        y = F.conv2d(x, weight, padding=self.pad, groups=c)
        return y.unflatten(1, (c, self.n))

    def bilateral_weights(self, xyz: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """Per-class neighbour weights (B, C, n, H, W) from raw xyz (B,3,H,W) and mask (B,1,H,W)."""
        nb = self._neighbours(xyz, self.gather_xyz)  # (B, 3, n, H, W)
        d2 = ((nb - xyz.unsqueeze(2)) ** 2).sum(dim=1, keepdim=True)  # (B, 1, n, H, W)
        nb_mask = self._neighbours(mask, self.gather_1)  # (B, 1, n, H, W)
        c, n = self.num_classes, self.n
        w = torch.exp(-d2 * self.inv_two_theta_r2.view(1, c, 1, 1, 1))
        w = w * self.bi_angular.view(1, c, n, 1, 1)  # (B, C, n, H, W)
        return w * (nb_mask * mask.unsqueeze(2))

    def forward(self, logits: torch.Tensor, xyz: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """Refine logits (B, C, H, W); returns energies of the same shape (softmax them)."""
        if self.iterations == 0:
            return logits
        with torch.autocast(device_type="cpu", enabled=False):  # the CRF always runs in fp32
            return self._iterate(logits.float(), xyz, mask)

    def _iterate(self, logits: torch.Tensor, xyz: torch.Tensor, mask: torch.Tensor
                 ) -> torch.Tensor:
        xyz = xyz.float()
        mask = mask.float()
        bi_w = self.bilateral_weights(xyz, mask)
        energy = logits
        for _ in range(self.iterations):
            # Softmax written out: ONNX Runtime's Softmax on axis 1 transposes NCHW to the last
            # axis and back (1.2 ms/frame per iteration at batch 8); these five ops cost less.
            e = torch.exp(energy - energy.amax(dim=1, keepdim=True))
            q = e / e.sum(dim=1, keepdim=True)
            qm = q * mask
            ang = F.conv2d(qm, self.angular_filter, padding=self.pad, groups=self.num_classes)
            bi = (self._neighbours(qm, self.gather_q) * bi_w).sum(dim=2) * mask
            # Mean-field update: the unary is the network's logits, and the Potts penalty
            # (compatibility (1 - I)·coef) of neighbours holding other classes is subtracted.
            energy = logits - self.angular_compat(ang) - self.bilateral_compat(bi)
        return energy
