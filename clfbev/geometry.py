"""Camera geometry, depth bins and the direction coding: what the model and its supervision both
need (a leaf: the model never imports the training supervision).

- :class:`CameraGeometry`: where each camera feature cell looks (intrinsics, extrinsics, image
  augmentation, the feature stride and the depth bins), for the lift and for the lidar's
  projection into the cameras.
- :func:`nearest_lidar_points` / :func:`nearest_depth_bins`: the nearest key-frame lidar point of
  every camera feature cell, projected through the same geometry the lift uses (BEVDepth's depth
  target, and the oracle lift's depth); :func:`batch_nearest_lidar_points` /
  :func:`batch_depth_bins` those of a batch's own points and cameras, pasted points left out.
- :func:`direction_target`: the direction bin of a heading (the head's direction classifier).
"""
from __future__ import annotations

import math
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor

from clfbev.ops.boxes import limit_period

# Direction bins start at this heading: with 2 bins, bin 0 is [-pi/4, 3pi/4) and bin 1
# [3pi/4, 7pi/4). The bin borders sit on the diagonals, away from the headings along and
# across the road where most objects are, so few targets fall right on a border (mmdet3d's
# nuScenes PointPillars uses the same -pi/4).
DIR_OFFSET = -0.25 * math.pi


class CameraGeometry(NamedTuple):
    """Where the camera feature cells look: what lift-splat lifts with and the depth target
    projects the lidar with.

    intrinsics : (B, N, 3, 3) K of the ORIGINAL images (before ``img_aug``).
    T_lidar_from_cam : (B, N, 4, 4) camera -> lidar frame.
    img_aug : (B, N, 3, 3) original -> augmented pixels, or None for identity.
    image_size : (H, W) of the augmented image the network sees.
    feature_stride : s, the feature map's stride; H and W are multiples of it.
    depth_bins : (d_min, d_max, d_step) of camera z, see :func:`depth_bin_centres`.
    """

    intrinsics: Tensor
    T_lidar_from_cam: Tensor
    img_aug: Tensor | None
    image_size: tuple[int, int]
    feature_stride: int
    depth_bins: tuple[float, float, float]

    @classmethod
    def of_batch(cls, batch, cfg) -> "CameraGeometry":
        """The cameras of a :class:`clfbev.data.Batch` as the model of ``cfg`` (a
        :class:`clfbev.config.ModelConfig`) sees them."""
        return cls(batch.intrinsics, batch.T_lidar_from_cam, batch.img_aug, cfg.image_size, cfg.feature_stride,
                   cfg.depth_bins)


def depth_bin_centres(depth_bins: tuple[float, float, float]) -> Tensor:
    """(D,) float32 depths (m, camera z) of the bins of ``(d_min, d_max, d_step)``, at bin centres."""
    d_min, d_max, d_step = (float(v) for v in depth_bins)
    n = int(round((d_max - d_min) / d_step)) if d_step > 0 else 0
    if n < 1 or d_min <= 0:
        raise ValueError(f"depth_bins (d_min, d_max, d_step) must give >= 1 bin at d_min > 0, got {depth_bins}")
    return d_min + d_step * (torch.arange(n, dtype=torch.float32) + 0.5)


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


def nearest_depth_bins(points: list[Tensor], cams: CameraGeometry, ignore: list[Tensor | None] | None = None) -> Tensor:
    """Nearest-lidar depth bin of every camera feature cell; the parameters are those of
    :func:`nearest_lidar_points`.

    Returns
    -------
    (B, N, H / s, W / s) int64 bin index, -1 where the cell has no target.
    """
    depth, _ = nearest_lidar_points(points, cams, ignore)
    return bins_of(depth, cams.depth_bins)


def batch_nearest_lidar_points(batch, cfg) -> tuple[Tensor, Tensor]:
    """:func:`nearest_lidar_points` of a :class:`clfbev.data.Batch`: its points, its cameras as the
    model of ``cfg`` (a :class:`clfbev.config.ModelConfig`) sees them, its pasted points left out
    (they have no pixels). The one projection behind the depth targets and the oracle lift."""
    return nearest_lidar_points(batch.points, CameraGeometry.of_batch(batch, cfg), batch.pasted or None)


def batch_depth_bins(batch, cfg) -> Tensor:
    """(B, N, H / s, W / s) int64 :func:`bins_of` ``cfg.depth_bins`` of the depths of
    :func:`batch_nearest_lidar_points`, -1 where a cell has no point."""
    depth, _ = batch_nearest_lidar_points(batch, cfg)
    return bins_of(depth, cfg.depth_bins)


def bins_of(depth: Tensor, depth_bins: tuple[float, float, float]) -> Tensor:
    """Depth bin of camera z (any shape, inf = none) -> int64, -1 where inf."""
    d_min, _, d_step = (float(v) for v in depth_bins)
    bins = torch.floor((depth - d_min) / d_step)
    return torch.where(torch.isfinite(depth), bins, -1.0).long()


def direction_target(yaw: Tensor, dir_offset: float = DIR_OFFSET, n_bins: int = 2) -> Tensor:
    """Direction bin of a heading (eq. 8): ``floor(limit_period(yaw - offset, 0, 2 pi) / (2 pi /
    n_bins))``. yaw (...,) radians, lidar frame -> (...,) int64 in ``[0, n_bins)``."""
    wrapped = limit_period(yaw - dir_offset, 0.0, 2.0 * math.pi)
    return torch.floor(wrapped / (2.0 * math.pi / n_bins)).long().clamp(0, n_bins - 1)
