"""Anchor detection head (PointPillars / SECOND SSD head): predictions and decoding to boxes
(the target assignment is :mod:`clfbev.supervision.assign`).

Layout
------
Anchors are class-specific (:mod:`clfbev.anchors`): each BEV cell has ``A = n_cls * n_rot``
anchors, anchor ``a = cls * n_rot + rot``. Each anchor predicts

* one classification logit, for *its own* class: matching is class-aware, so an anchor of
  class c can only ever be positive for c, and logits for the other classes would always have
  target 0;
* ``code_size`` box residuals (:func:`clfbev.ops.boxes.encode_boxes`: 7 + ``vx, vy``);
* ``n_dir_bins`` direction logits (which half-turn the heading is in).

Map channels are anchor-major: channel ``a * k + j`` holds value ``j`` of anchor ``a``
(``k = 1, code_size, n_dir_bins``). :meth:`HeadOutput.flatten` turns the maps into per-anchor
rows in the order ``(iy, ix, cls, rot)``, the order of ``make_anchors(...).reshape(-1, 7)``.

Labels: GT labels and decoded labels are 0-based indices into the head's class list; the
assignment labels are ``-1`` ignore, ``0`` background, ``1 + class`` positive.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from clfbev.anchors import anchor_class_ids
from clfbev.geometry import DIR_OFFSET
from clfbev.layers import BN_EPS, BN_MOMENTUM, conv_bn_relu
from clfbev.ops.boxes import decode_boxes, limit_period, rotated_nms

# Largest predicted log size ratio at decoding (exp(4) ~ 55x the anchor): keeps an untrained
# head from producing inf sizes, far beyond any real box.
_MAX_LOG_SIZE = 4.0


@dataclass(frozen=True)
class FlatPredictions:
    """Per-anchor predictions, anchors in the order ``(iy, ix, cls, rot)``.

    cls_logits : (B, N) one logit per anchor (its own class).
    box_deltas : (B, N, code_size) residuals.
    dir_logits : (B, N, n_dir_bins).
    moving_logits : (B, N) the velocity gate's logit (the box moves), or None without a gate.
    still_logits : (B, N) the logit of still state 1 (:mod:`clfbev.attributes`), or None without
        that head.
    """

    cls_logits: Tensor
    box_deltas: Tensor
    dir_logits: Tensor
    moving_logits: Tensor | None = None
    still_logits: Tensor | None = None


def _flatten_map(x: Tensor, n_anchors: int) -> Tensor:
    """(B, A * k, H, W) anchor-major channels -> (B, H * W * A, k)."""
    b, c, h, w = x.shape
    k = c // n_anchors
    return x.reshape(b, n_anchors, k, h, w).permute(0, 3, 4, 1, 2).reshape(b, h * w * n_anchors, k)


def per_anchor(x: Tensor | None, n_anchors: int) -> Tensor | None:
    """(B, A, H, W) one value per anchor -> (B, H * W * A); None stays None."""
    return None if x is None else _flatten_map(x, n_anchors)[..., 0]


def pointwise(conv: nn.Conv2d, x: Tensor) -> Tensor:
    """The 1x1 convolution ``conv`` of x (B, C, H, W) as one matrix product over the channels
    of the channels-last rows: (B, C_out, H, W) in channels-last memory, the numbers of
    ``conv(x)``. The maps then flatten to per-anchor rows without a copy (:func:`_flatten_map`);
    ``conv(x)`` on one CPU thread takes PyTorch's im2col path for a 1x1 kernel, with a layout
    copy of its input and output each way, forward and backward."""
    return F.linear(x.permute(0, 2, 3, 1), conv.weight.flatten(1), conv.bias).permute(0, 3, 1, 2)


@dataclass(frozen=True)
class HeadOutput:
    """Raw head maps on the BEV grid (row = y, column = x of the lidar frame).

    cls_logits : (B, A, H, W), ``A = n_cls * n_rot``.
    box_deltas : (B, A * code_size, H, W).
    dir_logits : (B, A * n_dir_bins, H, W).
    moving_logits : (B, A, H, W) the velocity gate's logits, or None without a gate.
    still_logits : (B, A, H, W) the still-state logits (:mod:`clfbev.attributes`), or None.
    """

    cls_logits: Tensor
    box_deltas: Tensor
    dir_logits: Tensor
    moving_logits: Tensor | None = None
    still_logits: Tensor | None = None

    def flatten(self) -> FlatPredictions:
        n_anchors = self.cls_logits.shape[1]
        return FlatPredictions(
            cls_logits=per_anchor(self.cls_logits, n_anchors),
            box_deltas=_flatten_map(self.box_deltas, n_anchors),
            dir_logits=_flatten_map(self.dir_logits, n_anchors),
            moving_logits=per_anchor(self.moving_logits, n_anchors),
            still_logits=per_anchor(self.still_logits, n_anchors),
        )


class VelocityTower(nn.Module):
    """The velocity residuals from their own convolutions, on two scales: a 1x1 conv-BN-ReLU
    reduces the input to ``channels``; a 3x3 stride-2 conv and three 3x3 convs (dilations 1, 2
    and 4) on the half-resolution grid see 31 BEV cells (25 m on the 0.8 m BEV: from a bus's
    centre, both its ends and a 10-sweep trail behind it); their output, upsampled (nearest)
    and joined with the reduced full-resolution input, gives ``vx, vy`` per anchor through a
    1x1 convolution.

    Why its own layers: in a shared 1x1 head the velocity channels read the features that
    classification and box regression shape, in which parked and moving cars look alike; the
    L1-like loss then settles on the parked majority's 0 (docs/benchmarks.md, the linear
    probe). Here only the velocity loss trains these layers, on the backbone output and the
    sweep bands (the point counts per lag band, :mod:`clfbev.sweep_bev`), the trail itself.
    Why this reach: with 15 cells (12 m) the tower found a moving bus's speed but not its sign,
    as from the bus's centre it saw neither end, so not the side the sweeps trail. Why two
    scales: 3x3 convolutions of this width on the full grid cost a fifth of a training step,
    these 8%; the full-resolution skip keeps a pedestrian's velocity its own beside a car's.

    With ``gate`` it also gives each anchor a moving logit: whether the box moves at all (faster
    than :data:`clfbev.supervision.losses.MOVING_SPEED`), a classification that the still
    majority cannot shrink, while the speed is regressed on the moving boxes alone
    (:func:`clfbev.supervision.losses.gated_velocity_loss`); decoding keeps the regressed
    velocity only where the gate fires.

    Parameters
    ----------
    in_ch : channels of the backbone output plus the motion channels.
    n_anchors : anchors per cell.
    channels : width of the convolutions.
    gate : also predict the moving logit.
    """

    DILATIONS = (1, 2, 4)

    def __init__(self, in_ch: int, n_anchors: int, channels: int, gate: bool = False) -> None:
        super().__init__()
        self.outputs = 3 if gate else 2
        self.reduce = nn.Sequential(nn.Conv2d(in_ch, channels, 1, bias=False),
                                    nn.BatchNorm2d(channels, eps=BN_EPS, momentum=BN_MOMENTUM), nn.ReLU(inplace=True))
        layers = conv_bn_relu(channels, channels, stride=2)
        for d in self.DILATIONS:
            layers += conv_bn_relu(channels, channels, dilation=d)
        self.coarse = nn.Sequential(*layers)
        self.out = nn.Conv2d(2 * channels, n_anchors * self.outputs, 1)
        nn.init.normal_(self.out.weight, std=0.01)   # starts at 0 m/s, like the head's residuals
        nn.init.zeros_(self.out.bias)

    def forward(self, x: Tensor) -> Tensor:
        """x (B, in_ch, H, W) -> (B, n_anchors * k, H, W), anchor-major ``(vx, vy)`` or, with the
        gate, ``(vx, vy, moving logit)``."""
        fine = self.reduce(x)
        coarse = F.interpolate(self.coarse(fine), size=fine.shape[-2:], mode="nearest")
        return pointwise(self.out, torch.cat([fine, coarse], dim=1))


class AnchorHead(nn.Module):
    """1x1 convolutions from the fused BEV to per-anchor logits, residuals and directions.

    Parameters
    ----------
    in_ch : channels of the BEV feature map.
    n_classes : number of classes (the anchor class axis).
    n_rot : anchor rotations per class and cell.
    code_size : box residuals per anchor (7 + 2 velocity).
    n_dir_bins : direction bins.
    prior_prob : initial foreground probability of every anchor. With focal loss the bias
        ``-log((1 - p) / p)`` keeps the ~all-background start from drowning the first steps in
        a huge background loss (RetinaNet).
    velocity_tower : 0, the velocity is 2 of the 1x1 box residuals; else the width of a
        :class:`VelocityTower` that predicts it (needs ``code_size`` 9).
    motion_ch : channels given to the tower beside the BEV features (the sweep bands).
    velocity_detach : the tower reads the BEV features without sending its gradient back into
        them, so the velocity loss cannot reshape the features the boxes are read from.
    velocity_gate : the tower also predicts whether each box moves (:class:`VelocityTower`).
    still_head : also a 1x1 convolution giving each anchor its still logit: which of its class's
        two states at rest the object is in (:mod:`clfbev.attributes`; parked or stopped, with
        or without a rider).
    """

    def __init__(
        self,
        in_ch: int,
        n_classes: int,
        n_rot: int = 2,
        code_size: int = 9,
        n_dir_bins: int = 2,
        prior_prob: float = 0.01,
        velocity_tower: int = 0,
        motion_ch: int = 0,
        velocity_detach: bool = False,
        velocity_gate: bool = False,
        still_head: bool = False,
    ) -> None:
        super().__init__()
        if velocity_tower and code_size != 9:
            raise ValueError(f"a velocity tower needs code_size 9 (7 + vx, vy), got {code_size}")
        if velocity_gate and not velocity_tower:
            raise ValueError("a velocity gate needs a velocity tower")
        self.n_classes, self.n_rot = n_classes, n_rot
        self.code_size, self.n_dir_bins = code_size, n_dir_bins
        n_anchors = n_classes * n_rot
        self.conv_cls = nn.Conv2d(in_ch, n_anchors, 1)
        self.conv_box = nn.Conv2d(in_ch, n_anchors * (7 if velocity_tower else code_size), 1)
        self.conv_dir = nn.Conv2d(in_ch, n_anchors * n_dir_bins, 1)
        self.velocity = (VelocityTower(in_ch + motion_ch, n_anchors, velocity_tower, velocity_gate)
                         if velocity_tower else None)
        self.velocity_detach = velocity_detach
        self.conv_still = nn.Conv2d(in_ch, n_anchors, 1) if still_head else None
        # Small weights: the first residuals are ~0 (boxes start at the anchors) and the first
        # scores ~prior_prob everywhere.
        for conv in (self.conv_cls, self.conv_box, self.conv_dir, self.conv_still):
            if conv is None:
                continue
            nn.init.normal_(conv.weight, std=0.01)
            nn.init.zeros_(conv.bias)
        nn.init.constant_(self.conv_cls.bias, -math.log((1.0 - prior_prob) / prior_prob))

    def forward(self, bev: Tensor, motion: Tensor | None = None) -> HeadOutput:
        """bev (B, in_ch, H, W), motion (B, motion_ch, H, W) or None -> HeadOutput on the same grid
        (channels-last maps, :func:`pointwise`)."""
        box = pointwise(self.conv_box, bev)
        moving = None
        if self.velocity is not None:
            shared = bev.detach() if self.velocity_detach else bev
            tower_in = shared if motion is None else torch.cat([shared, motion], dim=1)
            b, _, h, w = box.shape
            n_anchors, k = self.n_classes * self.n_rot, self.velocity.outputs
            # Joined per cell and anchor in (B, H, W, A, k) rows, so the channels-last maps stay views.
            tower = self.velocity(tower_in).permute(0, 2, 3, 1).reshape(b, h, w, n_anchors, k)
            box = torch.cat([box.permute(0, 2, 3, 1).reshape(b, h, w, n_anchors, 7), tower[..., :2]], dim=-1)
            box = box.view(b, h, w, n_anchors * 9).permute(0, 3, 1, 2)
            if k == 3:
                moving = tower[..., 2].permute(0, 3, 1, 2)
        still = None if self.conv_still is None else pointwise(self.conv_still, bev)
        return HeadOutput(pointwise(self.conv_cls, bev), box, pointwise(self.conv_dir, bev), moving, still)


# ----------------------------------------------------------------------------------------------
# Decoding
# ----------------------------------------------------------------------------------------------


class Detections(NamedTuple):
    """Detections of one sample, sorted by descending score (a NamedTuple: ``dets[:3]`` is
    ``boxes, scores, labels``).

    boxes : (K, code_size) ``(x, y, z, l, w, h, yaw, vx, vy)``, lidar frame, yaw in
        ``[dir_offset, dir_offset + 2 pi)``.
    scores : (K,) sigmoid scores.
    labels : (K,) int64 class indices (0-based).
    still : (K,) the still-state logits (:mod:`clfbev.attributes`), or None without that head.
    """

    boxes: Tensor
    scores: Tensor
    labels: Tensor
    still: Tensor | None = None


def correct_direction(yaw: Tensor, dir_bin: Tensor, dir_offset: float = DIR_OFFSET, n_bins: int = 2) -> Tensor:
    """Heading from the pi-periodic regressed yaw and the direction bin:
    ``limit_period(yaw - offset, 0, P) + offset + P * bin`` with ``P = 2 pi / n_bins``."""
    period = 2.0 * math.pi / n_bins
    return limit_period(yaw - dir_offset, 0.0, period) + dir_offset + period * dir_bin.to(yaw.dtype)


def heading_from_motion(boxes: Tensor, min_speed: float, dir_offset: float = DIR_OFFSET,
                        follow: Tensor | None = None) -> Tensor:
    """(K,) the yaw of ``boxes`` (K, >= 9) ``x, y, z, l, w, h, yaw, vx, vy`` (lidar frame),
    turned by pi where the box moves faster than ``min_speed`` m/s against its heading, and set
    to the velocity's direction where it moves that fast and ``follow`` (K,) bool is True.

    A vehicle, cycle or walker moves forwards: where the velocity, read from the sweeps' trail,
    is clearly above noise it tells front from back better than the direction bin, which sees
    a near-symmetric shape. A walker's near-square footprint does not even show its axis, so
    for the classes of ``follow`` the velocity gives the whole heading. Kept in
    ``[dir_offset, dir_offset + 2 pi)``."""
    yaw, vx, vy = boxes[:, 6], boxes[:, 7], boxes[:, 8]
    moving = torch.hypot(vx, vy) > min_speed
    against = (torch.cos(yaw) * vx + torch.sin(yaw) * vy) < 0
    yaw = torch.where(moving & against, yaw + math.pi, yaw)
    if follow is not None:
        yaw = torch.where(moving & follow, torch.atan2(vy, vx), yaw)
    return limit_period(yaw - dir_offset, 0.0, 2.0 * math.pi) + dir_offset


@torch.no_grad()
def decode(
    cls_logits: Tensor,
    box_deltas: Tensor,
    dir_logits: Tensor,
    anchors: Tensor,
    score_thr: float = 0.1,
    nms_iou: float = 0.2,
    max_per_sample: int = 500,
    pre_nms: int = 1000,
    dir_offset: float = DIR_OFFSET,
    heading_speed: float = 0.0,
    moving_logits: Tensor | None = None,
    heading_follow: tuple[int, ...] = (),
    still_logits: Tensor | None = None,
) -> list[Detections]:
    """Head maps -> boxes in the lidar frame, per sample.

    Sigmoid scores, the ``pre_nms`` best anchors, those with score >= ``score_thr`` are
    decoded, their heading corrected by the direction bin, then rotated NMS per class, and the
    ``max_per_sample`` best survivors kept.

    Parameters
    ----------
    cls_logits, box_deltas, dir_logits : the maps of :class:`HeadOutput`, (B, A * k, H, W).
    anchors : (H, W, n_cls, n_rot, 7) anchors of the same grid.
    score_thr : minimum score.
    nms_iou : BEV IoU above which a lower-scoring box of the same class is suppressed.
    max_per_sample : boxes kept per sample after NMS.
    pre_nms : anchors considered per sample (bounds NMS cost).
    dir_offset : start of the direction bins, as in training.
    heading_speed : m/s; above it a box's heading follows its predicted velocity
        (:func:`heading_from_motion`); 0: off.
    heading_follow : class indices whose heading is set to the predicted velocity's direction
        above ``heading_speed`` (the others' is only turned by pi).
    moving_logits : (B, A, H, W) the velocity gate's logits, or None: where given, a box whose
        gate says still (logit < 0) gets velocity 0, whatever was regressed.
    still_logits : (B, A, H, W) the still-state logits, or None: each box keeps its anchor's.

    Returns
    -------
    B Detections.
    """
    flat = HeadOutput(cls_logits, box_deltas, dir_logits, moving_logits, still_logits).flatten()
    flat_anchors = anchors.reshape(-1, 7).to(box_deltas.dtype)
    class_ids = anchor_class_ids(anchors)
    n_bins = flat.dir_logits.shape[-1]
    results = []
    for b in range(flat.cls_logits.shape[0]):
        scores = torch.sigmoid(flat.cls_logits[b])
        top_scores, top = torch.topk(scores, min(pre_nms, scores.shape[0]))
        keep = top_scores >= score_thr
        top, top_scores = top[keep], top_scores[keep]

        deltas = flat.box_deltas[b, top].clone()
        deltas[:, 3:6] = deltas[:, 3:6].clamp(max=_MAX_LOG_SIZE)
        if flat.moving_logits is not None:
            deltas[:, 7:9] *= (flat.moving_logits[b, top] >= 0).to(deltas.dtype)[:, None]
        boxes = decode_boxes(deltas, flat_anchors[top])
        dir_bin = flat.dir_logits[b, top].argmax(dim=-1)
        boxes[:, 6] = correct_direction(boxes[:, 6], dir_bin, dir_offset, n_bins)
        labels = class_ids[top]
        if heading_speed > 0 and boxes.shape[1] >= 9:
            follow = torch.isin(labels, torch.tensor(heading_follow, dtype=labels.dtype, device=labels.device))
            boxes[:, 6] = heading_from_motion(boxes, heading_speed, dir_offset, follow)

        # Per-class NMS: a car and a pedestrian may overlap in BEV (a person next to a door).
        kept = [top.new_zeros(0)]
        for c in torch.unique(labels).tolist():
            idx = torch.nonzero(labels == c).flatten()
            kept.append(idx[rotated_nms(boxes[idx], top_scores[idx], nms_iou, max_out=max_per_sample)])
        kept_idx = torch.cat(kept)
        order = torch.sort(top_scores[kept_idx], descending=True, stable=True).indices[:max_per_sample]
        kept_idx = kept_idx[order]
        still = None if flat.still_logits is None else flat.still_logits[b, top[kept_idx]]
        results.append(Detections(boxes[kept_idx], top_scores[kept_idx], labels[kept_idx], still))
    return results
