"""Target assignment of the anchor head (SECOND's class-aware IoU matching with a forced match
per GT): :func:`assign_targets` turns one sample's GT boxes into per-anchor
:class:`AnchorTargets`.

Anchors are in the order ``(iy, ix, cls, rot)`` of :mod:`clfbev.anchors` (see
:mod:`clfbev.head` for the layout). Labels: GT labels are 0-based indices into the head's class
list; the assignment labels are ``-1`` ignore, ``0`` background, ``1 + class`` positive.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, fields

import torch
from torch import Tensor

from clfbev.geometry import DIR_OFFSET, direction_target
from clfbev.ops.boxes import encode_boxes, limit_period
from clfbev.supervision.anchor_pairs import AnchorGrid, Pairs, anchor_grid, candidate_pairs, exact_ious


@dataclass(frozen=True)
class AnchorTargets:
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

    def to(self, device: torch.device | str) -> "AnchorTargets":
        """A copy with every tensor on ``device``."""
        return AnchorTargets(*(getattr(self, f.name).to(device) for f in fields(self)))


def stack_targets(targets: Sequence[AnchorTargets]) -> AnchorTargets:
    """Per-sample targets -> one batch with a leading axis B (all samples share the anchors)."""
    return AnchorTargets(*(torch.stack([getattr(t, f.name) for t in targets]) for f in fields(AnchorTargets)))



def _closest_rotation(grid: AnchorGrid, gt_yaw: Tensor, gt_cls: Tensor) -> Tensor:
    """(M,) index of the anchor rotation of each GT's class nearest to its yaw, modulo pi
    (boxes are pi-periodic here; the direction bin carries the rest). A yaw exactly between
    two rotations gets the lower index."""
    rotations = grid.template[gt_cls, :, 6].double()  # (M, n_rot)
    gap = limit_period(gt_yaw.double()[:, None] - rotations, 0.5, math.pi).abs()
    return gap.argmin(dim=1)  # argmin returns the first of equal minima


def _nearest_index(centres: Tensor, coord: Tensor) -> Tensor:
    """(M,) index of the centre nearest to each coordinate along one ascending grid axis,
    ties (exactly between two centres) to the lower index."""
    if centres.shape[0] == 1:
        return torch.zeros_like(coord, dtype=torch.long)
    centres = centres.double().contiguous()
    coord = coord.double().contiguous()
    above = torch.searchsorted(centres, coord).clamp(1, centres.shape[0] - 1)
    below = above - 1
    go_up = (centres[above] - coord).abs() < (coord - centres[below]).abs()
    return torch.where(go_up, above, below)


def _best_gt_per_anchor(pairs: Pairs, iou: Tensor, m: int) -> tuple[Tensor, Tensor, Tensor]:
    """Per candidate anchor (the others overlap no GT): its flat index (U,), its best IoU over
    the GT of its class (U,) (0 where none overlaps), and that GT (U,) (ties to the lower GT
    index; -1 where none overlaps)."""
    rows, slot = torch.unique(pairs.row, return_inverse=True)
    best_iou = iou.new_zeros(rows.shape[0]).scatter_reduce(0, slot, iou, "amax")
    tie = (iou > 0) & (iou == best_iou[slot])
    best_gt = torch.full_like(rows, m).scatter_reduce(0, slot[tie], pairs.gt[tie], "amin")
    return rows, best_iou, torch.where(best_gt == m, -1, best_gt)


def _forced_anchors(
    grid: AnchorGrid, pairs: Pairs, iou: Tensor, gt_boxes: Tensor, gt_cls: Tensor, forced_rot: Tensor
) -> tuple[Tensor, Tensor]:
    """The anchor each GT forces positive and its IoU, two (M,) tensors.

    Among the anchors of the GT's class and closest rotation: the highest IoU (ties to the
    lower anchor index); if none overlaps (a small box between anchor centres), the anchor
    whose centre is nearest to the box centre.
    """
    m, n = gt_boxes.shape[0], grid.n_anchors  # n: "no anchor yet", above every index
    on_forced = pairs.rot == forced_rot[pairs.gt]
    best = iou.new_zeros(m).scatter_reduce(0, pairs.gt[on_forced], iou[on_forced], "amax")
    tie = on_forced & (iou > 0) & (iou == best[pairs.gt])
    best_row = torch.full((m,), n, dtype=torch.long, device=iou.device)
    best_row = best_row.scatter_reduce(0, pairs.gt[tie], pairs.row[tie], "amin")
    nearest_row = grid.row(
        _nearest_index(grid.ys, gt_boxes[:, 1]), _nearest_index(grid.xs, gt_boxes[:, 0]), gt_cls, forced_rot
    )
    return torch.where(best > 0, best_row, nearest_row), best


def _forcing_winners(forced_row: Tensor, forced_iou: Tensor) -> Tensor:
    """(M,) bool: the GT that keeps its forced anchor. Where several GT force the same anchor,
    the one with the highest IoU with it wins, ties to the lower GT index; the others keep
    only the anchors they reach above the positive threshold: one pass, a loser gets no
    second choice."""
    m = forced_row.shape[0]
    gt = torch.arange(m, device=forced_row.device)
    anchor, slot = torch.unique(forced_row, return_inverse=True)
    top = forced_iou.new_zeros(anchor.shape[0]).scatter_reduce(0, slot, forced_iou, "amax")
    tie = forced_iou == top[slot]
    first = torch.full_like(anchor, m).scatter_reduce(0, slot[tie], gt[tie], "amin")
    return first[slot] == gt


def _centre_anchors(grid: AnchorGrid, gt_boxes: Tensor, gt_cls: Tensor, rot: Tensor, k: int) -> tuple[Tensor, Tensor]:
    """The ``k`` (<= 4) anchors of each GT's class and rotation ``rot`` whose centres lie nearest
    to its centre (ties to the lower anchor index), and their distances: two (M, k) tensors.
    They lie in the 3 x 3 cells around the nearest one (the 4 nearest centres of a square grid
    are the 2 x 2 cells around the point); where the grid's edge cuts those, fewer are found
    (their distance is inf)."""
    m, ny, nx = gt_boxes.shape[0], grid.ys.shape[0], grid.xs.shape[0]
    step = torch.tensor([-1, 0, 1], device=gt_boxes.device)
    iy = (_nearest_index(grid.ys, gt_boxes[:, 1])[:, None, None] + step[None, :, None]).expand(m, 3, 3)
    ix = (_nearest_index(grid.xs, gt_boxes[:, 0])[:, None, None] + step[None, None, :]).expand(m, 3, 3)
    inside = (iy >= 0) & (iy < ny) & (ix >= 0) & (ix < nx)
    iy, ix, inside = iy.clamp(0, ny - 1).reshape(m, 9), ix.clamp(0, nx - 1).reshape(m, 9), inside.reshape(m, 9)
    dist = torch.hypot(grid.xs.double()[ix] - gt_boxes[:, :1].double(), grid.ys.double()[iy] - gt_boxes[:, 1:2].double())
    dist = torch.where(inside, dist, torch.inf)
    rows = grid.row(iy, ix, gt_cls[:, None], rot[:, None])
    by_row = torch.sort(rows, dim=1, stable=True).indices      # then a stable sort by distance: ties to the lower row
    rows, dist = rows.gather(1, by_row), dist.gather(1, by_row)
    order = torch.sort(dist, dim=1, stable=True).indices[:, :k]
    return rows.gather(1, order), dist.gather(1, order)


def _centre_positives(labels: Tensor, grid: AnchorGrid, gt_boxes: Tensor, gt_cls: Tensor, rot: Tensor,
                      k: int) -> tuple[Tensor, Tensor]:
    """FCOS/ATSS-style centre sampling on top of the IoU matching: each GT's ``k`` nearest
    anchors (:func:`_centre_anchors`) that are not positive already become its positives; an
    anchor several GT reach goes to the nearest (ties to the lower GT index). Returns the rows
    (K,) and their GT (K,)."""
    rows, dist = _centre_anchors(grid, gt_boxes, gt_cls, rot, k)
    gt = torch.arange(gt_boxes.shape[0], device=rows.device)[:, None].expand_as(rows)
    free = (labels[rows] <= 0) & torch.isfinite(dist)
    rows, dist, gt = rows[free], dist[free], gt[free]
    anchor, slot = torch.unique(rows, return_inverse=True)
    nearest = dist.new_full((anchor.shape[0],), torch.inf).scatter_reduce(0, slot, dist, "amin")
    tie = dist == nearest[slot]
    first = torch.full_like(anchor, gt_boxes.shape[0]).scatter_reduce(0, slot[tie], gt[tie], "amin")
    return anchor, first


def _regression_targets(
    flat_anchors: Tensor, gt_boxes: Tensor, rows: Tensor, gt_of_rows: Tensor, dir_offset: float, n_dir_bins: int
) -> tuple[Tensor, Tensor, Tensor]:
    """Box residuals, box weights (N, code_size) and direction bins (N,) of the positive
    anchors ``rows`` (K,), which regress the GT ``gt_of_rows`` (K,); zeros elsewhere."""
    n, code_size = flat_anchors.shape[0], gt_boxes.shape[1]
    box_targets = flat_anchors.new_zeros((n, code_size))
    box_weights = flat_anchors.new_zeros((n, code_size))
    dir_targets = torch.zeros(n, dtype=torch.long, device=flat_anchors.device)
    gt = gt_boxes[gt_of_rows]
    known = torch.isfinite(gt)  # velocity may be NaN where the annotation has none
    box_targets[rows] = encode_boxes(torch.where(known, gt, torch.zeros_like(gt)), flat_anchors[rows])
    box_weights[rows] = known.to(box_weights.dtype)
    dir_targets[rows] = direction_target(gt[:, 6], dir_offset, n_dir_bins)
    return box_targets, box_weights, dir_targets


def assign_targets(
    anchors: Tensor,
    gt_boxes: Tensor,
    gt_labels: Tensor,
    thresholds: Sequence[tuple[float, float]],
    dir_offset: float = DIR_OFFSET,
    n_dir_bins: int = 2,
    min_positives: int = 1,
) -> AnchorTargets:
    """Class-aware anchor matching by BEV IoU, as in SECOND, for one sample.

    Anchors of class c are compared only with GT of class c. Per anchor, with ``iou`` its best
    IoU over those GT: positive if ``iou >= pos``, negative if ``iou < neg``, ignored in
    between; a positive regresses its best-IoU GT (ties to the lower GT index).

    On top of that every GT forces one anchor positive, so that each object trains something
    whatever its size and place on the grid (SECOND's forced match, mmdet3d's
    ``min_pos_iou``): among the anchors of its class whose rotation is closest to its yaw
    (modulo pi), the one with the highest IoU (ties to the lower anchor index), or, if none of
    them overlaps it (a small object between anchor centres), the one whose centre is nearest
    to its centre. Restricting the forced anchor to the closest rotation keeps a thin box
    (bicycle, barrier) from being matched to the crossing anchor on one sample and the
    parallel one on the next. A forced anchor regresses its forcing GT. Where several GT force
    the same anchor, the one with the highest IoU with it keeps it (ties to the lower GT
    index); the others keep only their above-threshold anchors.

    With ``min_positives`` k > 1, each GT also takes its k nearest anchors (its class, closest
    rotation) that are not positive already (FCOS/ATSS centre sampling; one that two GT reach goes
    to the nearer): a cone or a bicycle then trains k anchors instead of its one forced anchor.

    Only the pairs that can matter get an exact IoU (:mod:`clfbev.supervision.anchor_pairs`).

    Parameters
    ----------
    anchors : (ny, nx, n_cls, n_rot, 7) from :func:`clfbev.anchors.make_anchors`, lidar frame
        (a regular grid: checked on its axes and corner cells).
    gt_boxes : (M, 7 + E) GT boxes ``(x, y, z, l, w, h, yaw[, vx, vy])``, lidar frame. NaN
        velocities (unknown) get box weight 0. Centres are expected inside the grid (the loader
        crops boxes to the range); one outside forces the nearest edge anchor.
    gt_labels : (M,) int64 class indices into the anchors' class axis; GT with a label
        outside ``[0, n_cls)`` are ignored (classes the head does not detect).
    thresholds : ``(pos, neg)`` per class with ``0 < neg <= pos``, e.g.
        :func:`clfbev.anchors.match_thresholds`.
    dir_offset, n_dir_bins : direction binning, see :func:`direction_target`.
    min_positives : 1 (SECOND's matching) to 4, see above.

    Returns
    -------
    AnchorTargets with ``N = ny * nx * n_cls * n_rot`` rows and ``code_size = 7 + E``.
    """
    grid = _checked_grid(anchors, thresholds)
    if not 1 <= min_positives <= 4:
        raise ValueError(f"min_positives must be in [1, 4], got {min_positives}")
    device = anchors.device
    flat_anchors = anchors.reshape(-1, 7)
    gt_boxes = gt_boxes.to(device=device, dtype=anchors.dtype)
    gt_labels = gt_labels.to(device=device, dtype=torch.long)
    # In the IoUs' dtype, so that the comparisons round as a Python-float threshold would.
    pos_thr, neg_thr = torch.tensor(list(thresholds), dtype=anchors.dtype, device=device).unbind(1)

    # Matching on the GT of the detected classes only; `gt_index` maps back to the input rows.
    gt_index = torch.nonzero((gt_labels >= 0) & (gt_labels < grid.n_cls)).flatten()
    boxes, cls = gt_boxes[gt_index], gt_labels[gt_index]
    pairs = candidate_pairs(grid, boxes, cls)
    forced_rot = _closest_rotation(grid, boxes[:, 6], cls)
    iou = exact_ious(flat_anchors, boxes, pairs, neg_thr[cls], forced_rot)

    labels, matched, positive = _labels(grid, pairs, iou, boxes, cls, forced_rot, pos_thr, neg_thr, min_positives)
    matched[positive] = gt_index[matched[positive]]  # back to the caller's GT indices
    box_targets, box_weights, dir_targets = _regression_targets(
        flat_anchors, gt_boxes, positive, matched[positive], dir_offset, n_dir_bins
    )
    return AnchorTargets(
        labels=labels,
        cls_weights=(labels >= 0).to(flat_anchors.dtype),
        box_targets=box_targets,
        box_weights=box_weights,
        dir_targets=dir_targets,
        matched_gt=matched,
    )


def _labels(grid: AnchorGrid, pairs: Pairs, iou: Tensor, boxes: Tensor, cls: Tensor, forced_rot: Tensor,
            pos_thr: Tensor, neg_thr: Tensor, min_positives: int) -> tuple[Tensor, Tensor, Tensor]:
    """The matching rules of :func:`assign_targets` in turn (the IoU thresholds, each GT's forced
    anchor, centre sampling): labels (N,), matched GT (N,; indices into ``boxes``) and the
    positive rows (K,)."""
    labels, matched, above_rows = _threshold_labels(grid, pairs, iou, boxes.shape[0], pos_thr, neg_thr)
    forced_row, forced_iou = _forced_anchors(grid, pairs, iou, boxes, cls, forced_rot)
    keep = _forcing_winners(forced_row, forced_iou)
    labels[forced_row[keep]] = cls[keep] + 1                                 # forced positives regress
    matched[forced_row[keep]] = torch.arange(boxes.shape[0], device=boxes.device)[keep]   # the GT that forced them
    positive = torch.cat([above_rows, forced_row[keep]])
    if min_positives > 1:
        centre_rows, centre_gt = _centre_positives(labels, grid, boxes, cls, forced_rot, min_positives)
        labels[centre_rows], matched[centre_rows] = cls[centre_gt] + 1, centre_gt
        positive = torch.cat([positive, centre_rows])
    return labels, matched, positive.unique()


def _checked_grid(anchors: Tensor, thresholds: Sequence[tuple[float, float]]) -> AnchorGrid:
    """The grid of ``anchors`` once they and the per-class ``thresholds`` are checked."""
    if anchors.dim() != 5 or anchors.shape[-1] != 7:
        raise ValueError(f"anchors must be (ny, nx, n_cls, n_rot, 7), got {tuple(anchors.shape)}")
    n_cls = anchors.shape[2]
    if len(thresholds) != n_cls:
        raise ValueError(f"need (pos, neg) thresholds for {n_cls} classes, got {len(thresholds)}")
    if not all(0 < neg <= pos for pos, neg in thresholds):
        # neg > 0: the anchors no GT reaches are negatives without looking at them.
        raise ValueError(f"thresholds must satisfy 0 < neg <= pos, got {thresholds}")
    return anchor_grid(anchors)


def _threshold_labels(
    grid: AnchorGrid, pairs: Pairs, iou: Tensor, m: int, pos_thr: Tensor, neg_thr: Tensor
) -> tuple[Tensor, Tensor, Tensor]:
    """Labels (N,) and matched GT (N,) by the IoU thresholds alone, and the rows (K,) above the
    positive threshold. Only the anchors some GT can reach are labelled from their IoU; all
    others overlap nothing: negatives."""
    n = grid.n_anchors
    rows, best_iou, best_gt = _best_gt_per_anchor(pairs, iou, m)
    row_cls = (rows // grid.n_rot) % grid.n_cls
    above = best_iou >= pos_thr[row_cls]
    labels = torch.zeros(n, dtype=torch.long, device=iou.device)
    labels[rows] = torch.where(above, row_cls + 1, torch.where(best_iou < neg_thr[row_cls], 0, -1))
    matched = torch.full((n,), -1, dtype=torch.long, device=iou.device)
    matched[rows] = torch.where(above, best_gt, -1)
    return labels, matched, rows[above]
