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

The network still has to turn those means into a speed, and at the recipe's budget it does not
for walkers (docs/benchmarks.md). ``sweep_trails`` hands it the answer a least-squares fit gives:
the slope of the points' position against their lag, per cell and over each cell's 3x3
neighbourhood (the second-order moments of a pillar's points in (x, y, t), as PointPillars gives
the first). On the benchmark's sim-val walkers the 3x3 fit reads moving ones at 0.99 of their
speed with cosine 0.99, standing ones at 0.16 m/s.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from clfbev.settings import TRAIL_WINDOWS


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


TRAIL_MIN_POINTS = 6          # fewer points give a slope of noise
TRAIL_MIN_LAG_STD = 0.05      # s: points from one sweep (or two adjacent ones) carry no slope
TRAIL_MAX_SPEED = 20.0        # m/s: an urban scene's fastest actor; a fit beyond it is noise


def window_sum(maps: Tensor, k: int) -> Tensor:
    """(B, C, H, W) -> the sums over each cell's k x k neighbourhood (k odd; zeros beyond the
    edges), separably: two passes of k shifted adds, exact in any dtype."""
    if k == 1:
        return maps
    r = k // 2
    padded = F.pad(maps, (r, r, r, r))
    h, w = maps.shape[-2:]
    rows = sum(padded[..., i:i + h, :] for i in range(k))
    return sum(rows[..., j:j + w] for j in range(k))


def sweep_trails(
    points: Tensor,
    batch_idx: Tensor,
    batch_size: int,
    pc_range: tuple[float, ...],
    bev_shape: tuple[int, int],
    min_z: float,
) -> Tensor:
    """The least-squares velocity of each BEV cell's points: ``v = -cov(xy, lag) / var(lag)``.

    A moving object's older points (larger lag) lie behind it, so the slope of position
    against lag is minus its velocity. Fitted over the cell (``TRAIL_WINDOWS``) and over its
    3x3 neighbourhood, from the moments ``sum 1, t, t^2, x, y, x t, y t`` accumulated per cell
    and summed over the window. A car's trail is longer than these windows and its points
    slide over its body, so the fit reads a fraction of its speed; the backbone and the tower
    read cars from the bands.

    Parameters
    ----------
    points : (N, >= 5) float, lidar frame: x, y, z, intensity, time lag (s, 0 = key frame).
    batch_idx : (N,) long sample index.
    batch_size : B.
    pc_range : (xmin, ymin, zmin, xmax, ymax, zmax) m.
    bev_shape : (ny, nx) of the BEV over the range's x and y.
    min_z : m, lidar frame; points below it are left out: the road's ring pattern is fixed to
        the sensor and so moves with the ego, not with anything on the road.

    Returns
    -------
    (B, 2 * len(TRAIL_WINDOWS), ny, nx) float ``vx, vy`` (m/s, lidar axes) per window, 0 where a
    window holds fewer than ``TRAIL_MIN_POINTS`` or its lags spread less than
    ``TRAIL_MIN_LAG_STD``; clamped to ``TRAIL_MAX_SPEED``.
    """
    ny, nx = bev_shape
    xmin, ymin, zmin, xmax, ymax, zmax = pc_range
    x, y, z = points[:, 0], points[:, 1], points[:, 2]
    keep = (x >= xmin) & (x < xmax) & (y >= ymin) & (y < ymax) & (z >= max(zmin, min_z)) & (z < zmax)
    # float64: the covariance is a difference of products of positions up to the range's size.
    kept = points[keep].double()
    dx, dy, t = kept[:, 0] - xmin, kept[:, 1] - ymin, kept[:, 4]
    ix = (dx * (nx / (xmax - xmin))).long().clamp_(0, nx - 1)
    iy = (dy * (ny / (ymax - ymin))).long().clamp_(0, ny - 1)
    cell = (batch_idx[keep] * ny + iy) * nx + ix
    weights = (torch.ones_like(t), t, t * t, dx, dy, dx * t, dy * t)
    size = batch_size * ny * nx
    moments = torch.stack([torch.bincount(cell, weights=w, minlength=size) for w in weights], dim=1)
    moments = moments.view(batch_size, ny, nx, len(weights)).permute(0, 3, 1, 2)     # (B, 7, ny, nx)
    out = []
    for k in TRAIL_WINDOWS:
        summed = window_sum(moments, k)
        n, st, stt, sx, sy, sxt, syt = summed.unbind(dim=1)
        n_safe = n.clamp(min=1)
        var_t = stt / n_safe - (st / n_safe) ** 2
        fit = (n >= TRAIL_MIN_POINTS) & (var_t >= TRAIL_MIN_LAG_STD ** 2)
        for sum_p, sum_pt in ((sx, sxt), (sy, syt)):
            cov = sum_pt / n_safe - (sum_p / n_safe) * (st / n_safe)
            v = torch.where(fit, -cov / var_t.clamp(min=TRAIL_MIN_LAG_STD ** 2), torch.zeros_like(cov))
            out.append(v.clamp(-TRAIL_MAX_SPEED, TRAIL_MAX_SPEED))
    return torch.stack(out, dim=1).to(points.dtype)
