"""The lidar sweeps' time axis as BEV channels: per BEV cell, the points of each band of time lag.

Velocity is read from how far a moving object's older sweeps trail behind its newest: several
BEV cells for a car at urban speed over the span of 10 sweeps. The VFE sees every point's lag,
but its max over a voxel's points and the sparse encoder's narrow first stage bring the lag to
the BEV only weakly. Counting each lag band's points per cell hands the 2D backbone the trail
itself, so that its 3x3 convolutions can compare where the old and the new points are: the
"early fusion" of Luo et al., *Fast and Furious* (CVPR 2018), which stacks the sweeps'
occupancy along the channels of the BEV.
"""
from __future__ import annotations

import torch
from torch import Tensor


def sweep_occupancy(
    points: Tensor,
    batch_idx: Tensor,
    batch_size: int,
    pc_range: tuple[float, ...],
    bev_shape: tuple[int, int],
    n_bands: int,
    time_lag_span: float,
) -> Tensor:
    """``log(1 + n)`` of the points ``n`` of each lag band in each BEV cell.

    Parameters
    ----------
    points : (N, >= 5) float, lidar frame: x, y, z, intensity, time lag (s, 0 = key frame).
    batch_idx : (N,) long sample index.
    batch_size : B.
    pc_range : (xmin, ymin, zmin, xmax, ymax, zmax) m; points outside it are not counted (as
        the voxelizer drops them).
    bev_shape : (ny, nx) of the BEV over the range's x and y.
    n_bands : K equal bands of lag over ``[0, time_lag_span]``; band 0 holds the key frame,
        lags beyond the span fall into the last band.
    time_lag_span : s, the lag of the oldest sweep.

    Returns
    -------
    (B, K, ny, nx), the lidar frame's BEV (row = y, column = x), as the lidar BEV.
    """
    ny, nx = bev_shape
    xmin, ymin, zmin, xmax, ymax, zmax = pc_range
    x, y, z, lag = points[:, 0], points[:, 1], points[:, 2], points[:, 4]
    inside = (x >= xmin) & (x < xmax) & (y >= ymin) & (y < ymax) & (z >= zmin) & (z < zmax)
    ix = ((x - xmin) * (nx / (xmax - xmin))).long().clamp_(0, nx - 1)
    iy = ((y - ymin) * (ny / (ymax - ymin))).long().clamp_(0, ny - 1)
    band = (lag * (n_bands / time_lag_span)).long().clamp_(0, n_bands - 1)
    cell = ((batch_idx * n_bands + band) * ny + iy) * nx + ix
    counts = torch.bincount(cell[inside], minlength=batch_size * n_bands * ny * nx)
    return torch.log1p(counts.to(points.dtype)).view(batch_size, n_bands, ny, nx)
