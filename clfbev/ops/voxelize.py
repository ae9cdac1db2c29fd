"""Hard voxelization: points -> a fixed budget of voxels with a fixed budget of points each.

Pure torch and fully vectorised (sort + unique + scatter), so it runs unchanged on CPU and CUDA.

Which points and voxels survive the caps is deterministic and follows the input order, as in
mmcv's hard voxelization:

- a voxel keeps the *first* ``max_points_per_voxel`` of its points, in input order;
- voxels are ordered by sample, then by the input position of their first point, and each sample
  keeps its *first* ``max_voxels`` voxels in that order (the cap is per sample, as when
  mmdet3d voxelizes each sample of a batch separately).

So shuffling the points (the usual augmentation) is what randomises which ones are dropped; the
function itself never draws random numbers.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor


@dataclass(frozen=True)
class Voxels:
    """Voxelized points of a batch.

    Attributes
    ----------
    features : (V, P, C) same dtype as the points; the points of each voxel (lidar frame, all C
        channels), zero-padded after ``num_points[v]`` rows.
    num_points : (V,) long; points kept per voxel, in [1, P].
    coords : (V, 4) long; integer voxel index (batch, z, y, x). Rows are sorted by batch.
    grid_shape : (nz, ny, nx); the voxel grid size of one sample.
    """

    features: Tensor
    num_points: Tensor
    coords: Tensor
    grid_shape: tuple[int, int, int]


def grid_shape_of(pc_range: tuple[float, ...], voxel_size: tuple[float, ...]) -> tuple[int, int, int]:
    """Grid size (nz, ny, nx) for a range (xmin, ymin, zmin, xmax, ymax, zmax) and voxel (dx, dy, dz).

    Rounded, not floored, so that e.g. a 102.4 m range over 0.1 m voxels gives 1024 despite
    floating-point error.
    """
    if len(pc_range) != 6 or len(voxel_size) != 3:
        raise ValueError(f"pc_range needs 6 values and voxel_size 3, got {pc_range}, {voxel_size}")
    n_xyz = [int(round((pc_range[i + 3] - pc_range[i]) / voxel_size[i])) for i in range(3)]
    if min(n_xyz) < 1:
        raise ValueError(f"empty voxel grid for pc_range={pc_range}, voxel_size={voxel_size}")
    return n_xyz[2], n_xyz[1], n_xyz[0]


def voxelize(
    points: Tensor,
    batch_idx: Tensor,
    pc_range: tuple[float, ...],
    voxel_size: tuple[float, ...],
    max_points_per_voxel: int,
    max_voxels: int,
) -> Voxels:
    """Group points into voxels (hard voxelization, deterministic caps).

    Parameters
    ----------
    points : (n, C) float, lidar frame; columns 0..2 are x, y, z in metres, the rest
        (intensity, time lag, ...) are carried along untouched.
    batch_idx : (n,) long; the sample each point belongs to, in [0, B).
    pc_range : (xmin, ymin, zmin, xmax, ymax, zmax) in metres. A point is kept when its voxel
        index lies inside the grid, i.e. ``min <= p < min + n * voxel`` per axis.
    voxel_size : (dx, dy, dz) in metres.
    max_points_per_voxel : P, the first P points of a voxel (input order) are kept.
    max_voxels : per sample, the first ``max_voxels`` voxels (by first point's input order) are
        kept.

    Returns
    -------
    Voxels with V voxels in total; see the module docstring for the order.
    """
    if points.ndim != 2 or points.shape[1] < 3:
        raise ValueError(f"points must be (n, C>=3), got {tuple(points.shape)}")
    if batch_idx.shape != points.shape[:1]:
        raise ValueError(f"batch_idx must be ({points.shape[0]},), got {tuple(batch_idx.shape)}")
    if max_points_per_voxel < 1 or max_voxels < 1:
        raise ValueError("max_points_per_voxel and max_voxels must be >= 1")
    device = points.device
    nz, ny, nx = grid_shape_of(pc_range, voxel_size)
    lo = torch.tensor(pc_range[:3], dtype=points.dtype, device=device)
    vs = torch.tensor(voxel_size, dtype=points.dtype, device=device)
    n_xyz = torch.tensor([nx, ny, nz], device=device)

    # Integer indices; the range test is done on them so that kept points and their voxel agree
    # exactly (a float test on the metres could disagree with the floor at the upper edge).
    ijk = torch.floor((points[:, :3] - lo) / vs).long()  # (n, 3) as (x, y, z)
    inside = ((ijk >= 0) & (ijk < n_xyz)).all(dim=1)
    pts = points[inside]
    ijk = ijk[inside]
    b = batch_idx[inside].long()
    m = pts.shape[0]
    P = max_points_per_voxel
    if m == 0:
        return Voxels(
            features=points.new_zeros((0, P, points.shape[1])),
            num_points=torch.zeros(0, dtype=torch.long, device=device),
            coords=torch.zeros((0, 4), dtype=torch.long, device=device),
            grid_shape=(nz, ny, nx),
        )

    key = ((b * nz + ijk[:, 2]) * ny + ijk[:, 1]) * nx + ijk[:, 0]  # (m,) int64
    # A stable sort keeps the input order inside each voxel: that is what makes "first P points"
    # well defined and identical on every device.
    key_sorted, perm = torch.sort(key, stable=True)
    uniq, inv_sorted, counts = torch.unique_consecutive(key_sorted, return_inverse=True, return_counts=True)
    starts = torch.cumsum(counts, 0) - counts  # (U,) first sorted position of each voxel
    first_pt = perm[starts]  # (U,) input position of each voxel's first point
    rank_in_voxel = torch.arange(m, device=device) - starts[inv_sorted]  # (m,) in sorted order

    # Order voxels by (sample, first point) and cap each sample at max_voxels.
    vox_b = uniq // (nz * ny * nx)
    order = torch.argsort(vox_b * m + first_pt)  # (U,) both terms < m per sample, so no clash
    b_ordered = vox_b[order]
    _, b_counts = torch.unique_consecutive(b_ordered, return_counts=True)
    b_starts = torch.repeat_interleave(torch.cumsum(b_counts, 0) - b_counts, b_counts)
    keep = (torch.arange(order.numel(), device=device) - b_starts) < max_voxels
    kept = order[keep]  # (V,) voxel ids (into uniq) in output order
    V = kept.numel()
    new_id = torch.full((uniq.numel(),), -1, dtype=torch.long, device=device)
    new_id[kept] = torch.arange(V, device=device)

    # Scatter the kept points into their (voxel, slot) cells.
    vid = new_id[inv_sorted]  # (m,) in sorted order
    ok = (vid >= 0) & (rank_in_voxel < P)
    features = pts.new_zeros((V, P, pts.shape[1]))
    features[vid[ok], rank_in_voxel[ok]] = pts[perm[ok]]

    k = uniq[kept]
    x = k % nx
    y = (k // nx) % ny
    z = (k // (nx * ny)) % nz
    coords = torch.stack([vox_b[kept], z, y, x], dim=1)
    return Voxels(
        features=features,
        num_points=counts[kept].clamp(max=P),
        coords=coords,
        grid_shape=(nz, ny, nx),
    )
