"""SqueezeSeg (Wu et al., arXiv 1710.07368) in torch, matching the official TensorFlow network.

Only the width is downsampled. TensorFlow "SAME" padding on the stride-(1,2) layers pads 0 columns
left and 1 right; we pad explicitly with F.pad so that the port is not shifted by one column.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from falsify.models.crf import NUM_CLASSES, THETA_A, THETA_R, RecurrentCRF
from falsify.models.spec import ALL_CHANNELS, DEFAULT_CHANNELS


def _same_pad_w(width: int, kernel: int, stride: int) -> tuple[int, int]:
    """TensorFlow SAME padding along one axis: (left, right). Ints, so the ONNX pads are static."""
    out = -(-width // stride)
    total = max((out - 1) * stride + kernel - width, 0)
    return total // 2, total - total // 2


class Conv(nn.Module):
    """Conv with bias, TF-SAME padding, optional ReLU.

    Unstrided odd kernels pad symmetrically inside the Conv (its ONNX ``pads``): a separate Pad
    node makes ONNX Runtime leave its blocked NCHWc layout around it (these 13 convs and the
    CRF's gathers together: about 3 ms/frame on the 2-core EPYC). Only the strided conv1, on
    the network input, pads explicitly.
    """

    def __init__(self, cin: int, cout: int, k: int, stride: tuple[int, int] = (1, 1),
                 relu: bool = True) -> None:
        super().__init__()
        inside = k // 2 if stride == (1, 1) and k % 2 else 0
        self.conv = nn.Conv2d(cin, cout, k, stride=stride, padding=inside)
        self.k, self.stride, self.relu = k, stride, relu
        self.explicit_pad = k > 1 and not inside

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.explicit_pad:
            left, right = _same_pad_w(int(x.shape[-1]), self.k, self.stride[1])
            top = (self.k - 1) // 2
            x = F.pad(x, (left, right, top, self.k - 1 - top))
        x = self.conv(x)
        return F.relu(x) if self.relu else x


class Pool(nn.Module):
    """3x3 max-pool, stride (1, 2), TF-SAME padding, expressed in the pool itself.

    SAME pads one column on the right only for even widths: that is ``ceil_mode`` with no column
    padding, so no Pad node breaks ONNX Runtime's blocked layout (a Pad plus its two reorders
    cost 8 ms/frame per pool). Odd widths pad one column each side.
    """

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        left, right = _same_pad_w(int(x.shape[-1]), 3, 2)
        return F.max_pool2d(x, 3, stride=(1, 2), padding=(1, left), ceil_mode=right > left)


class Fire(nn.Module):
    """Squeeze 1x1 -> expand 1x1 and 3x3, concatenated."""

    def __init__(self, cin: int, s: int, e1: int, e3: int) -> None:
        super().__init__()
        self.squeeze = Conv(cin, s, 1)
        self.expand1x1 = Conv(s, e1, 1)
        self.expand3x3 = Conv(s, e3, 3)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = self.squeeze(x)
        return torch.cat([self.expand1x1(x), self.expand3x3(x)], dim=1)


def bilinear_kernel(channels: int, width: int = 4) -> torch.Tensor:
    """Diagonal 1 x width bilinear upsampling weights for a ConvTranspose2d: (C, C, 1, width)."""
    f = int(np.ceil(width / 2.0))
    c = (2 * f - 1 - f % 2) / (2.0 * f)
    row = torch.tensor([1 - abs(x / f - c) for x in range(width)], dtype=torch.float32)
    w = torch.zeros(channels, channels, 1, width)
    for i in range(channels):
        w[i, i, 0] = row
    return w


class FireDeconv(nn.Module):
    """Squeeze 1x1 -> transposed conv 1x4 stride (1,2) (bilinear init) -> expand 1x1 and 3x3."""

    def __init__(self, cin: int, s: int, e1: int, e3: int) -> None:
        super().__init__()
        self.squeeze = Conv(cin, s, 1)
        # padding (0, 1) on a 1x4 stride-2 transposed conv is TF SAME: output width exactly 2W
        self.deconv = nn.ConvTranspose2d(s, s, (1, 4), stride=(1, 2), padding=(0, 1))
        with torch.no_grad():
            self.deconv.weight.copy_(bilinear_kernel(s))
            self.deconv.bias.zero_()
        self.expand1x1 = Conv(s, e1, 1)
        self.expand3x3 = Conv(s, e3, 3)

    def forward(self, x: torch.Tensor, width: int) -> torch.Tensor:
        x = F.relu(self.deconv(self.squeeze(x)))
        if int(x.shape[-1]) != width:  # odd skip widths only; static at export time
            x = x[..., :width]
        return torch.cat([self.expand1x1(x), self.expand3x3(x)], dim=1)


class SqueezeSeg(nn.Module):
    """SqueezeSeg encoder-decoder + optional recurrent CRF; outputs logits (B, 4, H, W).

    ``forward(x, xyz, mask)``: x is the normalised, masked input with the mask as last channel;
    xyz (B,3,H,W) are the raw coordinates and mask (B,1,H,W) the valid mask, used by the CRF only.
    """

    def __init__(self, channels: Sequence[str] = DEFAULT_CHANNELS, crf_iterations: int = 3,
                 num_classes: int = NUM_CLASSES, dropout: float = 0.5) -> None:
        super().__init__()
        bad = [c for c in channels if c not in ALL_CHANNELS]
        if bad or not channels:
            raise ValueError(f"channels must be a subset of {ALL_CHANNELS}, got {list(channels)}")
        self.channels = tuple(channels)
        self.crf_iterations = crf_iterations
        cin = len(self.channels) + 1  # + mask
        self.conv1 = Conv(cin, 64, 3, stride=(1, 2))
        self.conv1_skip = Conv(cin, 64, 1)
        self.pool1 = Pool()
        self.fire2 = Fire(64, 16, 64, 64)
        self.fire3 = Fire(128, 16, 64, 64)
        self.pool3 = Pool()
        self.fire4 = Fire(128, 32, 128, 128)
        self.fire5 = Fire(256, 32, 128, 128)
        self.pool5 = Pool()
        self.fire6 = Fire(256, 48, 192, 192)
        self.fire7 = Fire(384, 48, 192, 192)
        self.fire8 = Fire(384, 64, 256, 256)
        self.fire9 = Fire(512, 64, 256, 256)
        self.fire_deconv10 = FireDeconv(512, 64, 128, 128)
        self.fire_deconv11 = FireDeconv(256, 32, 64, 64)
        self.fire_deconv12 = FireDeconv(128, 16, 32, 32)
        self.fire_deconv13 = FireDeconv(64, 16, 32, 32)
        self.drop = nn.Dropout(dropout)
        self.conv14 = Conv(64, num_classes, 3, relu=False)
        # The published CRF kernels are per KITTI class; other class sets take car's for all.
        thetas = {} if num_classes == NUM_CLASSES else {
            "theta_a": [THETA_A[1]] * num_classes, "theta_r": [THETA_R[1]] * num_classes}
        self.crf = RecurrentCRF(crf_iterations, num_classes, **thetas)

    def backbone(self, x: torch.Tensor) -> torch.Tensor:
        """Logits before the CRF."""
        conv1 = self.conv1(x)
        skip = self.conv1_skip(x)
        fire3 = self.fire3(self.fire2(self.pool1(conv1)))
        fire5 = self.fire5(self.fire4(self.pool3(fire3)))
        fire9 = self.fire9(self.fire8(self.fire7(self.fire6(self.pool5(fire5)))))
        f10 = self.fire_deconv10(fire9, int(fire5.shape[-1])) + fire5
        f11 = self.fire_deconv11(f10, int(fire3.shape[-1])) + fire3
        f12 = self.fire_deconv12(f11, int(conv1.shape[-1])) + conv1
        f13 = self.fire_deconv13(f12, int(skip.shape[-1])) + skip
        return self.conv14(self.drop(f13))

    def forward(self, x: torch.Tensor, xyz: torch.Tensor | None = None,
                mask: torch.Tensor | None = None) -> torch.Tensor:
        logits = self.backbone(x)
        if self.crf_iterations == 0:
            return logits
        if mask is None:
            mask = x[:, -1:]
        if xyz is None:
            raise ValueError("the CRF needs the raw xyz input")
        return self.crf(logits, xyz, mask)


def load_state(weights) -> dict:
    """The model state of a weights file: a state dict, or a training checkpoint's `model`;
    FalsifyError naming the file when it is neither."""
    from falsify.errors import FalsifyError

    try:
        state = torch.load(weights, map_location="cpu", weights_only=True)
    except Exception as exc:  # OSError, RuntimeError, pickle.UnpicklingError, ...
        raise FalsifyError(f"{weights}: cannot load weights "
                           f"({str(exc).splitlines()[0]})") from None
    if not isinstance(state, dict):
        raise FalsifyError(f"{weights}: not a state dict or training checkpoint")
    return state.get("model", state)


def load_weights_into(model: SqueezeSeg, state: dict, weights: object) -> None:
    """Load `state` into `model`; FalsifyError naming `weights` and, for SqueezeSeg weights of
    another class set or input channels, both shapes (torch's own message names neither)."""
    from falsify.errors import FalsifyError

    try:
        model.load_state_dict(state)
    except RuntimeError as exc:
        bias, conv1 = state.get("conv14.conv.bias"), state.get("conv1.conv.weight")
        want = (model.conv14.conv.out_channels, len(model.channels))
        if (isinstance(bias, torch.Tensor) and bias.ndim == 1 and isinstance(conv1, torch.Tensor)
                and conv1.ndim == 4 and (bias.shape[0], conv1.shape[1] - 1) != want):
            raise FalsifyError(
                f"{weights}: SqueezeSeg weights for {bias.shape[0]} classes and "
                f"{conv1.shape[1] - 1} input channels; this needs {want[0]} classes and "
                f"{want[1]} channels ({','.join(model.channels)})") from None
        detail = [ln.strip() for ln in str(exc).splitlines()[1:] if ln.strip()]
        raise FalsifyError(f"{weights}: not SqueezeSeg weights "
                           f"({(detail or [str(exc)])[0][:200]})") from None


def count_parameters(model: nn.Module, include_crf: bool = False) -> int:
    """Trainable parameter count, by default without the CRF's compatibility matrices."""
    return sum(p.numel() for n, p in model.named_parameters() if include_crf or "crf." not in n)

