"""ResNet-18/34/50/101 image backbone and an FPN neck, in plain torch.

torchvision has no CPU build on this machine, so the backbone is written out here. It is trained
from scratch: there is no weight download, ever. The layout follows He et al. (2016) and
torchvision's ``resnet*`` (stride on the 3x3 conv of a bottleneck, "ResNet v1.5"), with one extra
knob, ``width``: the channels of the first stage (64 in the paper). The CPU ``tiny`` config uses a
narrow ResNet-18 (width 16 or 32); every stage scales with it.

Feature maps, for an input of (B, 3, H, W):

====  ======  ====================================
name  stride  channels (expansion e: 1 basic, 4 bottleneck)
====  ======  ====================================
C3    8       2 * width * e
C4    16      4 * width * e
C5    32      8 * width * e
====  ======  ====================================

Spatial sizes follow conv arithmetic (``ceil(H / stride)`` per stride-2 step), so an H divisible
by 32 gives exactly H / stride.
"""

from __future__ import annotations

import torch.nn.functional as F
from torch import Tensor, nn

# depth -> (block kind, blocks per stage)
_LAYOUTS: dict[int, tuple[str, tuple[int, int, int, int]]] = {
    18: ("basic", (2, 2, 2, 2)),
    34: ("basic", (3, 4, 6, 3)),
    50: ("bottleneck", (3, 4, 6, 3)),
    101: ("bottleneck", (3, 4, 23, 3)),
}


def _conv_bn(in_ch: int, out_ch: int, k: int, stride: int = 1) -> list[nn.Module]:
    # No conv bias: the BatchNorm shift right after makes it redundant.
    return [nn.Conv2d(in_ch, out_ch, k, stride, padding=k // 2, bias=False), nn.BatchNorm2d(out_ch)]


class BasicBlock(nn.Module):
    """Two 3x3 convs plus identity (or 1x1 projection) shortcut; ResNet-18/34."""

    expansion = 1

    def __init__(self, in_ch: int, mid_ch: int, stride: int = 1) -> None:
        super().__init__()
        out_ch = mid_ch * self.expansion
        self.body = nn.Sequential(
            *_conv_bn(in_ch, mid_ch, 3, stride), nn.ReLU(inplace=True), *_conv_bn(mid_ch, out_ch, 3)
        )
        self.shortcut = (
            nn.Sequential(*_conv_bn(in_ch, out_ch, 1, stride))
            if stride != 1 or in_ch != out_ch
            else nn.Identity()
        )

    def forward(self, x: Tensor) -> Tensor:
        return F.relu(self.body(x) + self.shortcut(x), inplace=True)


class Bottleneck(nn.Module):
    """1x1 reduce, 3x3 (carries the stride), 1x1 expand by 4, plus shortcut; ResNet-50/101."""

    expansion = 4

    def __init__(self, in_ch: int, mid_ch: int, stride: int = 1) -> None:
        super().__init__()
        out_ch = mid_ch * self.expansion
        self.body = nn.Sequential(
            *_conv_bn(in_ch, mid_ch, 1), nn.ReLU(inplace=True),
            *_conv_bn(mid_ch, mid_ch, 3, stride), nn.ReLU(inplace=True),
            *_conv_bn(mid_ch, out_ch, 1),
        )
        self.shortcut = (
            nn.Sequential(*_conv_bn(in_ch, out_ch, 1, stride))
            if stride != 1 or in_ch != out_ch
            else nn.Identity()
        )

    def forward(self, x: Tensor) -> Tensor:
        return F.relu(self.body(x) + self.shortcut(x), inplace=True)


class ResNet(nn.Module):
    """ResNet backbone returning (C3, C4, C5) at strides (8, 16, 32).

    Parameters
    ----------
    depth : 18, 34, 50 or 101.
    in_ch : input image channels.
    width : channels of the first stage (64 in the standard nets); stage i has ``width * 2**i``
        mid channels.
    zero_init_residual : start the last BN of every block at gamma = 0, so each block starts as
        the identity (Goyal et al. 2017; helps training from scratch). Off by default because it
        also zeroes the initial gradient of the convs inside each block.
    """

    def __init__(self, depth: int, in_ch: int = 3, width: int = 64, zero_init_residual: bool = False) -> None:
        super().__init__()
        if depth not in _LAYOUTS:
            raise ValueError(f"ResNet depth must be one of {sorted(_LAYOUTS)}, got {depth}")
        if width < 1:
            raise ValueError(f"ResNet width must be >= 1, got {width}")
        kind, blocks = _LAYOUTS[depth]
        block = BasicBlock if kind == "basic" else Bottleneck
        self.depth = depth
        # Stem: 7x7/2 conv + 3x3/2 max-pool -> stride 4.
        self.stem = nn.Sequential(
            *_conv_bn(in_ch, width, 7, 2), nn.ReLU(inplace=True), nn.MaxPool2d(3, 2, padding=1)
        )
        stages = []
        ch = width
        for i, n in enumerate(blocks):
            mid = width * 2**i
            layers = []
            for j in range(n):
                # The first block of stages 2..4 halves the resolution (stride 4 -> 8 -> 16 -> 32).
                stride = 2 if (j == 0 and i > 0) else 1
                layers.append(block(ch, mid, stride))
                ch = mid * block.expansion
            stages.append(nn.Sequential(*layers))
        self.layer1, self.layer2, self.layer3, self.layer4 = stages
        self._out_channels = tuple(width * 2**i * block.expansion for i in (1, 2, 3))
        self._init_weights(zero_init_residual)

    def _init_weights(self, zero_init_residual: bool) -> None:
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")
            elif isinstance(m, nn.BatchNorm2d):
                nn.init.ones_(m.weight)
                nn.init.zeros_(m.bias)
        if zero_init_residual:
            for m in self.modules():
                if isinstance(m, (BasicBlock, Bottleneck)):
                    nn.init.zeros_(m.body[-1].weight)

    @property
    def out_channels(self) -> tuple[int, int, int]:
        """Channels of (C3, C4, C5)."""
        return self._out_channels

    @property
    def strides(self) -> tuple[int, int, int]:
        """Output strides of (C3, C4, C5) with respect to the input."""
        return (8, 16, 32)

    def forward(self, x: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """x (B, in_ch, H, W) -> (C3 (B, c3, H/8, W/8), C4 (B, c4, H/16, W/16), C5 (B, c5, H/32, W/32))."""
        c2 = self.layer1(self.stem(x))
        c3 = self.layer2(c2)
        c4 = self.layer3(c3)
        c5 = self.layer4(c4)
        return c3, c4, c5


class FPN(nn.Module):
    """Feature pyramid (Lin et al. 2017) fused into ONE map at the finest input's resolution.

    Lateral 1x1 convs bring every level to ``out_ch``; a top-down pass upsamples (nearest, to
    the exact size of the finer level, so odd sizes such as 11 -> 6 round trip) and adds; a 3x3
    conv + BN + ReLU smooths the sum. Only the finest map is returned, because lift-splat needs a
    single feature map per image.

    The output stride is that of the first input. The camera encoder passes (C3, C4, C5) for a
    stride-8 map (the default: denser frustum, as BEVFusion) or (C4, C5) for stride 16 (BEVDet;
    4x fewer frustum points, cheaper on CPU).

    Parameters
    ----------
    in_channels : channels of the inputs, finest first.
    out_ch : output channels.
    """

    def __init__(self, in_channels: list[int] | tuple[int, ...], out_ch: int) -> None:
        super().__init__()
        if len(in_channels) < 1:
            raise ValueError("FPN needs at least one input level")
        self.lateral = nn.ModuleList(nn.Conv2d(c, out_ch, 1) for c in in_channels)
        self.smooth = nn.Sequential(*_conv_bn(out_ch, out_ch, 3), nn.ReLU(inplace=True))
        self.out_ch = out_ch

    def forward(self, feats: list[Tensor] | tuple[Tensor, ...]) -> Tensor:
        """feats: maps (B, c_i, h_i, w_i), finest first -> (B, out_ch, h_0, w_0)."""
        if len(feats) != len(self.lateral):
            raise ValueError(f"FPN built for {len(self.lateral)} levels, got {len(feats)}")
        x = self.lateral[-1](feats[-1])
        for lat, f in zip(reversed(self.lateral[:-1]), reversed(feats[:-1])):
            x = lat(f) + F.interpolate(x, size=f.shape[-2:], mode="nearest")
        return self.smooth(x)
