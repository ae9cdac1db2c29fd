"""Auxiliary heads on the camera BEV, for training only: denser supervision of the camera's BEV
than the anchor head's few positives give it.

- ``cam_heatmap > 0``: a class-centre heatmap head (a 3x3 conv-BN-ReLU and a 1x1 conv to one
  logit per class, CenterPoint's heatmap head at its smallest), trained against CenterPoint's
  Gaussians of the boxes (:mod:`clfbev.supervision.heatmap`);
- ``cam_distill > 0``: a 1x1 adapter from the camera BEV's channels to a lidar teacher's, trained
  to reproduce the teacher's BEV features (:mod:`clfbev.supervision.distill`).

Neither feeds the detection: the camera BEV that reaches the backbone (or the fusion) is the
same tensor, and what they change is only the gradient it receives. Their weights are in the
detector's state dict (so a resumed run continues them) and unused at inference.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import Tensor, nn

from clfbev.config import ModelConfig
from clfbev.layers import conv_bn_relu


# The heatmap head's initial centre probability (CenterPoint's heatmap bias of -2.19).
HEATMAP_PRIOR = 0.1


def heatmap_prior_bias() -> float:
    """The logit of :data:`HEATMAP_PRIOR`: the heatmap head's initial bias."""
    return -math.log((1 - HEATMAP_PRIOR) / HEATMAP_PRIOR)


class CameraAuxOutputs(NamedTuple):
    """heatmap : (B, n_classes, ny, nx) centre logits, or None without the heatmap head.
    distill : (B, teacher_channels, ny, nx) the adapted camera BEV, or None without the adapter."""

    heatmap: Tensor | None = None
    distill: Tensor | None = None


def teacher_channels(cfg: ModelConfig) -> int:
    """Channels of a lidar teacher's features for ``cfg``: its sparse encoder's, the lidar BEV
    without the sweep bands' channels that join it."""
    trail_out = 0 if cfg.sweep_trail_in_bev else cfg.trail_channels
    return cfg.lidar_bev_channels - cfg.sweep_channels + trail_out


class CameraBEVHeads(nn.Module):
    """The auxiliary heads on a camera BEV of ``in_ch`` channels.

    n_classes : heatmap channels (0: no heatmap head). distill_ch : the teacher's channels (0: no
    adapter).
    """

    def __init__(self, in_ch: int, n_classes: int, distill_ch: int) -> None:
        super().__init__()
        self.heatmap: nn.Sequential | None = None
        self.adapter: nn.Conv2d | None = None
        if n_classes > 0:
            self.heatmap = nn.Sequential(*conv_bn_relu(in_ch, in_ch), nn.Conv2d(in_ch, n_classes, 1))
            # CenterPoint's start: every cell at the centre probability HEATMAP_PRIOR.
            nn.init.constant_(self.heatmap[-1].bias, heatmap_prior_bias())
        if distill_ch > 0:
            self.adapter = nn.Conv2d(in_ch, distill_ch, 1)

    @classmethod
    def from_config(cls, cfg: ModelConfig) -> "CameraBEVHeads | None":
        """The heads ``cfg`` asks for (``cam_heatmap``, ``cam_distill``), or None for neither."""
        if not (cfg.cam_heatmap > 0 or cfg.cam_distill > 0):
            return None
        return cls(cfg.cam_bev_channels, len(cfg.class_names) if cfg.cam_heatmap > 0 else 0,
                   teacher_channels(cfg) if cfg.cam_distill > 0 else 0)

    def forward(self, cam_bev: Tensor) -> CameraAuxOutputs:
        """cam_bev (B, in_ch, ny, nx) -> :class:`CameraAuxOutputs`."""
        x = cam_bev.contiguous(memory_format=torch.channels_last)
        return CameraAuxOutputs(None if self.heatmap is None else self.heatmap(x),
                                None if self.adapter is None else self.adapter(x))
