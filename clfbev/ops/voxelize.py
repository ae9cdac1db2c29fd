"""Dynamic voxelization: every point in range is assigned to its voxel; no point is dropped.

Pure torch and fully vectorised (one stable sort of the voxel keys), so it runs unchanged on CPU
and CUDA.

Hard voxelization (a fixed budget of P points per voxel, as in VoxelNet / SECOND) throws points
away, and mostly the older sweeps' (the first P in input order survive), i.e. the motion cue
velocity needs.
Dynamic voxelization (Zhou et al. 2019, "End-to-end multi-view fusion"; mmdet3d's
``DynamicVFE``) keeps a point -> voxel map instead, and the VFE max-pools over all of a voxel's
points with a scatter. The only cap left is ``max_voxels`` per sample, a memory bound; which
voxels survive it is deterministic and follows the input order of their first point, so the
training augmentation shuffles the points (:func:`clfbev.augment.random_augment`) to make no
sweep the first to lose voxels.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from clfbev.settings import grid_shape_of


@dataclass(frozen=True)
class PointVoxels:
    """Points of a batch grouped by voxel.

    Attributes
    ----------
    point_index : (M,) long; the input rows of the kept points, grouped by voxel (voxel by
        voxel in ``coords`` order, each voxel's points in input order).
    voxel_id : (M,) long; the voxel of each kept point, a row of ``coords``; non-decreasing, so
        that per-voxel reductions are segment reductions over ``num_points`` (faster than a
        scatter, forward and backward).
    coords : (V, 4) long; integer voxel index (batch, z, y, x), rows sorted by (b, z, y, x).
    num_points : (V,) long; kept points per voxel (>= 1).
    grid_shape : (nz, ny, nx); the voxel grid of one sample.
    """

    point_index: Tensor
    voxel_id: Tensor
    coords: Tensor
    num_points: Tensor
    grid_shape: tuple[int, int, int]


def voxelize(
    points: Tensor,
    batch_idx: Tensor,
    pc_range: tuple[float, ...],
    voxel_size: tuple[float, ...],
    max_voxels: int,
) -> PointVoxels:
    """Assign every point in range to its voxel (dynamic voxelization).

    Parameters
    ----------
    points : (n, C) float, lidar frame; columns 0..2 are x, y, z in metres.
    batch_idx : (n,) long; the sample each point belongs to, in [0, B).
    pc_range : (xmin, ymin, zmin, xmax, ymax, zmax) in metres. A point is kept when its voxel
        index lies inside the grid, i.e. ``min <= p < min + n * voxel`` per axis.
    voxel_size : (dx, dy, dz) in metres.
    max_voxels : per sample, the ``max_voxels`` voxels whose first point comes first in the
        input are kept, with all their points; the points of the others are dropped.

    Returns
    -------
    PointVoxels; see its docstring for the order.
    """
    if points.ndim != 2 or points.shape[1] < 3:
        raise ValueError(f"points must be (n, C>=3), got {tuple(points.shape)}")
    if batch_idx.shape != points.shape[:1]:
        raise ValueError(f"batch_idx must be ({points.shape[0]},), got {tuple(batch_idx.shape)}")
    if max_voxels < 1:
        raise ValueError("max_voxels must be >= 1")
    device = points.device
    nz, ny, nx = grid_shape_of(pc_range, voxel_size)
    lo = torch.tensor(pc_range[:3], dtype=points.dtype, device=device)
    vs = torch.tensor(voxel_size, dtype=points.dtype, device=device)
    n_xyz = torch.tensor([nx, ny, nz], device=device)

    # Integer indices; the range test is done on them so that kept points and their voxel agree
    # exactly (a float test on the metres could disagree with the floor at the upper edge).
    ijk = torch.floor((points[:, :3] - lo) / vs).long()  # (n, 3) as (x, y, z)
    inside = torch.nonzero(((ijk >= 0) & (ijk < n_xyz)).all(dim=1)).flatten()  # (m,) input rows
    ijk = ijk[inside]
    b = batch_idx[inside].long()
    m = inside.numel()
    if m == 0:
        empty = torch.zeros(0, dtype=torch.long, device=device)
        return PointVoxels(empty, empty, torch.zeros((0, 4), dtype=torch.long, device=device), empty, (nz, ny, nx))

    key = ((b * nz + ijk[:, 2]) * ny + ijk[:, 1]) * nx + ijk[:, 0]  # (m,) int64
    # One stable sort groups the points by voxel, each voxel's points in input order.
    key, by_voxel = torch.sort(key, stable=True)
    uniq, counts = torch.unique_consecutive(key, return_counts=True)
    vox_b = uniq // (nz * ny * nx)
    kept = _first_voxels(vox_b, by_voxel[torch.cumsum(counts, 0) - counts], m, max_voxels)
    if kept is not None:
        point_kept = torch.repeat_interleave(kept, counts)
        by_voxel, uniq, vox_b, counts = by_voxel[point_kept], uniq[kept], vox_b[kept], counts[kept]
    coords = torch.stack([vox_b, (uniq // (nx * ny)) % nz, (uniq // nx) % ny, uniq % nx], dim=1)
    return PointVoxels(
        point_index=inside[by_voxel],
        voxel_id=torch.repeat_interleave(torch.arange(uniq.numel(), device=device), counts),
        coords=coords,
        num_points=counts,
        grid_shape=(nz, ny, nx),
    )


def _first_voxels(vox_b: Tensor, first_pt: Tensor, m: int, max_voxels: int) -> Tensor | None:
    """(U,) bool: of each sample's voxels, the ``max_voxels`` whose first point (``first_pt``, an
    input position < m) comes first; None when no sample has more (nothing to drop)."""
    if int(torch.bincount(vox_b).max()) <= max_voxels:
        return None
    order = torch.argsort(vox_b * m + first_pt)  # by (sample, first point); both terms < m, no clash
    _, b_counts = torch.unique_consecutive(vox_b[order], return_counts=True)
    b_starts = torch.repeat_interleave(torch.cumsum(b_counts, 0) - b_counts, b_counts)
    kept = torch.zeros(vox_b.numel(), dtype=torch.bool, device=vox_b.device)
    kept[order[(torch.arange(order.numel(), device=vox_b.device) - b_starts) < max_voxels]] = True
    return kept
