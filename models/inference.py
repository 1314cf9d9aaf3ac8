"""Equivalent, faster forms of SqueezeSeg's layers for the exported graph (same weights).

Training keeps the plain layers; `for_export` swaps in forms that ONNX Runtime runs faster on
the CPU, with the same output up to float rounding (tested to 1e-5). Measured with ONNX
Runtime fp32, 1 thread, the bundled network on the 2-core EPYC:

- `TapConv` for conv14 (3x3, 64 -> 4 classes at full resolution): ONNX Runtime runs a conv with
  so few outputs through im2col (3.1 ms/frame; 4.1 ms as int8). As a 1x1 conv to the 9 taps x 4
  classes, already zero-padded, plus the sum of 9 shifted slices: about 1 ms, and the 1x1 conv
  quantises well.
- `PhaseDeconv` for the 1x4 stride-2 transposed convs: a (1,3) conv to the even and odd output
  columns, interleaved by a reshape; ONNX Runtime has no int8 ConvTranspose, so this keeps the
  decoder in int8 (about 1.5 ms/frame in the int8 graph).
"""

from __future__ import annotations

import copy

import torch
from torch import nn

from falsify.models.squeezeseg import SqueezeSeg


class TapConv(nn.Module):
    """A stride-1, odd-kernel, zero-padded ("same") Conv2d as a 1x1 conv to one channel block per
    kernel tap, followed by the sum of the shifted blocks."""

    def __init__(self, conv: nn.Conv2d) -> None:
        super().__init__()
        co, ci, kh, kw = conv.weight.shape
        if conv.stride != (1, 1) or conv.groups != 1 or conv.dilation != (1, 1) or \
                conv.padding != (kh // 2, kw // 2) or not kh % 2 or not kw % 2:
            raise ValueError("TapConv takes a stride-1, ungrouped conv with odd 'same' padding")
        self.out_channels, self.kernel = co, (kh, kw)
        # output channel (i*kw + j)*co + c is tap (i, j) of class c; padding on a 1x1 conv
        # writes the zero border the shifted slices need, with no Pad node
        self.taps = nn.Conv2d(ci, co * kh * kw, 1, padding=(kh // 2, kw // 2), bias=False)
        with torch.no_grad():
            self.taps.weight.copy_(conv.weight.permute(2, 3, 0, 1).reshape(-1, ci, 1, 1))
        bias = conv.bias if conv.bias is not None else torch.zeros(co)
        self.bias = nn.Parameter(bias.detach().clone().view(1, co, 1, 1))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h, w = int(x.shape[-2]), int(x.shape[-1])  # static at export: no Shape nodes
        z = self.taps(x)
        kh, kw = self.kernel
        co = self.out_channels
        out = self.bias
        for i in range(kh):
            for j in range(kw):
                t = (i * kw + j) * co
                out = out + z[:, t:t + co, i:i + h, j:j + w]
        return out


class PhaseDeconv(nn.Module):
    """ConvTranspose2d with kernel (1, 4), stride (1, 2), padding (0, 1) (output width 2W) as a
    (1, 3) conv giving the even and the odd output columns, then interleaved."""

    def __init__(self, deconv: nn.ConvTranspose2d) -> None:
        super().__init__()
        if deconv.kernel_size != (1, 4) or deconv.stride != (1, 2) or \
                deconv.padding != (0, 1) or deconv.groups != 1 or \
                deconv.output_padding != (0, 0) or deconv.dilation != (1, 1):
            raise ValueError("PhaseDeconv takes a 1x4 stride-(1,2) padding-(0,1) ConvTranspose2d")
        ci, co = deconv.weight.shape[:2]
        w = deconv.weight[:, :, 0, :].transpose(0, 1)  # (out, in, 4)
        k = torch.zeros(2 * co, ci, 1, 3)
        # even output 2m takes inputs m-1 (tap 3) and m (tap 1); odd 2m+1: m (tap 2), m+1 (tap 0)
        k[:co, :, 0, 0], k[:co, :, 0, 1] = w[..., 3], w[..., 1]
        k[co:, :, 0, 1], k[co:, :, 0, 2] = w[..., 2], w[..., 0]
        self.out_channels = co
        self.conv = nn.Conv2d(ci, 2 * co, (1, 3), padding=(0, 1))
        bias = deconv.bias if deconv.bias is not None else torch.zeros(co)
        with torch.no_grad():
            self.conv.weight.copy_(k)
            self.conv.bias.copy_(torch.cat([bias, bias]))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h, w = int(x.shape[-2]), int(x.shape[-1])
        y = self.conv(x).view(-1, 2, self.out_channels, h, w).permute(0, 2, 3, 4, 1)
        return y.reshape(-1, self.out_channels, h, 2 * w)


def for_export(model: SqueezeSeg) -> SqueezeSeg:
    """A copy of ``model`` (eval mode) with conv14 as a `TapConv` and the decoder's transposed
    convs as `PhaseDeconv`s; ``model`` itself is left as it is."""
    m = copy.deepcopy(model).eval()
    m.conv14.conv = TapConv(m.conv14.conv)
    for name in ("fire_deconv10", "fire_deconv11", "fire_deconv12", "fire_deconv13"):
        block = getattr(m, name)
        block.deconv = PhaseDeconv(block.deconv)
    return m
