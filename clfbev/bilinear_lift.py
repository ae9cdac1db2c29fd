"""A lift with no depth: every BEV cell samples the image features where its column projects
(Simple-BEV, Harley et al. 2023), the alternative to lift-splat's depth bins
(:func:`clfbev.camera_encoder.splat`).

Lift-splat places a feature cell's context along its ray, weighted by the predicted depth: a
far BEV cell gets features only where some ray's depth bin lands in it, and only as much as the
depth head believes it. Here every BEV cell of the grid takes a column of 3D points (its x, y
centre, at fixed heights), projects each point into every camera through the same geometry the
splat uses (:class:`clfbev.geometry.CameraGeometry`: ``img_aug @ K @ T_cam_from_lidar``),
and samples the context map bilinearly there. A far cell is filled wherever a camera sees it,
whatever the depth head says; the price is that all the cells along one ray share that ray's
features (no depth to tell them apart: the BEV backbone has to).

The column's points are at fixed heights (``cam_lift_heights``, lidar-frame z): a cell's value
is the mean of its samples over the (camera, height) pairs that see it (a point in front of the
camera at camera z >= ``d_min``, the nearest depth bin's start, inside the network image), per z
slab of the camera grid over the heights inside it, and exactly zero where none does. The
heights are where the objects are: with one mean over the column, a point under the road or
above a car samples the road before the cell or what stands behind it, and dilutes the cell's
object. ``tiny``'s, 0.44 m and 1.24 m above the road (lidar 1.84 m up), lie inside a car's body
and a walker's; two of them cost what the splat costs (docs/benchmarks.md). Simple-BEV
concatenates its heights into channels and reduces them with a convolution; the mean keeps the
camera BEV's channels (and the encoder checkpoint's tensors) those of the splat, and
``cam_z_slabs`` keeps heights apart where wanted.

Bilinear sampling follows ``F.grid_sample(..., align_corners=False, padding_mode="border")`` on
the feature map, whose cell (i, j) is centred at augmented pixel ((j + 0.5) s, (i + 0.5) s)
(the pixel-edge convention of :mod:`clfbev.camera_encoder`), so a point projecting to a cell's
centre takes exactly that cell's feature. It is computed as a weighted sum of context rows with
``F.embedding_bag`` (as the splat), over the valid samples only: a column is seen by one or two
of the six cameras, and ``grid_sample`` over all of them would sample six times the points.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from clfbev.settings import grid_shape_of


def column_points(pc_range: tuple[float, ...], bev_voxel: tuple[float, float, float],
                  heights: tuple[float, ...]) -> tuple[Tensor, Tensor]:
    """Every BEV cell's column: (len(heights), ny, nx, 3) float64 lidar-frame xyz, x and y at
    the cell's centre, z each of ``heights`` (ascending), and (len(heights),) int64 the z slab of
    each height. ValueError for a height outside the grid or a slab without one."""
    nz, ny, nx = grid_shape_of(pc_range, bev_voxel)
    xmin, ymin, zmin = (float(v) for v in pc_range[:3])
    dx, dy, dz = (float(v) for v in bev_voxel)
    f64 = dict(dtype=torch.float64)
    z = torch.tensor(sorted(float(v) for v in heights), **f64)
    slab = torch.floor((z - zmin) / dz).long()
    if len(z) == 0 or slab.min() < 0 or slab.max() >= nz or len(slab.unique()) < nz:
        raise ValueError(f"heights {tuple(heights)} must lie in z [{zmin}, {zmin + nz * dz}) with one in each of "
                         f"the {nz} slabs")
    x = xmin + (torch.arange(nx, **f64) + 0.5) * dx
    y = ymin + (torch.arange(ny, **f64) + 0.5) * dy
    zz, yy, xx = torch.meshgrid(z, y, x, indexing="ij")
    return torch.stack([xx, yy, zz], dim=-1), slab


def project(points: Tensor, cams) -> tuple[Tensor, Tensor]:
    """Points into every camera's feature map.

    points : (P, 3) lidar frame. cams : the B x N cameras
    (:class:`clfbev.geometry.CameraGeometry`). Returns ``xy`` (B, N, P, 2) float64, the
    continuous feature-map coordinates in cell units with cell (i, j)'s centre at (j, i), and
    ``valid`` (B, N, P) bool: in front at camera z >= the depth bins' d_min and inside the
    network image.
    """
    H, W = cams.image_size
    s = cams.feature_stride
    T_cam_from_lidar = torch.linalg.inv(cams.T_lidar_from_cam.double())                 # (B, N, 4, 4)
    p_cam = torch.einsum("bnij,pj->bnpi", T_cam_from_lidar[..., :3, :3], points.double()) \
        + T_cam_from_lidar[..., None, :3, 3]                                            # (B, N, P, 3)
    M = cams.intrinsics.double() if cams.img_aug is None else cams.img_aug.double() @ cams.intrinsics.double()
    uvw = torch.einsum("bnij,bnpj->bnpi", M, p_cam)
    z = p_cam[..., 2]
    # Only in front of the camera is the division meaningful; elsewhere valid is False anyway.
    uv = uvw[..., :2] / torch.where(uvw[..., 2:3] > 0, uvw[..., 2:3], torch.ones_like(uvw[..., 2:3]))
    u, v = uv.unbind(-1)
    valid = (z >= float(cams.depth_bins[0])) & (uvw[..., 2] > 0) & (u >= 0) & (u < W) & (v >= 0) & (v < H)
    return uv / s - 0.5, valid


def bilinear_taps(xy: Tensor, h: int, w: int) -> tuple[Tensor, Tensor]:
    """The four neighbour cells and weights of bilinear sampling at ``xy`` (..., 2) (cell units,
    centre of (i, j) at (j, i)) on an (h, w) map, border-clamped as grid_sample's ``border``
    padding. Returns ``cell`` (..., 4) int64 flat index ``i * w + j`` and ``weight`` (..., 4)."""
    x = xy[..., 0].clamp(0, w - 1)
    y = xy[..., 1].clamp(0, h - 1)
    x0, y0 = x.floor(), y.floor()
    fx, fy = x - x0, y - y0
    x0, y0 = x0.long(), y0.long()
    x1, y1 = (x0 + 1).clamp(max=w - 1), (y0 + 1).clamp(max=h - 1)
    cell = torch.stack([y0 * w + x0, y0 * w + x1, y1 * w + x0, y1 * w + x1], dim=-1)
    weight = torch.stack([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy], dim=-1)
    return cell, weight


def bilinear_lift(context: Tensor, cams, pc_range: tuple[float, ...],
                  bev_voxel: tuple[float, float, float], heights: tuple[float, ...]) -> Tensor:
    """The camera BEV of ``context`` by bilinear sampling (module docstring).

    context : (B, N, C, h, w) per-cell features of the N cameras (h, w = image_size / stride).
    cams : their geometry (:class:`clfbev.geometry.CameraGeometry`).
    pc_range, bev_voxel : the camera voxel grid (nz, ny, nx), lidar frame.
    heights : lidar-frame z (metres) of each column's points, at least one in each z slab.

    Returns (B, nz * C, ny, nx): slab iz fills channels [iz C, (iz + 1) C) (as the splat's
    :func:`clfbev.camera_encoder.compress_z`); zero where no camera sees any of a cell's points.
    """
    B, N, C, h, w = context.shape
    nz, ny, nx = grid_shape_of(pc_range, bev_voxel)
    pts, slab = column_points(pc_range, bev_voxel, heights)                                 # (Zh, ny, nx, 3)
    xy, valid = project(pts.reshape(-1, 3).to(context.device), cams)                        # (B, N, P, *)
    b, n, p = valid.nonzero(as_tuple=True)                                                  # the seen samples
    cell, weight = bilinear_taps(xy[b, n, p], h, w)                                         # (S, 4)
    # Output cell of each sample: (b, slab, iy, ix); p runs over (height, iy, ix).
    bag = (b * nz + slab.to(p.device)[p // (ny * nx)]) * (ny * nx) + p % (ny * nx)          # (S,)
    n_bags = B * nz * ny * nx
    seen = torch.bincount(bag, minlength=n_bags)                                            # samples per bag
    weight = weight / seen[bag, None].to(weight.dtype)                                      # a mean per bag
    row = ((b * N + n) * (h * w))[:, None] + cell                                           # (S, 4)
    order = torch.argsort(bag, stable=True)
    taps = seen * 4                                                                         # taps per bag
    rows = context.permute(0, 1, 3, 4, 2).reshape(B * N * h * w, C)
    out = F.embedding_bag(row[order].reshape(-1), rows, torch.cumsum(taps, 0) - taps, mode="sum",
                          per_sample_weights=weight[order].reshape(-1).to(rows.dtype))     # (n_bags, C)
    return out.view(B, nz, ny, nx, C).permute(0, 1, 4, 2, 3).reshape(B, nz * C, ny, nx)
