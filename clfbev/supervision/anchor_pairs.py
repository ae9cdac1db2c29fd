"""Candidate (anchor, GT) pairs of the anchor matching (:mod:`clfbev.supervision.assign`) and
their BEV IoUs, computed only where they can change a label or a match.

The anchors form the regular grid of :func:`clfbev.anchors.make_anchors`, so the anchors a GT
box can overlap are a window of cells found by binary search on the grid's axes
(:func:`candidate_pairs`), and a cheap upper bound of the IoU (:func:`iou_upper_bound`) skips
the exact rotated-rectangle IoU of most of them (:func:`exact_ious`). The result equals the
all-pairs computation (tested).
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from clfbev.ops.boxes import bev_iou_aligned

# Matching runs on candidate (anchor, GT) pairs only. A pair whose cheap IoU upper bound is
# below what could matter (the class's negative threshold, or the GT's best IoU so far) by
# more than this cannot change a label or a match, so its exact IoU is skipped. The margin is
# far above the rounding of the bound (float64) and of the exact kernel (its float32
# output), and far below any threshold that matters.
IOU_BOUND_SLACK = 1e-6

# Metres added to every overlap test of the prefilter, so that boxes that touch are still
# candidates: the exact kernel gives them an IoU at rounding level (~1e-8 for float32 boxes),
# not always 0, and "some overlap" decides between best IoU and nearest centre.
TOUCH_MARGIN = 1e-6


class AnchorGrid(NamedTuple):
    """The regular layout of :func:`clfbev.anchors.make_anchors` anchors.

    xs : (nx,) ascending anchor-centre x of each column, lidar frame.
    ys : (ny,) ascending anchor-centre y of each row.
    template : (n_cls, n_rot, 7) the anchor of each class and rotation (its x, y are those of
        cell (0, 0); every other cell only moves it).
    """

    xs: Tensor
    ys: Tensor
    template: Tensor

    @property
    def n_cls(self) -> int:
        return self.template.shape[0]

    @property
    def n_rot(self) -> int:
        return self.template.shape[1]

    @property
    def n_anchors(self) -> int:
        return self.ys.shape[0] * self.xs.shape[0] * self.n_cls * self.n_rot

    def row(self, iy: Tensor, ix: Tensor, cls: Tensor, rot: Tensor) -> Tensor:
        """Flat anchor index in the order ``(iy, ix, cls, rot)``."""
        return ((iy * self.xs.shape[0] + ix) * self.n_cls + cls) * self.n_rot + rot


def anchor_grid(anchors: Tensor) -> AnchorGrid:
    """Reads the grid off (ny, nx, n_cls, n_rot, 7) anchors.

    The candidate windows rely on x depending on the column only, y on the row only, and the
    size and yaw on the class and rotation only, as :func:`clfbev.anchors.make_anchors` builds
    them. Checked on the axes and the four corner cells only: a full comparison would cost
    more than the matching itself.
    """
    xs, ys = anchors[0, :, 0, 0, 0], anchors[:, 0, 0, 0, 1]
    template = anchors[0, 0]
    corners = anchors[[0, -1]][:, [0, -1]]  # (2, 2, n_cls, n_rot, 7)
    expected = template.expand(corners.shape).clone()
    expected[..., 0] = xs[[0, -1]].view(1, 2, 1, 1)
    expected[..., 1] = ys[[0, -1]].view(2, 1, 1, 1)
    ascending = bool((xs[1:] > xs[:-1]).all()) and bool((ys[1:] > ys[:-1]).all())
    if not ascending or not torch.equal(corners, expected):
        raise ValueError("anchors must form a regular grid as made by clfbev.anchors.make_anchors")
    return AnchorGrid(xs, ys, template)


def _half_extents(length: Tensor, width: Tensor, yaw: Tensor) -> tuple[Tensor, Tensor]:
    """Half sizes along x and y of the axis-aligned box around a rotated rectangle."""
    cos, sin = torch.cos(yaw).abs(), torch.sin(yaw).abs()
    return 0.5 * (cos * length + sin * width), 0.5 * (sin * length + cos * width)


class Pairs(NamedTuple):
    """Candidate (anchor, GT) pairs, one entry per pair.

    gt : (P,) GT index (into the valid GT).
    row : (P,) flat anchor index, order ``(iy, ix, cls, rot)``.
    rot : (P,) anchor rotation index.
    """

    gt: Tensor
    row: Tensor
    rot: Tensor


def candidate_pairs(grid: AnchorGrid, gt_boxes: Tensor, gt_cls: Tensor) -> Pairs:
    """Anchors of its class that may overlap each GT, straight from the grid.

    Two boxes can only overlap if their axis-aligned bounding boxes do, so the candidates of
    a GT and a rotation are the cells whose centres lie within the sum of both boxes' half
    extents along x and along y: a window of columns and rows found by binary search in the
    grid's axes, with no test against every anchor. The windows are then cut down to pairs
    whose circumscribed circles meet, the test :func:`clfbev.ops.boxes.bev_iou` uses.

    gt_boxes (M, 7+) and gt_cls (M,) class indices, lidar frame -> pairs ordered by GT, then
    rotation, row, column (each GT's windows are contiguous).
    """
    m, n_rot = gt_boxes.shape[0], grid.n_rot
    g = gt_boxes[:, :7].double()
    anchor = grid.template[gt_cls].double()  # (M, n_rot, 7): the anchors each GT meets
    a_hx, a_hy = _half_extents(anchor[..., 3], anchor[..., 4], anchor[..., 6])
    g_hx, g_hy = _half_extents(g[:, 3:4], g[:, 4:5], g[:, 6:7])
    reach_x = a_hx + g_hx + TOUCH_MARGIN  # (M, n_rot)
    reach_y = a_hy + g_hy + TOUCH_MARGIN
    xs, ys = grid.xs.double().contiguous(), grid.ys.double().contiguous()
    gx, gy = g[:, 0:1].expand(m, n_rot), g[:, 1:2].expand(m, n_rot)
    x0 = torch.searchsorted(xs, (gx - reach_x).contiguous(), side="left")
    x1 = torch.searchsorted(xs, (gx + reach_x).contiguous(), side="right")
    y0 = torch.searchsorted(ys, (gy - reach_y).contiguous(), side="left")
    y1 = torch.searchsorted(ys, (gy + reach_y).contiguous(), side="right")

    # One window per (GT, rotation); enumerate the cells of all windows at once.
    width, height = (x1 - x0).flatten(), (y1 - y0).flatten()
    counts = width * height
    window = torch.repeat_interleave(torch.arange(m * n_rot, device=xs.device), counts)
    local = torch.arange(window.shape[0], device=xs.device) - (torch.cumsum(counts, 0) - counts)[window]
    iy = y0.flatten()[window] + local // width[window]
    ix = x0.flatten()[window] + local % width[window]
    gt, rot = window // n_rot, window % n_rot
    row = grid.row(iy, ix, gt_cls[gt], rot)

    # Circumscribed circles, computed as bev_iou does (in the anchors' dtype).
    template = grid.template[gt_cls[gt], rot]
    radius_a = 0.5 * torch.hypot(template[:, 3], template[:, 4])
    radius_g = 0.5 * torch.hypot(gt_boxes[gt, 3], gt_boxes[gt, 4])
    dist_sq = (grid.xs[ix] - gt_boxes[gt, 0]).pow(2) + (grid.ys[iy] - gt_boxes[gt, 1]).pow(2)
    keep = dist_sq <= (radius_a + radius_g).pow(2)
    return Pairs(gt[keep], row[keep], rot[keep])


def iou_upper_bound(boxes_a: Tensor, boxes_b: Tensor) -> Tensor:
    """Cheap upper bound of the BEV IoU of paired boxes, (P, 7+) x (P, 7+) -> (P,) float64.

    The intersection lies inside box a and inside the bounding rectangle of box b in a's
    frame, so its area is at most the product of the two boxes' overlaps along a's axes; the
    same holds in b's frame. IoU grows with the intersection, so the smaller product bounds
    it. Overlaps are widened by ``TOUCH_MARGIN``: touching boxes get a positive bound.
    """
    a, b = boxes_a[:, :7].double(), boxes_b[:, :7].double()
    dx, dy = b[:, 0] - a[:, 0], b[:, 1] - a[:, 1]

    def overlap_product(p: Tensor, q: Tensor, sign: float) -> Tensor:
        """Overlap of q's bounding rectangle with p along p's axes (times each other)."""
        cos, sin = torch.cos(p[:, 6]), torch.sin(p[:, 6])
        du = sign * (cos * dx + sin * dy)  # centre of q in p's frame
        dv = sign * (-sin * dx + cos * dy)
        q_hu, q_hv = _half_extents(q[:, 3], q[:, 4], q[:, 6] - p[:, 6])
        p_hu, p_hv = 0.5 * p[:, 3], 0.5 * p[:, 4]
        ou = torch.minimum(p_hu, du + q_hu) - torch.maximum(-p_hu, du - q_hu) + TOUCH_MARGIN
        ov = torch.minimum(p_hv, dv + q_hv) - torch.maximum(-p_hv, dv - q_hv) + TOUCH_MARGIN
        return ou.clamp(min=0.0) * ov.clamp(min=0.0)

    inter = torch.minimum(overlap_product(a, b, 1.0), overlap_product(b, a, -1.0))
    area_a, area_b = a[:, 3] * a[:, 4], b[:, 3] * b[:, 4]
    inter = torch.minimum(inter, torch.minimum(area_a, area_b))
    return inter / (area_a + area_b - inter).clamp(min=1e-12)


def exact_ious(flat_anchors: Tensor, gt_boxes: Tensor, pairs: Pairs, neg_thr: Tensor, forced_rot: Tensor) -> Tensor:
    """Exact BEV IoU of the candidate pairs that can matter, 0 on the others: (P,) in the
    anchors' dtype.

    An anchor's label only depends on IoUs >= the class's negative threshold (any less is a
    negative), so pairs whose upper bound is below it are skipped. A GT's forced anchor is its
    best IoU among the anchors of its closest rotation: if some computed IoU there reaches
    the negative threshold the skipped ones cannot beat it; otherwise (small objects, or
    boxes near 45 degrees) a second pass computes that GT's pairs in that rotation whose
    bound reaches the best IoU found so far. Skipped pairs are below the computed best by at
    least ``IOU_BOUND_SLACK``, so they cannot even tie with it.

    neg_thr : (M,) negative threshold of each GT's class; forced_rot : (M,) its closest
    rotation.
    """
    boxes_a, boxes_b = flat_anchors[pairs.row], gt_boxes[pairs.gt]
    bound = iou_upper_bound(boxes_a, boxes_b)
    iou = flat_anchors.new_zeros(pairs.row.shape[0])
    needed = bound >= neg_thr[pairs.gt].double() - IOU_BOUND_SLACK
    iou[needed] = bev_iou_aligned(boxes_a[needed], boxes_b[needed])

    on_forced = pairs.rot == forced_rot[pairs.gt]
    best = iou.new_zeros(gt_boxes.shape[0]).scatter_reduce(0, pairs.gt[on_forced], iou[on_forced], "amax")
    unsettled = best < neg_thr
    reach = bound >= best[pairs.gt].double() - IOU_BOUND_SLACK
    more = on_forced & unsettled[pairs.gt] & ~needed & reach & (bound > 0)
    iou[more] = bev_iou_aligned(boxes_a[more], boxes_b[more])
    return iou
