"""The BatchNorm settings of SECOND / spconv networks and the 3x3 conv-BN-ReLU block built on
them, shared by the sparse lidar encoder, the BEV backbone and the head's velocity tower."""
from __future__ import annotations

from torch import nn

# A small momentum: BEV and sparse batches are small and noisy (SECOND, OpenPCDet).
BN_EPS, BN_MOMENTUM = 1e-3, 0.01


def conv_bn_relu(in_ch: int, out_ch: int, stride: int = 1, dilation: int = 1) -> list[nn.Module]:
    """A 3x3 convolution (size-preserving padding at stride 1), BatchNorm2d, ReLU."""
    return [
        # No conv bias: the BatchNorm's shift is the bias.
        nn.Conv2d(in_ch, out_ch, 3, stride=stride, padding=dilation, dilation=dilation, bias=False),
        nn.BatchNorm2d(out_ch, eps=BN_EPS, momentum=BN_MOMENTUM),
        nn.ReLU(inplace=True),
    ]
