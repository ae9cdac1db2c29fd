"""3D box utilities: residual coder, exact rotated BEV IoU, rotated NMS.

Pure torch, vectorised, device-agnostic (every tensor is created on the input's device).

Box convention (everywhere in ``clfbev``): ``(x, y, z, l, w, h, yaw)`` in the lidar frame, metres
and radians. ``z`` is the box centre, ``l`` lies along the heading, ``yaw`` is the rotation about
+z measured from +x (counter-clockwise seen from above). Extra trailing columns (e.g. velocity
``vx, vy``) are allowed where stated.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

# Pairs of boxes processed at once by the IoU kernel. Each pair needs a few KiB of temporaries,
# so the peak stays in the tens of MiB whatever N x M is; on CPU this size also measured fastest
# (about 3 us per pair on one core), larger chunks fall out of cache.
_PAIRS_PER_CHUNK = 2**14


def limit_period(angle: Tensor, offset: float = 0.5, period: float = math.pi) -> Tensor:
    """Wrap ``angle`` into ``[-offset * period, (1 - offset) * period)``.

    With the defaults this maps to ``[-pi/2, pi/2)``: the heading modulo pi, which is what the
    box regression sees, while a direction classifier recovers the remaining pi.
    """
    return angle - torch.floor(angle / period + offset) * period


# ----------------------------------------------------------------------------------------------
# Residual coder (SECOND / PointPillars; the paper's box residuals)
# ----------------------------------------------------------------------------------------------


def encode_boxes(gt: Tensor, anchors: Tensor) -> Tensor:
    """Regression targets of ``gt`` relative to ``anchors``.

    ``dx = (xg - xa) / d``, ``dy = (yg - ya) / d`` with the anchor BEV diagonal
    ``d = sqrt(la^2 + wa^2)``; ``dz = (zg - za) / ha``; ``dl, dw, dh = log(g / a)``;
    ``dtheta = yaw_g - yaw_a`` (not wrapped: the sin-difference loss makes it periodic).

    Parameters
    ----------
    gt : (..., 7 + E) boxes, lidar frame. The E extra columns (e.g. ``vx, vy``) are encoded as
        plain differences ``gt_extra - anchor_extra``; when ``anchors`` has only 7 columns the
        anchor extras count as zero, so they pass through unchanged.
    anchors : (..., 7) or (..., 7 + E), broadcastable against ``gt``.

    Returns
    -------
    (..., 7 + E) residuals.
    """
    xa, ya, za, la, wa, ha, ra = anchors[..., :7].unbind(-1)
    xg, yg, zg, lg, wg, hg, rg = gt[..., :7].unbind(-1)
    diag = torch.sqrt(la * la + wa * wa)
    deltas = [
        (xg - xa) / diag,
        (yg - ya) / diag,
        (zg - za) / ha,
        torch.log(lg / la),
        torch.log(wg / wa),
        torch.log(hg / ha),
        rg - ra,
    ]
    out = torch.stack(deltas, dim=-1)
    if gt.shape[-1] > 7:
        extra = gt[..., 7:]
        if anchors.shape[-1] > 7:
            extra = extra - anchors[..., 7:]
        out = torch.cat([out, extra.expand(*out.shape[:-1], extra.shape[-1])], dim=-1)
    return out


def decode_boxes(deltas: Tensor, anchors: Tensor) -> Tensor:
    """Inverse of :func:`encode_boxes`.

    Parameters
    ----------
    deltas : (..., 7 + E) residuals.
    anchors : (..., 7) or (..., 7 + E), broadcastable against ``deltas``.

    Returns
    -------
    (..., 7 + E) boxes, lidar frame. Sizes are ``exp(dl) * la`` etc. without clamping, so the
    caller must keep predicted log-ratios finite.
    """
    xa, ya, za, la, wa, ha, ra = anchors[..., :7].unbind(-1)
    dx, dy, dz, dl, dw, dh, dr = deltas[..., :7].unbind(-1)
    diag = torch.sqrt(la * la + wa * wa)
    boxes = [
        dx * diag + xa,
        dy * diag + ya,
        dz * ha + za,
        torch.exp(dl) * la,
        torch.exp(dw) * wa,
        torch.exp(dh) * ha,
        dr + ra,
    ]
    out = torch.stack(boxes, dim=-1)
    if deltas.shape[-1] > 7:
        extra = deltas[..., 7:]
        if anchors.shape[-1] > 7:
            extra = extra + anchors[..., 7:]
        out = torch.cat([out, extra.expand(*out.shape[:-1], extra.shape[-1])], dim=-1)
    return out


# ----------------------------------------------------------------------------------------------
# BEV geometry
# ----------------------------------------------------------------------------------------------


def boxes_bev_corners(boxes: Tensor) -> Tensor:
    """BEV corners of boxes, counter-clockwise seen from above.

    Parameters
    ----------
    boxes : (..., 7+) boxes, lidar frame.

    Returns
    -------
    (..., 4, 2) corners ``(x, y)`` in the lidar frame, in the order front-left, rear-left,
    rear-right, front-right (local ``(+l/2, +w/2), (-l/2, +w/2), (-l/2, -w/2), (+l/2, -w/2)``).
    """
    half_l = 0.5 * boxes[..., 3:4]
    half_w = 0.5 * boxes[..., 4:5]
    sign_l = boxes.new_tensor([1.0, -1.0, -1.0, 1.0])
    sign_w = boxes.new_tensor([1.0, 1.0, -1.0, -1.0])
    local_x = half_l * sign_l  # (..., 4)
    local_y = half_w * sign_w
    cos = torch.cos(boxes[..., 6:7])
    sin = torch.sin(boxes[..., 6:7])
    x = boxes[..., 0:1] + cos * local_x - sin * local_y
    y = boxes[..., 1:2] + sin * local_x + cos * local_y
    return torch.stack([x, y], dim=-1)


def _inside_rect(px: Tensor, py: Tensor, cx: Tensor, cy: Tensor) -> Tensor:
    """Whether points lie in (or on the border of) rectangles.

    px, py : (P, K) point coordinates; cx, cy : (P, 4) rectangle corners ordered as by
    :func:`boxes_bev_corners`. Returns (P, K) bool. Projecting on the two rectangle axes is
    exact for rectangles and cheap.
    """
    ox, oy = cx[:, 1:2], cy[:, 1:2]  # rear-left corner
    lx, ly = cx[:, 0:1] - ox, cy[:, 0:1] - oy  # axis along the length
    wx, wy = cx[:, 2:3] - ox, cy[:, 2:3] - oy  # axis across the width
    rx, ry = px - ox, py - oy
    proj_l = rx * lx + ry * ly
    proj_w = rx * wx + ry * wy
    len_l = lx * lx + ly * ly
    len_w = wx * wx + wy * wy
    # A relative tolerance so vertices on a shared border count as inside: such points lie on
    # the intersection polygon, and including them costs nothing, while dropping a true corner
    # to rounding would.
    tol_l = 1e-5 * len_l
    tol_w = 1e-5 * len_w
    return (proj_l >= -tol_l) & (proj_l <= len_l + tol_l) & (proj_w >= -tol_w) & (proj_w <= len_w + tol_w)


def _intersection_area(ax: Tensor, ay: Tensor, bx: Tensor, by: Tensor) -> Tensor:
    """Exact area of the intersection of paired rectangles.

    The intersection of two convex polygons is the convex polygon whose vertices are the
    vertices of either that lie inside the other, plus the crossings of their edges. All
    4 + 4 + 16 = 24 candidates are built with fixed-size tensors, the valid ones are ordered
    by angle around their centroid and the shoelace formula gives the area. Unlike clipping,
    this has no variable vertex count to compact, so rounding on shared or collinear edges can
    only add or drop points that lie on the polygon's border, never lose a corner.

    Parameters
    ----------
    ax, ay, bx, by : (P, 4) counter-clockwise corner coordinates of the paired rectangles a
        and b, ideally near the origin (the caller centres each pair on box a) to keep
        float32 cancellation small. x and y are kept apart because contiguous tensors are
        several times faster on CPU than strided (..., 2) slices.

    Returns
    -------
    (P,) intersection areas.
    """
    num_pairs = ax.shape[0]
    a_in_b = _inside_rect(ax, ay, bx, by)  # (P, 4)
    b_in_a = _inside_rect(bx, by, ax, ay)

    # Edge i of a: p + t r, edge j of b: q + u s, for all 4 x 4 edge pairs -> (P, 4, 4).
    rx = (torch.roll(ax, -1, dims=1) - ax)[:, :, None]
    ry = (torch.roll(ay, -1, dims=1) - ay)[:, :, None]
    sx = (torch.roll(bx, -1, dims=1) - bx)[:, None, :]
    sy = (torch.roll(by, -1, dims=1) - by)[:, None, :]
    qpx = bx[:, None, :] - ax[:, :, None]
    qpy = by[:, None, :] - ay[:, :, None]
    denom = rx * sy - ry * sx
    parallel = denom == 0
    safe = torch.where(parallel, torch.ones_like(denom), denom)
    t = (qpx * sy - qpy * sx) / safe
    u = (qpx * ry - qpy * rx) / safe
    # Parallel edges contribute no crossing: where they overlap, their end points are already
    # candidates through the inside tests.
    crosses = (~parallel) & (t >= 0) & (t <= 1) & (u >= 0) & (u <= 1)
    cross_x = (ax[:, :, None] + t * rx).reshape(num_pairs, 16)
    cross_y = (ay[:, :, None] + t * ry).reshape(num_pairs, 16)

    px = torch.cat([ax, bx, cross_x], dim=1)  # (P, 24)
    py = torch.cat([ay, by, cross_y], dim=1)
    valid = torch.cat([a_in_b, b_in_a, crosses.reshape(num_pairs, 16)], dim=1)
    count = valid.sum(dim=1, keepdim=True)  # (P, 1)

    weights = valid.to(px.dtype)
    denom_c = count.clamp(min=1).to(px.dtype)
    px = px - (px * weights).sum(1, keepdim=True) / denom_c  # relative to the valid centroid
    py = py - (py * weights).sum(1, keepdim=True) / denom_c
    angle = torch.atan2(py, px)
    # Invalid points sort last (angle > pi), then get replaced by the last valid point: a
    # repeated vertex adds a zero-length edge, i.e. nothing, to the shoelace sum.
    angle = torch.where(valid, angle, torch.full_like(angle, 4.0))
    order = torch.sort(angle, dim=1, stable=True).indices
    slot = torch.arange(px.shape[1], device=px.device)
    order = torch.gather(order, 1, torch.minimum(slot[None, :], (count - 1).clamp(min=0)))
    px = torch.gather(px, 1, order)
    py = torch.gather(py, 1, order)

    area = 0.5 * (px * torch.roll(py, -1, dims=1) - torch.roll(px, -1, dims=1) * py).sum(dim=1)
    # Fewer than 3 valid points means touching or disjoint boxes: no area.
    return torch.where(count[:, 0] >= 3, area.abs(), torch.zeros_like(area))


def _pair_iou(boxes_a: Tensor, boxes_b: Tensor) -> Tensor:
    """IoU of paired boxes, (P, 7+) x (P, 7+) -> (P,), chunked over P."""
    out = boxes_a.new_zeros(boxes_a.shape[0])
    for start in range(0, boxes_a.shape[0], _PAIRS_PER_CHUNK):
        a = boxes_a[start : start + _PAIRS_PER_CHUNK]
        b = boxes_b[start : start + _PAIRS_PER_CHUNK]
        # Shift both boxes so that a's centre is the origin *before* building corners: with
        # coordinates of a few metres, float32 rounding stays far below the IoU tolerance even
        # for boxes 100 m away.
        centre = a[:, 0:2]
        a_rel = torch.cat([torch.zeros_like(centre), a[:, 2:7]], dim=1)
        b_rel = torch.cat([b[:, 0:2] - centre, b[:, 2:7]], dim=1)
        corners_a = boxes_bev_corners(a_rel)
        corners_b = boxes_bev_corners(b_rel)
        inter = _intersection_area(
            corners_a[..., 0].contiguous(),
            corners_a[..., 1].contiguous(),
            corners_b[..., 0].contiguous(),
            corners_b[..., 1].contiguous(),
        )
        union = a[:, 3] * a[:, 4] + b[:, 3] * b[:, 4] - inter
        out[start : start + _PAIRS_PER_CHUNK] = inter / union.clamp(min=1e-12)
    return out


def bev_iou(boxes_a: Tensor, boxes_b: Tensor) -> Tensor:
    """Exact rotated-rectangle IoU in bird's-eye view, all pairs.

    Parameters
    ----------
    boxes_a : (N, 7+) boxes, lidar frame (only x, y, l, w, yaw are used).
    boxes_b : (M, 7+) boxes, same frame.

    Returns
    -------
    (N, M) IoU in [0, 1].

    Notes
    -----
    Only pairs whose circumscribed circles overlap are evaluated (others are 0 exactly), in
    chunks of ``_PAIRS_PER_CHUNK`` pairs, so memory is bounded for e.g. 20000 anchors x 50 GT:
    the dense part is just the (N, M) distance test.
    """
    n, m = boxes_a.shape[0], boxes_b.shape[0]
    iou = boxes_a.new_zeros((n, m))
    if n == 0 or m == 0:
        return iou
    radius_a = 0.5 * torch.hypot(boxes_a[:, 3], boxes_a[:, 4])
    radius_b = 0.5 * torch.hypot(boxes_b[:, 3], boxes_b[:, 4])
    dist_sq = (boxes_a[:, None, 0:2] - boxes_b[None, :, 0:2]).pow(2).sum(-1)
    reach = radius_a[:, None] + radius_b[None, :]
    ia, ib = torch.nonzero(dist_sq <= reach * reach, as_tuple=True)
    if ia.numel() > 0:
        iou[ia, ib] = _pair_iou(boxes_a[ia], boxes_b[ib])
    return iou


def bev_iou_aligned(boxes_a: Tensor, boxes_b: Tensor) -> Tensor:
    """Exact BEV IoU of row-aligned pairs, (N, 7+) x (N, 7+) -> (N,), e.g. predictions vs
    their assigned GT."""
    if boxes_a.shape[0] == 0:
        return boxes_a.new_zeros(0)
    return _pair_iou(boxes_a, boxes_b)


# ----------------------------------------------------------------------------------------------
# Rotated NMS
# ----------------------------------------------------------------------------------------------


def rotated_nms(
    boxes: Tensor,
    scores: Tensor,
    iou_threshold: float,
    max_out: int | None = None,
    pre_max: int | None = None,
) -> Tensor:
    """Greedy non-maximum suppression with exact rotated BEV IoU.

    A box is suppressed when its BEV IoU with an already kept, higher-scoring box is strictly
    greater than ``iou_threshold``.

    Parameters
    ----------
    boxes : (N, 7+) boxes, lidar frame.
    scores : (N,) scores; ties are broken by the lower index first (stable sort), so the
        result is deterministic.
    iou_threshold : suppression threshold.
    max_out : keep at most this many boxes (None: no limit).
    pre_max : only the ``pre_max`` best-scoring boxes enter NMS (None: all). Bounds the
        quadratic IoU matrix.

    Returns
    -------
    (K,) int64 indices into ``boxes``, sorted by descending score.

    Notes
    -----
    With ``K = min(N, pre_max)``: the K x K IoU matrix is computed once, vectorised
    (``O(K^2)`` work, but only for pairs whose circumscribed circles overlap). The greedy pass
    then iterates once per *kept* box, each step an ``O(K)`` vector operation on the
    overlap matrix moved to the CPU once (so a CUDA input does not sync per step), giving
    ``O(kept * K)`` and never a Python loop over all pairs.
    """
    if boxes.shape[0] == 0:
        return torch.zeros(0, dtype=torch.long, device=boxes.device)
    order = torch.sort(scores, descending=True, stable=True).indices
    if pre_max is not None:
        order = order[:pre_max]
    overlap = (bev_iou(boxes[order], boxes[order]) > iou_threshold).cpu()
    limit = order.shape[0] if max_out is None else min(max_out, order.shape[0])

    alive = torch.ones(order.shape[0], dtype=torch.bool)
    kept: list[int] = []
    while len(kept) < limit:
        candidates = torch.nonzero(alive)
        if candidates.numel() == 0:
            break
        best = int(candidates[0, 0])  # highest score among the survivors
        kept.append(best)
        alive &= ~overlap[best]
        alive[best] = False
    kept_t = torch.tensor(kept, dtype=torch.long, device=boxes.device)
    return order[kept_t]
