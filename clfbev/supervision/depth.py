"""Depth supervision of the camera branch from the lidar (BEVDepth, Li et al. 2023).

A lift-splat camera trained only through the detection loss has to discover depth from a few
thousand boxes, and on small data it does not (BEVDepth's ablation). The lidar measures the
depth of every pixel it hits, so:

1. project the key-frame lidar points into each camera through the same intrinsics,
   extrinsics and image augmentation that lift-splat uses (``img_aug @ K @ T_cam_from_lidar``),
   so that a target cell is exactly the feature cell whose frustum the point lies in;
2. per feature cell (stride s: cell (i, j) covers augmented pixels [j s, (j + 1) s) x
   [i s, (i + 1) s)) keep the NEAREST depth (the surface the cell sees, not what is behind it),
   as the bin of :mod:`clfbev.camera_encoder` (``floor((z - d_min) / step)``, camera z);
3. a binary cross-entropy between the predicted depth distribution and the one-hot bin,
   summed over bins and averaged over the cells that have a target (cells without a point,
   and depths outside the bins, are ignored).

Only key-frame points (time lag 0) are used: the earlier sweeps are motion-compensated for the
ego but not for moving objects. Points pasted by GT-paste are excluded: they have no pixels.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from clfbev.camera_encoder import CameraGeometry, depth_bin_centres


def nearest_lidar_points(
    points: list[Tensor], cams: CameraGeometry, ignore: list[Tensor | None] | None = None
) -> tuple[Tensor, Tensor]:
    """The nearest key-frame lidar point of every camera feature cell (steps 1 and 2 above).

    Parameters
    ----------
    points : B tensors (n_i, >= 5) x, y, z, intensity, time lag; key-frame lidar frame.
    cams : the B x N cameras (``img_aug`` required); feature map (H / s, W / s) of
        ``cams.image_size`` at ``cams.feature_stride``; points outside ``cams.depth_bins`` are
        left out.
    ignore : optional B masks (n_i,) of points to leave out (pasted objects), or None entries.

    Returns
    -------
    depth : (B, N, H / s, W / s) float64 camera z of the nearest point, inf where none.
    index : (B, N, H / s, W / s) int64 row of that point in ``points[b]``, -1 where none (of
        equally near points, the last row).
    """
    B, N = cams.intrinsics.shape[:2]
    H, W = cams.image_size
    feature_stride = cams.feature_stride
    h, w = H // feature_stride, W // feature_stride
    d_min, d_max, d_step = (float(v) for v in cams.depth_bins)
    z_max = d_min + int(round((d_max - d_min) / d_step)) * d_step
    device = cams.intrinsics.device
    # P = A K [R | t]_cam_from_lidar, per camera; float64 keeps pixels exact far from the centre.
    T_cam_from_lidar = torch.linalg.inv(cams.T_lidar_from_cam.double())
    P = cams.img_aug.double() @ cams.intrinsics.double() @ T_cam_from_lidar[..., :3, :]  # (B, N, 3, 4)
    depth = torch.full((B, N * h * w), float("inf"), dtype=torch.float64, device=device)
    index = torch.full((B, N * h * w), -1, dtype=torch.long, device=device)
    for b in range(B):                      # a loop over the batch; each sample is vectorised
        keep = points[b][:, 4] == 0
        if ignore is not None and ignore[b] is not None:
            keep &= ~ignore[b]
        kept = torch.nonzero(keep).squeeze(1)                           # (n,) rows of points[b]
        xyz1 = F.pad(points[b][kept, :3].double(), (0, 1), value=1.0)   # (n, 4)
        uvz = torch.einsum("nij,pj->npi", P[b], xyz1)                   # (N, n, 3)
        z = uvz[..., 2]
        u, v = uvz[..., 0] / z, uvz[..., 1] / z
        cols, rows = torch.floor(u / feature_stride).long(), torch.floor(v / feature_stride).long()
        ok = (z > d_min) & (z < z_max) & (cols >= 0) & (cols < w) & (rows >= 0) & (rows < h)
        cam = torch.arange(N, device=device)[:, None].expand_as(z)
        cell, z_ok = ((cam * h + rows) * w + cols)[ok], z[ok]
        depth[b].scatter_reduce_(0, cell, z_ok, reduce="amin")
        # The row of the nearest point: a max over the points at the cell's minimum (deterministic).
        nearest = z_ok == depth[b][cell]
        point_row = kept[None, :].expand_as(z)[ok]
        index[b].scatter_reduce_(0, cell[nearest], point_row[nearest], reduce="amax")
    return depth.view(B, N, h, w), index.view(B, N, h, w)


def depth_targets(points: list[Tensor], cams: CameraGeometry, ignore: list[Tensor | None] | None = None) -> Tensor:
    """Nearest-lidar depth bin of every camera feature cell; the parameters are those of
    :func:`nearest_lidar_points`.

    Returns
    -------
    (B, N, H / s, W / s) int64 bin index, -1 where the cell has no target.
    """
    depth, _ = nearest_lidar_points(points, cams, ignore)
    return bins_of(depth, cams.depth_bins)


def bins_of(depth: Tensor, depth_bins: tuple[float, float, float]) -> Tensor:
    """Depth bin of camera z (any shape, inf = none) -> int64, -1 where inf."""
    d_min, _, d_step = (float(v) for v in depth_bins)
    bins = torch.floor((depth - d_min) / d_step)
    return torch.where(torch.isfinite(depth), bins, -1.0).long()


def depth_loss(depth_probs: Tensor, targets: Tensor, depth_bins: tuple[float, float, float] | None = None,
               range_power: float = 0.0) -> Tensor:
    """BEVDepth's loss: BCE of the predicted distribution against the one-hot target bin,
    summed over bins, averaged over the cells with a target; with ``range_power`` p > 0 a
    weighted mean, each cell weighing (its target bin's depth)^p, the weights normalised to a
    mean of 1 (so the loss keeps its scale).

    Parameters
    ----------
    depth_probs : (B, N, D, h, w) softmax over D bins.
    targets : (B, N, h, w) int64 bin, -1 = no target.
    depth_bins : (d_min, d_max, d_step) of the bins (their centres give the weights); needed
        when ``range_power`` > 0.

    Returns
    -------
    () float32 loss (0 when no cell has a target).
    """
    D = depth_probs.shape[2]
    probs = depth_probs.permute(0, 1, 3, 4, 2).reshape(-1, D)
    t = targets.reshape(-1)
    fg = t >= 0
    # BCE on probabilities is not autocast-safe: always in float32.
    with torch.autocast(device_type=probs.device.type, enabled=False):
        p = probs[fg].float()
        onehot = F.one_hot(t[fg], D).float()
        if range_power > 0 and len(p):
            weight = depth_bin_centres(depth_bins).to(p.device)[t[fg]] ** range_power      # (n,)
            per_cell = F.binary_cross_entropy(p, onehot, reduction="none").sum(dim=1)
            total = (per_cell * (weight / weight.mean())).sum()
        else:
            total = F.binary_cross_entropy(p, onehot, reduction="sum")
    return total / max(1, int(fg.sum()))
