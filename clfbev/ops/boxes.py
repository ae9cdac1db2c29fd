"""3D box utilities: residual coder, exact rotated BEV IoU, rotated NMS, the points-in-box test.

Pure torch, vectorised, device-agnostic (every tensor is created on the input's device); the
points-in-box test also takes numpy arrays, as the loader's GT-paste works on them.

Box convention (everywhere in ``clfbev``): ``(x, y, z, l, w, h, yaw)`` in the lidar frame, metres
and radians. ``z`` is the box centre, ``l`` lies along the heading, ``yaw`` is the rotation about
+z measured from +x (counter-clockwise seen from above). Extra trailing columns (e.g. velocity
``vx, vy``) are allowed where stated.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

# Pairs of boxes processed at once by the IoU kernel. Each pair needs a few KiB of temporaries,
# so the peak stays in the tens of MiB whatever N x M is.
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


# Most vertices a clipped polygon can have: clipping a convex quadrilateral by one half-plane
# adds at most one vertex, and the intersection of two convex quadrilaterals has at most 8.
_MAX_VERTICES = 8


def _clip_half_plane(
    px: Tensor, py: Tensor, ex: Tensor, ey: Tensor, dx: Tensor, dy: Tensor, tol: Tensor
) -> tuple[Tensor, Tensor]:
    """One Sutherland-Hodgman step: clip polygons by the half-plane left of a directed line.

    Parameters
    ----------
    px, py : (P, K) polygon vertices in order. Repeated consecutive vertices are allowed (they
        are zero-length edges and change neither the clipping nor the area).
    ex, ey, dx, dy : (P, 1) a point on the clip line and its direction; the kept side is the
        left one, i.e. the inside of a counter-clockwise clip polygon.
    tol : (P, 1) tolerance in metres: the line is moved outwards by ``tol``, so vertices on a
        shared or collinear edge are inside despite rounding and cannot flicker in and out.

    Returns
    -------
    (P, _MAX_VERTICES) x and y of the clipped polygons, padded by repeating the last vertex;
    an empty result is one repeated point, whose area is 0.
    """
    # Signed distance (times |d|) to the moved line: >= 0 inside.
    dist = dx * (py - ey) - dy * (px - ex) + tol * torch.sqrt(dx * dx + dy * dy)
    inside = dist >= 0
    prev_x, prev_y = torch.roll(px, 1, dims=1), torch.roll(py, 1, dims=1)
    prev_dist, prev_inside = torch.roll(dist, 1, dims=1), torch.roll(inside, 1, dims=1)
    crossing = inside != prev_inside
    # On a crossing the two distances have opposite signs, so t is in [0, 1]: the new vertex
    # always lies on the edge, never at a far-away point of an ill-conditioned line-line solve.
    t = prev_dist / torch.where(crossing, prev_dist - dist, torch.ones_like(dist))
    t = t.clamp(0.0, 1.0)
    cross_x = prev_x + t * (px - prev_x)
    cross_y = prev_y + t * (py - prev_y)

    # Output candidates per input vertex i: [crossing on edge (i-1, i), vertex i], in order.
    num_pairs, k = px.shape
    cand_x = torch.stack([cross_x, px], dim=2).reshape(num_pairs, 2 * k)
    cand_y = torch.stack([cross_y, py], dim=2).reshape(num_pairs, 2 * k)
    keep = torch.stack([crossing, inside], dim=2).reshape(num_pairs, 2 * k)

    # Compact without scatter (deterministic on every device): output slot j takes the
    # (j+1)-th kept candidate, found by searchsorted on the running count; slots past the
    # count repeat the last kept candidate.
    running = torch.cumsum(keep.to(torch.int64), dim=1)
    count = running[:, -1:]
    rank = torch.arange(1, _MAX_VERTICES + 1, device=px.device).expand(num_pairs, -1)
    rank = torch.minimum(rank, count).contiguous()
    index = torch.searchsorted(running, rank).clamp(max=2 * k - 1)
    return torch.gather(cand_x, 1, index), torch.gather(cand_y, 1, index)


def _intersection_area(ax: Tensor, ay: Tensor, bx: Tensor, by: Tensor) -> Tensor:
    """Area of the intersection of paired convex quadrilaterals.

    Sutherland-Hodgman: rectangle a is clipped by the 4 edge half-planes of rectangle b with
    fixed-size tensors (at most 8 vertices, see ``_MAX_VERTICES``), then the shoelace formula
    gives the area.

    Parameters
    ----------
    ax, ay, bx, by : (P, 4) counter-clockwise corners of the paired quadrilaterals a and b,
        best near the origin (the caller centres each pair on box a). x and y are kept apart
        because contiguous tensors are several times faster on CPU than strided (..., 2)
        slices.

    Returns
    -------
    (P,) intersection areas.
    """
    # Rounding-level tolerance relative to the pair's extent: larger than the noise of the
    # corner coordinates, far smaller than any area that matters.
    extent = torch.cat([ax.abs(), ay.abs(), bx.abs(), by.abs()], dim=1).amax(dim=1, keepdim=True)
    tol = 64 * torch.finfo(ax.dtype).eps * extent.clamp(min=1.0)
    px, py = ax, ay
    for j in range(4):
        ex, ey = bx[:, j : j + 1], by[:, j : j + 1]
        dx = bx[:, (j + 1) % 4 : (j + 1) % 4 + 1] - ex
        dy = by[:, (j + 1) % 4 : (j + 1) % 4 + 1] - ey
        px, py = _clip_half_plane(px, py, ex, ey, dx, dy, tol)
    area = 0.5 * (px * torch.roll(py, -1, dims=1) - torch.roll(px, -1, dims=1) * py).sum(dim=1)
    # Degenerate (zero-width) boxes give a slightly negative sum at worst.
    return area.clamp(min=0.0)


def _pair_iou(boxes_a: Tensor, boxes_b: Tensor) -> Tensor:
    """IoU of paired boxes, (P, 7+) x (P, 7+) -> (P,), chunked over P.

    Computed in float64 whatever the input dtype: the kernel is cheap next to the network, and
    float64 keeps the clipping exact to ~1e-12 even for nearly parallel edges.
    """
    out = boxes_a.new_zeros(boxes_a.shape[0])
    for start in range(0, boxes_a.shape[0], _PAIRS_PER_CHUNK):
        a = boxes_a[start : start + _PAIRS_PER_CHUNK, :7].double()
        b = boxes_b[start : start + _PAIRS_PER_CHUNK, :7].double()
        # Shift both boxes so that a's centre is the origin *before* building corners, so that
        # rounding scales with the box sizes, not with the distance to the ego.
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
        iou = inter / union.clamp(min=1e-12)
        out[start : start + _PAIRS_PER_CHUNK] = iou.clamp(max=1.0).to(out.dtype)
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


def points_in_boxes(points: Tensor | np.ndarray, boxes: Tensor | np.ndarray, pad: float = 0.0) -> Tensor | np.ndarray:
    """(n, M) bool: point i lies in box j (faces included), each box grown by ``pad`` metres.

    points : (n, >= 3) x, y, z; boxes : (M, >= 7) x, y, z, l, w, h, yaw (z the box centre); one
    frame. Both numpy or both torch; the arithmetic is done in their (promoted) dtype.
    """
    xp = torch if isinstance(points, Tensor) else np
    d = points[:, None, :3] - boxes[None, :, :3]                              # (n, M, 3)
    c, s = xp.cos(boxes[:, 6]), xp.sin(boxes[:, 6])
    along = d[..., 0] * c + d[..., 1] * s                                     # box-frame x (length)
    across = -d[..., 0] * s + d[..., 1] * c                                   # box-frame y (width)
    half = boxes[:, 3:6] / 2 + pad
    return (abs(along) <= half[:, 0]) & (abs(across) <= half[:, 1]) & (abs(d[..., 2]) <= half[:, 2])


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
