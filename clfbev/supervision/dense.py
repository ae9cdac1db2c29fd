"""Image-view pretraining targets from dense labels, and their losses (``clfbev pretrain``).

A simulator knows the depth and the class of every pixel. Three targets teach the camera
encoder what the detector's lift needs, at the feature stride s of the encoder (cell (i, j)
covers network pixels [j s, (j + 1) s) x [i s, (i + 1) s), as in :mod:`clfbev.camera_encoder`):

1. depth: the lift's bin (``floor((z - d_min) / step)``, camera z) of the NEAREST labelled pixel
   of the cell. The minimum, not the median: the lift places the cell's context at the surface
   the cell sees first (a car's edge in front of a wall belongs to the car), and the
   detector's own depth target is the nearest lidar point of the cell for the same reason. A
   cell with no labelled pixel (sky) or a depth outside the bins has no target (-1);
2. class: the lidarseg class of that same nearest pixel (0, void, where the whole cell is
   sky), so depth and class describe one surface;
3. perspective 3D (CenterNet, Zhou et al. 2019; FCOS3D's targets): per detection class, a
   Gaussian heatmap around the projected centre of every annotated box whose centre lies in
   the image, and at the centre's cell the sub-cell offset, log depth, log size and the heading
   in the camera frame.

Losses: cross-entropy for depth and class (over the labelled cells), CenterNet's penalty-reduced
focal loss for the heatmap and L1 for the box terms (both over the number of centres).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from clfbev.geometry import CameraGeometry

# nuScenes-lidarseg's classes (index 0 = noise / void, 31 = vehicle.ego): what dense/*_seg.png holds.
LIDARSEG_CLASSES = 32
# Per-centre box terms: offset (2), log depth (1), log size l, w, h (3), heading cos, sin (2).
BOX_CODE = 8
# Loss weights of the total; each term is about ln(classes) at the start, so they are balanced.
WEIGHTS = {"loss_depth": 1.0, "loss_seg": 1.0, "loss_heatmap": 1.0, "loss_box": 1.0}


@dataclass(frozen=True)
class DenseTargets:
    """Targets of B samples with N cameras, feature map (h, w), C detection classes.

    depth : (B, N, h, w) int64 depth bin, -1 where none.  seg : (B, N, h, w) int64 lidarseg class.
    heatmap : (B, N, C, h, w) float32 in [0, 1].
    centre : (P, 4) int64 (b, n, i, j) of the P projected box centres.  box : (P, BOX_CODE) float32.
    """

    depth: Tensor
    seg: Tensor
    heatmap: Tensor
    centre: Tensor
    box: Tensor

    def to(self, device: torch.device | str) -> "DenseTargets":
        return DenseTargets(*(getattr(self, k).to(device) for k in ("depth", "seg", "heatmap", "centre", "box")))


def _nearest_pixel(depth_px: Tensor, stride: int) -> tuple[Tensor, Tensor]:
    """Per feature cell, the smallest positive depth of its pixels and that pixel's index in the
    cell's s x s block. depth_px (B, N, H, W) metres, 0 = none -> (B, N, h, w) each (inf where none)."""
    B, N, H, W = depth_px.shape
    h, w = H // stride, W // stride
    blocks = depth_px.reshape(B, N, h, stride, w, stride).permute(0, 1, 2, 4, 3, 5).reshape(B, N, h, w, -1)
    blocks = torch.where(blocks > 0, blocks, torch.full_like(blocks, float("inf")))
    return blocks.min(dim=-1)


def cell_depth_and_class(depth_px: Tensor, seg_px: Tensor, stride: int,
                         depth_bins: tuple[float, float, float]) -> tuple[Tensor, Tensor]:
    """Targets 1 and 2 of the module docstring.

    depth_px : (B, N, H, W) float32 z-depth in metres of the network image, 0 = none.
    seg_px : (B, N, H, W) uint8 lidarseg class.  stride : s.  depth_bins : (d_min, d_max, d_step).

    Returns (B, N, H / s, W / s) int64 depth bins (-1 = none) and classes.
    """
    B, N, H, W = depth_px.shape
    h, w = H // stride, W // stride
    z, where = _nearest_pixel(depth_px.float(), stride)
    d_min, d_max, d_step = depth_bins
    n_bins = int(round((d_max - d_min) / d_step))
    bins = torch.floor((z - d_min) / d_step)
    bins = torch.where(torch.isfinite(z) & (bins >= 0) & (bins < n_bins), bins, torch.full_like(bins, -1)).long()
    seg_blocks = seg_px.long().reshape(B, N, h, stride, w, stride).permute(0, 1, 2, 4, 3, 5).reshape(B, N, h, w, -1)
    return bins, seg_blocks.gather(-1, where[..., None])[..., 0]


def centre_targets(boxes: list[Tensor], labels: list[Tensor], cams: CameraGeometry,
                   n_classes: int) -> tuple[Tensor, Tensor, Tensor]:
    """Target 3: heatmap (B, N, C, h, w), centres (P, 4) (b, n, i, j) and box codes (P, BOX_CODE).

    boxes : B (M_b, >= 7) x, y, z, l, w, h, yaw, lidar frame.  labels : B (M_b,) int64 in [0, C).
    cams : the cameras (``img_aug`` required). A box is a centre of camera n when its centre is in
    front of the camera, inside the depth bins and inside the network image.
    """
    B, N = cams.intrinsics.shape[:2]
    H, W = cams.image_size
    s = cams.feature_stride
    h, w = H // s, W // s
    heatmap = torch.zeros(B * N * n_classes, h, w)
    box_lidar = torch.cat([b[:, :7].double() for b in boxes]) if boxes else torch.zeros(0, 7, dtype=torch.float64)
    if box_lidar.shape[0] == 0:
        return heatmap.view(B, N, n_classes, h, w), torch.zeros(0, 4, dtype=torch.long), torch.zeros(0, BOX_CODE)
    owner = torch.cat([torch.full((len(b),), i) for i, b in enumerate(boxes)])          # (M,) sample of each box
    label = torch.cat([lab.long() for lab in labels])
    # Every box in every camera of its sample: (M, N).
    T_cam_from_lidar = torch.linalg.inv(cams.T_lidar_from_cam.double())[owner]          # (M, N, 4, 4)
    c_cam = (T_cam_from_lidar[..., :3, :3] @ box_lidar[:, None, :3, None])[..., 0] + T_cam_from_lidar[..., :3, 3]
    P = cams.img_aug.double()[owner] @ cams.intrinsics.double()[owner]                  # (M, N, 3, 3)
    uvw = (P @ c_cam[..., None])[..., 0]
    z = c_cam[..., 2]
    uv = uvw[..., :2] / uvw[..., 2:3].clamp_min(1e-6)
    d_min, d_max, _ = cams.depth_bins
    seen = (z >= d_min) & (z < d_max) & (uv[..., 0] >= 0) & (uv[..., 0] < W) & (uv[..., 1] >= 0) & (uv[..., 1] < H)
    m, n = seen.nonzero(as_tuple=True)
    cell = uv[m, n] / s                                                                  # (P, 2) u, v in cells
    j, i = cell[:, 0].floor().long(), cell[:, 1].floor().long()
    # Gaussian radius from the box's apparent size: a third of its half-extent in cells, >= 1/2.
    focal = P[m, n, 0, 0]
    extent = focal * box_lidar[m, 3:6].max(dim=1).values / z[m, n] / s
    sigma = (extent / 6).clamp_min(0.5)
    yy, xx = torch.meshgrid(torch.arange(h, dtype=torch.float64) + 0.5, torch.arange(w, dtype=torch.float64) + 0.5,
                            indexing="ij")
    d2 = (xx - (j + 0.5).double()[:, None, None]) ** 2 + (yy - (i + 0.5).double()[:, None, None]) ** 2
    blobs = torch.exp(-d2 / (2 * sigma[:, None, None] ** 2)).float()                     # (P, h, w)
    channel = (owner[m] * N + n) * n_classes + label[m]
    heatmap.view(-1, h * w).scatter_reduce_(0, channel[:, None].expand(-1, h * w), blobs.view(-1, h * w), "amax")
    # Heading: the box's forward axis (lidar frame) in the camera frame, as (x, z) of the camera.
    yaw = box_lidar[m, 6]
    fwd = torch.stack([torch.cos(yaw), torch.sin(yaw), torch.zeros_like(yaw)], dim=-1)
    fwd_cam = (T_cam_from_lidar[m, n, :3, :3] @ fwd[..., None])[..., 0]
    heading = F.normalize(fwd_cam[:, [0, 2]], dim=-1)
    code = torch.cat([cell - torch.stack([j, i], -1).double(), z[m, n, None].log(), box_lidar[m, 3:6].log(),
                      heading], dim=-1).float()
    centres = torch.stack([owner[m], n, i, j], dim=-1)
    return heatmap.view(B, N, n_classes, h, w), centres, code


def dense_losses(depth_logits: Tensor, seg_logits: Tensor, heat_logits: Tensor, box_pred: Tensor,
                 targets: DenseTargets) -> dict[str, Tensor]:
    """The pretraining losses and their weighted total ``loss``.

    depth_logits : (B, N, D, h, w).  seg_logits : (B, N, LIDARSEG_CLASSES, h, w).
    heat_logits : (B, N, C, h, w).  box_pred : (B, N, BOX_CODE, h, w).
    """
    losses = {
        "loss_depth": F.cross_entropy(depth_logits.flatten(0, 1), targets.depth.flatten(0, 1), ignore_index=-1),
        "loss_seg": F.cross_entropy(seg_logits.flatten(0, 1), targets.seg.flatten(0, 1)),
        "loss_heatmap": centre_focal_loss(heat_logits, targets.heatmap),
    }
    b, n, i, j = targets.centre.unbind(-1)
    pred = box_pred.permute(0, 1, 3, 4, 2)[b, n, i, j]                                   # (P, BOX_CODE)
    losses["loss_box"] = F.l1_loss(pred, targets.box, reduction="sum") / max(1, len(targets.box))
    losses["loss"] = sum(WEIGHTS[k] * v for k, v in losses.items())
    return losses


def centre_focal_loss(logits: Tensor, heatmap: Tensor, alpha: float = 2.0, beta: float = 4.0) -> Tensor:
    """CenterNet's penalty-reduced pixel-wise focal loss, over the number of centres (cells
    whose target is 1). logits, heatmap : (..., h, w) of one shape."""
    p = logits.float().sigmoid().clamp(1e-4, 1 - 1e-4)
    centre = heatmap.eq(1).float()
    pos = -(1 - p) ** alpha * p.log() * centre
    neg = -(1 - heatmap) ** beta * p ** alpha * (1 - p).log() * (1 - centre)
    return (pos.sum() + neg.sum()) / centre.sum().clamp_min(1)
