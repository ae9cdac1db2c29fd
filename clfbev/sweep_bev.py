"""The lidar sweeps' time axis as BEV channels: per BEV cell, the points of each band of time lag.

Velocity is read from how far a moving object's older sweeps trail behind its newest: several
BEV cells for a car at urban speed over the span of 10 sweeps. The VFE sees every point's lag,
but its max over a voxel's points and the sparse encoder's narrow first stage bring the lag to
the BEV only weakly. Counting each lag band's points per cell hands the 2D backbone the trail
itself, so that its 3x3 convolutions can compare where the old and the new points are: the
"early fusion" of Luo et al., *Fast and Furious* (CVPR 2018), which stacks the sweeps'
occupancy along the channels of the BEV.

A walker's trail is shorter than a cell (1.2 m/s over the 0.45 s of 10 sweeps: 0.55 m, against
0.8 m cells), so the counts hardly move; ``offsets`` adds where in its cell each band's
points lie on average (as PointPillars gives each point its offset from the pillar's centre),
and the newest band's mean then sits ahead of the oldest's by the trail.
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
    offsets: bool = False,
) -> Tensor:
    """``log(1 + n)`` of the points ``n`` of each lag band in each BEV cell, and with
    ``offsets`` each band's mean offset in its cell.

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
    offsets : also the mean x and y offsets of each band's points from their cell's centre.

    Returns
    -------
    (B, K, ny, nx), or with ``offsets`` (B, 3K, ny, nx) whose channels K + 2k and K + 2k + 1 are
    band k's mean x and y offsets in cells (-0.5 to 0.5; 0 where the band has no point in the
    cell); the lidar frame's BEV (row = y, column = x), as the lidar BEV.
    """
    ny, nx = bev_shape
    xmin, ymin, zmin, xmax, ymax, zmax = pc_range
    x, y, z, lag = points[:, 0], points[:, 1], points[:, 2], points[:, 4]
    inside = (x >= xmin) & (x < xmax) & (y >= ymin) & (y < ymax) & (z >= zmin) & (z < zmax)
    fx, fy = (x - xmin) * (nx / (xmax - xmin)), (y - ymin) * (ny / (ymax - ymin))
    ix, iy = fx.long().clamp_(0, nx - 1), fy.long().clamp_(0, ny - 1)
    band = (lag * (n_bands / time_lag_span)).long().clamp_(0, n_bands - 1)
    cell = (((batch_idx * n_bands + band) * ny + iy) * nx + ix)[inside]
    shape, size = (batch_size, n_bands, ny, nx), batch_size * n_bands * ny * nx
    counts = torch.bincount(cell, minlength=size).to(points.dtype)
    occupancy = torch.log1p(counts).view(shape)
    if not offsets:
        return occupancy
    mean = [(torch.bincount(cell, weights=d[inside], minlength=size).to(points.dtype) / counts.clamp(min=1)).view(shape)
            for d in (fx - ix - 0.5, fy - iy - 0.5)]
    return torch.cat([occupancy, torch.stack(mean, dim=2).flatten(1, 2)], dim=1)
