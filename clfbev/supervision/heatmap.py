"""A class-centre heatmap on the camera's BEV grid (CenterPoint, Yin et al. 2021): the target of
an auxiliary head on the camera BEV, and the foreground weights of the distillation
(:mod:`clfbev.supervision.distill`).

The anchor head trains a handful of anchors per box; a dense heatmap tells every BEV cell
around a box how near a centre it is. Per box, a 2D Gaussian of peak exactly 1 sits at the
cell holding the box's centre, in the channel of its class; overlapping Gaussians of one class
keep their maximum (CenterNet, Zhou et al. 2019, whose drawing CenterPoint takes over):

- the radius r (cells) is the largest corner shift that keeps the IoU of a box of the
  footprint's size in cells (l / dx, w / dy) with its shifted copy at ``min_overlap`` in the
  worst of CornerNet's three cases (Law and Deng 2018, :func:`gaussian_radius`), truncated to an
  integer and raised to ``min_radius`` (CenterPoint's nuScenes setting: overlap 0.1, radius 2);
- sigma = (2 r + 1) / 6 (a diameter of 6 sigma), drawn over the (2 r + 1)^2 cells within r of
  the centre cell on both axes, zero beyond.

Cells follow :mod:`clfbev.camera_encoder`: cell (iy, ix) covers x in [xmin + ix dx, xmin + (ix +
1) dx) and y likewise, lidar frame; a box whose centre falls outside the grid draws nothing.

The loss is CenterNet's penalty-reduced focal loss (alpha 2, beta 4) over the number of centres,
:func:`clfbev.supervision.dense.centre_focal_loss`.
"""

from __future__ import annotations


import torch
from torch import Tensor

from clfbev.supervision.dense import centre_focal_loss

# CenterPoint's nuScenes settings of the target (its ``gaussian_overlap`` and ``min_radius``).
MIN_OVERLAP = 0.1
MIN_RADIUS = 2


def gaussian_radius(length: Tensor, width: Tensor, min_overlap: float = MIN_OVERLAP) -> Tensor:
    """The largest corner shift r (cells) under which a box of ``length`` x ``width`` cells and
    its shifted copy still overlap with IoU >= ``min_overlap``, in the worst of three cases
    (CornerNet, Law and Deng 2018, section 3.2). With a = l + w, p = l w, o = min_overlap:

    1. both corners shifted by r the same way (the copy translated by (r, r)):
       IoU = (l - r)(w - r) / (2 p - (l - r)(w - r)) = o  ->  r^2 - a r + p (1 - o) / (1 + o) = 0;
    2. both corners shifted inward (the copy shrunk by 2 r per axis):
       IoU = (l - 2 r)(w - 2 r) / p = o  ->  4 r^2 - 2 a r + p (1 - o) = 0;
    3. both shifted outward (the copy grown by 2 r per axis):
       IoU = p / ((l + 2 r)(w + 2 r)) = o  ->  4 o r^2 + 2 o a r - p (1 - o) = 0.

    Each IoU falls as r grows from 0, so the bound is the smallest positive root of cases 1 and
    2 and the positive root of case 3; the radius is their minimum. (CenterNet's published
    implementation, which CenterPoint calls, takes other roots of the same quadratics; with
    CenterPoint's ``min_radius`` of 2 at 0.8 m cells both give 2 for every nuScenes class.)

    length, width : (M,) float, cells. Returns (M,) float64 cells.
    """
    l, w = length.double(), width.double()
    a, p, o = l + w, l * w, float(min_overlap)
    r1 = (a - torch.sqrt(a * a - 4 * p * (1 - o) / (1 + o))) / 2
    r2 = (2 * a - torch.sqrt(4 * a * a - 16 * p * (1 - o))) / 8
    r3 = (-2 * o * a + torch.sqrt(4 * o * o * a * a + 16 * o * p * (1 - o))) / (8 * o)
    return torch.minimum(torch.minimum(r1, r2), r3)


def centre_radius(length: Tensor, width: Tensor, min_overlap: float = MIN_OVERLAP,
                  min_radius: int = MIN_RADIUS) -> Tensor:
    """(M,) int64 radius in cells of each box's Gaussian: ``max(min_radius, int(r))`` of
    :func:`gaussian_radius` (CenterPoint's truncation)."""
    r = gaussian_radius(length, width, min_overlap).floor().long()
    return r.clamp(min=min_radius)


def bev_heatmap(boxes: list[Tensor], labels: list[Tensor], n_classes: int, pc_range: tuple[float, ...],
                cell: tuple[float, float], min_overlap: float = MIN_OVERLAP, min_radius: int = MIN_RADIUS) -> Tensor:
    """The class-centre heatmap of a batch (module docstring).

    boxes : B tensors (M_b, >= 7) x, y, z, l, w, h, yaw, lidar frame, metres.
    labels : B tensors (M_b,) int64 in [0, n_classes).
    pc_range : (xmin, ymin, zmin, xmax, ymax, zmax); cell : (dx, dy) metres of a BEV cell.

    Returns (B, n_classes, ny, nx) float32 in [0, 1], exactly 1 at each box's centre cell.
    """
    B = len(boxes)
    xmin, ymin, _, xmax, ymax, _ = (float(v) for v in pc_range)
    dx, dy = float(cell[0]), float(cell[1])
    nx, ny = int(round((xmax - xmin) / dx)), int(round((ymax - ymin) / dy))
    device = boxes[0].device if B else torch.device("cpu")
    heat = torch.zeros(B * n_classes * ny * nx, device=device)
    if B == 0 or sum(len(b) for b in boxes) == 0:
        return heat.view(B, n_classes, ny, nx)
    box = torch.cat([b[:, :7].double() for b in boxes])                                  # (M, 7)
    owner = torch.cat([torch.full((len(b),), i, device=device) for i, b in enumerate(boxes)])
    label = torch.cat([lab.long() for lab in labels])
    ix = torch.floor((box[:, 0] - xmin) / dx).long()
    iy = torch.floor((box[:, 1] - ymin) / dy).long()
    inside = (ix >= 0) & (ix < nx) & (iy >= 0) & (iy < ny)
    box, owner, label, ix, iy = box[inside], owner[inside], label[inside], ix[inside], iy[inside]
    if len(box) == 0:
        return heat.view(B, n_classes, ny, nx)
    radius = centre_radius(box[:, 3] / dx, box[:, 4] / dy, min_overlap, min_radius)      # (M,)
    sigma = (2 * radius + 1).double() / 6
    # Every box's window of the largest radius; each keeps the offsets within its own radius.
    R = int(radius.max())
    off = torch.arange(-R, R + 1, device=device)
    oy, ox = torch.meshgrid(off, off, indexing="ij")                                      # (K, K)
    gx, gy = ix[:, None, None] + ox, iy[:, None, None] + oy                               # (M, K, K)
    keep = ((ox.abs() <= radius[:, None, None]) & (oy.abs() <= radius[:, None, None])
            & (gx >= 0) & (gx < nx) & (gy >= 0) & (gy < ny))
    value = torch.exp(-(ox * ox + oy * oy).double() / (2 * sigma[:, None, None] ** 2)).float()
    channel = (owner * n_classes + label)[:, None, None].expand_as(gx)
    flat = ((channel * ny + gy) * nx + gx)[keep]
    heat.scatter_reduce_(0, flat, value.expand_as(gx)[keep], "amax")
    return heat.view(B, n_classes, ny, nx)


def heatmap_loss(logits: Tensor, heatmap: Tensor) -> Tensor:
    """CenterNet's penalty-reduced focal loss (alpha 2, beta 4) of the aux head's ``logits``
    (B, n_classes, ny, nx) against ``heatmap`` of :func:`bev_heatmap`, over its centres: 0-d."""
    return centre_focal_loss(logits, heatmap)
