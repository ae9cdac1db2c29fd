"""Perspective (image-view) semantic supervision of the camera branch.

Depth supervision (:mod:`clfbev.supervision.depth`) teaches the camera WHERE a feature cell's
surface is, but not WHAT it is: trained from scratch on a few thousand boxes through
lift-splat, the BEV head and the anchor assignment, the image features can stay nearly
class-blind. Detectors that train their image backbone here add a loss in the image view (BEVFormer v2's
perspective head, the 2D auxiliary heads of BEVDet-family models); the lidar and the boxes give
one without any 2D labelling:

1. for every camera feature cell take its nearest key-frame lidar point, exactly as the depth
   target does (same projection through ``img_aug @ K @ T_cam_from_lidar``, same cells);
2. the cell's class is the class of the GT box that contains that point, background when the
   point lies in no box (the road, a building, a tree), no target when the cell has no point.
   The nearest point is what the pixel shows, so an object hidden behind a wall labels nothing,
   which a projected 2D box would get wrong;
3. a 1x1 conv on the FPN features predicts per-class logits, trained with the sigmoid focal
   loss of the detection head, summed over the labelled cells and classes and divided by the
   number of cells of an object class (as the detection loss divides by its positives).

By default the head only trains the image features and inference ignores it;
``cam_semantic_lift`` also lifts its class probabilities into the camera BEV
(:class:`clfbev.camera_encoder.CameraEncoder`).

Pasted objects (GT-paste) have no pixels: their points are left out of step 1, and the loader
removes the real points inside them, so no real point falls in a pasted box.
"""

from __future__ import annotations

import torch
from torch import Tensor

from clfbev.ops.boxes import points_in_boxes
from clfbev.supervision.losses import sigmoid_focal_loss


def point_classes(points: Tensor, boxes: Tensor, labels: Tensor) -> Tensor:
    """Class of the box that contains each point, -1 for points in no box.

    Parameters
    ----------
    points : (n, >= 3) x, y, z, lidar frame.
    boxes : (M, >= 7) x, y, z, l, w, h, yaw (z the box centre), lidar frame.
    labels : (M,) int64.

    Returns
    -------
    (n,) int64; where boxes overlap, the first box's label.
    """
    n = points.shape[0]
    if boxes.shape[0] == 0 or n == 0:
        return torch.full((n,), -1, dtype=torch.long, device=points.device)
    inside = points_in_boxes(points[:, :3].double(), boxes[:, :7].double())  # (n, M)
    first = inside.float().argmax(dim=1)                                      # first containing box
    return torch.where(inside.any(dim=1), labels.long()[first], -1)


def cell_classes(
    nearest: Tensor,
    points: list[Tensor],
    gt_boxes: list[Tensor],
    gt_labels: list[Tensor],
    n_classes: int,
) -> Tensor:
    """Class of every camera feature cell, from its nearest lidar point.

    Parameters
    ----------
    nearest : (B, N, h, w) int64 row of each cell's nearest point in ``points[b]``, -1 where
        none (:func:`clfbev.geometry.nearest_lidar_points`, which the depth target uses too).
    points : B tensors (n_i, >= 3), lidar frame.
    gt_boxes : B (M_i, >= 7) boxes, lidar frame.  gt_labels : B (M_i,) class indices.
    n_classes : C.

    Returns
    -------
    (B, N, h, w) int64: a class index in [0, C), C for background, -1 where the cell has no
    lidar point (no target).
    """
    out = torch.full_like(nearest, -1)
    for b in range(len(points)):             # a loop over the batch; each sample is vectorised
        cls = point_classes(points[b], gt_boxes[b], gt_labels[b])
        cls = torch.where(cls >= 0, cls, n_classes)
        has = nearest[b] >= 0
        out[b][has] = cls[nearest[b][has]]
    return out


def semantic_loss(logits: Tensor, targets: Tensor, alpha: float = 0.25, gamma: float = 2.0) -> Tensor:
    """Sigmoid focal loss of the per-class logits against the cell classes.

    Parameters
    ----------
    logits : (B, N, C, h, w) raw scores.
    targets : (B, N, h, w) int64 from :func:`cell_classes` (C = background, -1 = none).
    alpha, gamma : focal loss parameters (those of the detection head).

    Returns
    -------
    () float32: the sum over labelled cells and classes / max(1, cells of an object class).
    """
    C = logits.shape[2]
    flat = logits.permute(0, 1, 3, 4, 2).reshape(-1, C)
    t = targets.reshape(-1)
    labelled = t >= 0
    with torch.autocast(device_type=flat.device.type, enabled=False):
        onehot = torch.nn.functional.one_hot(t[labelled], C + 1)[:, :C].float()
        total = sigmoid_focal_loss(flat[labelled].float(), onehot, alpha, gamma).sum()
    return total / max(1, int((t[labelled] < C).sum()))
