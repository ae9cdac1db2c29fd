"""Anchor detection head (PointPillars / SECOND SSD head): predictions, target assignment,
decoding to boxes.

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
from collections.abc import Sequence
from dataclasses import dataclass, fields
from typing import NamedTuple

import torch
from torch import Tensor, nn

from clfbev.anchors import anchor_class_ids
from clfbev.ops.boxes import bev_iou, decode_boxes, encode_boxes, limit_period, rotated_nms

# Direction bins start at this heading: with 2 bins, bin 0 is [-pi/4, 3pi/4) and bin 1
# [3pi/4, 7pi/4). The bin borders sit on the diagonals, away from the headings along and
# across the road where most objects are, so few targets fall right on a border (mmdet3d's
# nuScenes PointPillars uses the same -pi/4).
DIR_OFFSET = -0.25 * math.pi

# Largest predicted log size ratio at decoding (exp(4) ~ 55x the anchor): keeps an untrained
# head from producing inf sizes, far beyond any real box.
_MAX_LOG_SIZE = 4.0


@dataclass(frozen=True)
class FlatPredictions:
    """Per-anchor predictions, anchors in the order ``(iy, ix, cls, rot)``.

    cls_logits : (B, N) one logit per anchor (its own class).
    box_deltas : (B, N, code_size) residuals.
    dir_logits : (B, N, n_dir_bins).
    """

    cls_logits: Tensor
    box_deltas: Tensor
    dir_logits: Tensor


def _flatten_map(x: Tensor, n_anchors: int) -> Tensor:
    """(B, A * k, H, W) anchor-major channels -> (B, H * W * A, k)."""
    b, c, h, w = x.shape
    k = c // n_anchors
    return x.view(b, n_anchors, k, h, w).permute(0, 3, 4, 1, 2).reshape(b, h * w * n_anchors, k)


@dataclass(frozen=True)
class HeadOutput:
    """Raw head maps on the BEV grid (row = y, column = x of the lidar frame).

    cls_logits : (B, A, H, W), ``A = n_cls * n_rot``.
    box_deltas : (B, A * code_size, H, W).
    dir_logits : (B, A * n_dir_bins, H, W).
    """

    cls_logits: Tensor
    box_deltas: Tensor
    dir_logits: Tensor

    def flatten(self) -> FlatPredictions:
        n_anchors = self.cls_logits.shape[1]
        return FlatPredictions(
            cls_logits=_flatten_map(self.cls_logits, n_anchors)[..., 0],
            box_deltas=_flatten_map(self.box_deltas, n_anchors),
            dir_logits=_flatten_map(self.dir_logits, n_anchors),
        )


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
    """

    def __init__(
        self,
        in_ch: int,
        n_classes: int,
        n_rot: int = 2,
        code_size: int = 9,
        n_dir_bins: int = 2,
        prior_prob: float = 0.01,
    ) -> None:
        super().__init__()
        self.n_classes, self.n_rot = n_classes, n_rot
        self.code_size, self.n_dir_bins = code_size, n_dir_bins
        n_anchors = n_classes * n_rot
        self.conv_cls = nn.Conv2d(in_ch, n_anchors, 1)
        self.conv_box = nn.Conv2d(in_ch, n_anchors * code_size, 1)
        self.conv_dir = nn.Conv2d(in_ch, n_anchors * n_dir_bins, 1)
        # Small weights: the first residuals are ~0 (boxes start at the anchors) and the first
        # scores ~prior_prob everywhere.
        for conv in (self.conv_cls, self.conv_box, self.conv_dir):
            nn.init.normal_(conv.weight, std=0.01)
            nn.init.zeros_(conv.bias)
        nn.init.constant_(self.conv_cls.bias, -math.log((1.0 - prior_prob) / prior_prob))

    def forward(self, bev: Tensor) -> HeadOutput:
        """bev (B, in_ch, H, W) -> HeadOutput on the same grid."""
        return HeadOutput(self.conv_cls(bev), self.conv_box(bev), self.conv_dir(bev))


# ----------------------------------------------------------------------------------------------
# Targets
# ----------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Targets:
    """Training targets per anchor, anchors in the order ``(iy, ix, cls, rot)``; a leading
    batch axis when stacked with :func:`stack_targets`.

    labels : (..., N) int64: -1 ignore, 0 background, ``1 + class`` positive.
    cls_weights : (..., N) float: 1 where the anchor counts in the classification loss
        (positive or negative), 0 where ignored.
    box_targets : (..., N, code_size) residuals of the matched GT (0 off positives).
    box_weights : (..., N, code_size) float: 1 on positives, 0 elsewhere and on unknown (NaN)
        GT velocities.
    dir_targets : (..., N) int64 direction bin of the matched GT heading (0 off positives).
    matched_gt : (..., N) int64 index of the matched GT box, -1 off positives.
    """

    labels: Tensor
    cls_weights: Tensor
    box_targets: Tensor
    box_weights: Tensor
    dir_targets: Tensor
    matched_gt: Tensor

    @property
    def positives(self) -> Tensor:
        """(..., N) bool, anchors with a matched GT."""
        return self.labels > 0


def stack_targets(targets: Sequence[Targets]) -> Targets:
    """Per-sample targets -> one batch with a leading axis B (all samples share the anchors)."""
    return Targets(*(torch.stack([getattr(t, f.name) for t in targets]) for f in fields(Targets)))


def direction_target(yaw: Tensor, dir_offset: float = DIR_OFFSET, n_bins: int = 2) -> Tensor:
    """Direction bin of a heading (eq. 8): ``floor(limit_period(yaw - offset, 0, 2 pi) / (2 pi /
    n_bins))``. yaw (...,) radians, lidar frame -> (...,) int64 in ``[0, n_bins)``."""
    wrapped = limit_period(yaw - dir_offset, 0.0, 2.0 * math.pi)
    return torch.floor(wrapped / (2.0 * math.pi / n_bins)).long().clamp(0, n_bins - 1)


def assign_targets(
    anchors: Tensor,
    gt_boxes: Tensor,
    gt_labels: Tensor,
    thresholds: Sequence[tuple[float, float]],
    dir_offset: float = DIR_OFFSET,
    n_dir_bins: int = 2,
) -> Targets:
    """Class-aware anchor matching by BEV IoU, as in SECOND, for one sample.

    Anchors of class c are compared only with GT of class c. Per anchor, with ``iou`` its best
    IoU over those GT: positive if ``iou >= pos``, negative if ``iou < neg``, ignored in
    between. Each GT's best anchor(s) (all ties, if that IoU > 0) are forced positive, so
    that a GT far from every anchor centre, or a small one on a coarse grid, still trains
    something; a GT touching no anchor of its class stays unmatched. A positive anchor
    regresses its best-IoU GT (for a forced anchor that is the forcing GT unless two GT share
    the anchor, as in SECOND).

    Parameters
    ----------
    anchors : (ny, nx, n_cls, n_rot, 7) from :func:`clfbev.anchors.make_anchors`, lidar frame.
    gt_boxes : (M, 7 + E) GT boxes ``(x, y, z, l, w, h, yaw[, vx, vy])``, lidar frame. NaN
        velocities (unknown) get box weight 0.
    gt_labels : (M,) int64 class indices into the anchors' class axis; GT with a label
        outside ``[0, n_cls)`` are ignored (classes the head does not detect).
    thresholds : ``(pos, neg)`` per class, e.g. :func:`clfbev.anchors.match_thresholds`.
    dir_offset, n_dir_bins : direction binning, see :func:`direction_target`.

    Returns
    -------
    Targets with ``N = ny * nx * n_cls * n_rot`` rows and ``code_size = 7 + E``.

    Notes
    -----
    Vectorised per class (the only Python loop). Cost on one CPU thread, 10 classes x 2
    rotations, 50 GT: ~0.2 s on a 128 x 128 grid, ~0.4 s on 180 x 180 (648k anchors); run it
    in the data-loader workers.
    """
    if anchors.dim() != 5 or anchors.shape[-1] != 7:
        raise ValueError(f"anchors must be (ny, nx, n_cls, n_rot, 7), got {tuple(anchors.shape)}")
    n_cls = anchors.shape[2]
    if len(thresholds) != n_cls:
        raise ValueError(f"need (pos, neg) thresholds for {n_cls} classes, got {len(thresholds)}")
    device = anchors.device
    flat_anchors = anchors.reshape(-1, 7)
    n = flat_anchors.shape[0]
    code_size = gt_boxes.shape[1]
    # Class-major copies, made once: each class's anchors and their rows in the flat order.
    anchors_by_class = anchors.permute(2, 0, 1, 3, 4).reshape(n_cls, -1, 7)
    rows_by_class = torch.arange(n, device=device).view(anchors.shape[:4]).permute(2, 0, 1, 3).reshape(n_cls, -1)
    gt_boxes = gt_boxes.to(device=device, dtype=anchors.dtype)
    gt_labels = gt_labels.to(device=device, dtype=torch.long)

    labels = torch.zeros(n, dtype=torch.long, device=device)
    matched = torch.full((n,), -1, dtype=torch.long, device=device)
    for c, (pos_thr, neg_thr) in enumerate(thresholds):
        gt_index = torch.nonzero(gt_labels == c).flatten()
        if gt_index.numel() == 0:
            continue  # no GT of this class: all its anchors are background
        rows = rows_by_class[c]
        iou = bev_iou(anchors_by_class[c], gt_boxes[gt_index])  # (Na_c, M_c)
        best_iou, best_gt = iou.max(dim=1)
        col_best = iou.max(dim=0).values  # (M_c,)
        forced = ((iou == col_best[None]) & (col_best[None] > 0)).any(dim=1)
        positive = (best_iou >= pos_thr) | forced
        class_labels = torch.where(best_iou < neg_thr, 0, -1)
        class_labels = torch.where(positive, c + 1, class_labels)
        labels[rows] = class_labels
        matched[rows] = torch.where(positive, gt_index[best_gt], -1)

    positive = matched >= 0
    box_targets = flat_anchors.new_zeros((n, code_size))
    box_weights = flat_anchors.new_zeros((n, code_size))
    dir_targets = torch.zeros(n, dtype=torch.long, device=device)
    if positive.any():
        gt = gt_boxes[matched[positive]]
        known = torch.isfinite(gt)  # velocity may be NaN where the annotation has none
        codes = encode_boxes(torch.where(known, gt, torch.zeros_like(gt)), flat_anchors[positive])
        box_targets[positive] = codes
        box_weights[positive] = known.to(box_weights.dtype)
        dir_targets[positive] = direction_target(gt[:, 6], dir_offset, n_dir_bins)
    return Targets(
        labels=labels,
        cls_weights=(labels >= 0).to(flat_anchors.dtype),
        box_targets=box_targets,
        box_weights=box_weights,
        dir_targets=dir_targets,
        matched_gt=matched,
    )


# ----------------------------------------------------------------------------------------------
# Decoding
# ----------------------------------------------------------------------------------------------


class Detections(NamedTuple):
    """Detections of one sample, sorted by descending score (a NamedTuple, so it unpacks as
    ``boxes, scores, labels``).

    boxes : (K, code_size) ``(x, y, z, l, w, h, yaw, vx, vy)``, lidar frame, yaw in
        ``[dir_offset, dir_offset + 2 pi)``.
    scores : (K,) sigmoid scores.
    labels : (K,) int64 class indices (0-based).
    """

    boxes: Tensor
    scores: Tensor
    labels: Tensor


def correct_direction(yaw: Tensor, dir_bin: Tensor, dir_offset: float = DIR_OFFSET, n_bins: int = 2) -> Tensor:
    """Heading from the pi-periodic regressed yaw and the direction bin:
    ``limit_period(yaw - offset, 0, P) + offset + P * bin`` with ``P = 2 pi / n_bins``."""
    period = 2.0 * math.pi / n_bins
    return limit_period(yaw - dir_offset, 0.0, period) + dir_offset + period * dir_bin.to(yaw.dtype)


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

    Returns
    -------
    B Detections.
    """
    flat = HeadOutput(cls_logits, box_deltas, dir_logits).flatten()
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
        boxes = decode_boxes(deltas, flat_anchors[top])
        dir_bin = flat.dir_logits[b, top].argmax(dim=-1)
        boxes[:, 6] = correct_direction(boxes[:, 6], dir_bin, dir_offset, n_bins)
        labels = class_ids[top]

        # Per-class NMS: a car and a pedestrian may overlap in BEV (a person next to a door).
        kept = [top.new_zeros(0)]
        for c in torch.unique(labels).tolist():
            idx = torch.nonzero(labels == c).flatten()
            kept.append(idx[rotated_nms(boxes[idx], top_scores[idx], nms_iou, max_out=max_per_sample)])
        kept_idx = torch.cat(kept)
        order = torch.sort(top_scores[kept_idx], descending=True, stable=True).indices[:max_per_sample]
        kept_idx = kept_idx[order]
        results.append(Detections(boxes[kept_idx], top_scores[kept_idx], labels[kept_idx]))
    return results
