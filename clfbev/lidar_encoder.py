"""Lidar branch of CL-FusionBEV: points -> voxels -> VFE -> 3D sparse conv -> z-compress -> BEV.

Paper: "an MLP lifts the points to 512 dimensions, and max-pooling per voxel gives the voxel
feature" (VoxelNet style), then "a 3D sparse conv encoder, then compression along z gives the
lidar BEV" (SECOND style).

Points are ``(n, 5)`` float in the lidar frame (z up, metres; nuScenes mounts LIDAR_TOP with x
to the right of the car and y forward): columns
``x, y, z, intensity, time_lag``, where ``time_lag`` is the age in seconds of the sweep a point
comes from (0 for the key frame; multi-sweep lidar, as the nuScenes peers use for velocity).
Only columns 0..2 have a geometric meaning here; any further columns are passed to the MLP as
they are, so ``point_ch`` may be anything >= 3.

Grid convention: voxel index (b, z, y, x), as in ``clfbev.ops.voxelize``; BEV maps are
``(B, C, ny, nx)``, row = y index, column = x index.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor, nn

from clfbev.layers import BN_EPS, BN_MOMENTUM
from clfbev.ops.sparse_conv import SparseConv3d, SparseTensor, SubMConv3d, subm_rulebook
from clfbev.ops.voxelize import voxelize
from clfbev.settings import TRAIL_WINDOWS, conv_out_size, grid_shape_of
from clfbev.sweep_bev import sweep_occupancy, sweep_trails

Triple = tuple[int, int, int]


class LidarFeatures(NamedTuple):
    """The lidar BEV and, by name, the motion features.

    bev : (B, out_channels, ny, nx) the lidar BEV: the sparse encoder's channels, then the sweep
        bands (if any; their trails only with ``trail_in_bev``).
    motion : (B, sweep_channels, ny, nx) the sweep bands (:mod:`clfbev.sweep_bev`), which the
        velocity tower reads beside the backbone's features; None without sweep bands.
    """

    bev: Tensor
    motion: Tensor | None


class VFE(nn.Module):
    """Dynamic VoxelNet-style voxel feature encoding: per-point MLP, then max over each voxel's
    points (every point of the voxel, see :mod:`clfbev.ops.voxelize`).

    Each point is augmented with its offset to the mean of its voxel's points and its offset to
    the voxel centre (VoxelNet / PointPillars), so the MLP sees where the point lies inside its
    voxel as well as where the voxel is. Every input is brought to order 1 first: the raw x, y,
    z to [-1, 1] over ``pc_range``, the two offsets in voxel units, and the time lag (column 4)
    to [0, 1] over ``time_lag_span``. In metres, a point at 40 m would feed the MLP a value 100
    times the 0.4 m voxel's offsets, and the local geometry (what tells a pole from a
    pedestrian) would be drowned by where the voxel is. In seconds, the lag of 3 sweeps at 20 Hz
    is at most 0.1, a tenth of every other input: the only per-point cue to which sweep a point
    comes from, hence to motion (velocity, and the heading of a moving object), starts a tenth
    as strong as the rest and stays weak through a short training.

        lag_norm = p[4] / time_lag_span   (when C >= 5; the other extra columns as they are)
        aug = [xyz_norm (3), p[3:] (C - 3), (xyz - mean) / voxel (3), (xyz - centre) / voxel (3)]
        h = ReLU(Norm(Linear(aug)))                                       (out_ch,)
        voxel feature = max over the voxel's points of h

    Parameters
    ----------
    in_ch : C, channels per point (5: x, y, z, intensity, time lag).
    out_ch : feature size per voxel (512 in the paper).
    voxel_size : (dx, dy, dz) metres.
    pc_range : (xmin, ymin, zmin, xmax, ymax, zmax) metres, lidar frame.
    norm : "batch" (BatchNorm1d over the points of the batch) or "layer" (LayerNorm per
        point, batch independent).
    time_lag_span : seconds, the lag of the oldest sweep (1.0 leaves column 4 as it is).
    """

    def __init__(
        self,
        in_ch: int,
        out_ch: int,
        voxel_size: tuple[float, float, float],
        pc_range: tuple[float, ...],
        norm: str = "batch",
        time_lag_span: float = 1.0,
    ) -> None:
        super().__init__()
        if in_ch < 3:
            raise ValueError(f"VFE needs points with x, y, z (in_ch >= 3), got in_ch={in_ch}")
        if not time_lag_span > 0:
            raise ValueError(f"time_lag_span must be > 0 s, got {time_lag_span}")
        self.in_ch, self.out_ch = in_ch, out_ch
        self.aug_ch = in_ch + 6
        # Scale of the extra columns p[3:]: the time lag (column 4) over its span, the rest as is.
        extra_scale = torch.ones(max(in_ch - 3, 0), dtype=torch.float32)
        if in_ch >= 5:
            extra_scale[1] = 1.0 / time_lag_span
        self.register_buffer("extra_scale", extra_scale, persistent=False)
        lo, hi = torch.tensor(pc_range[:3], dtype=torch.float32), torch.tensor(pc_range[3:], dtype=torch.float32)
        self.register_buffer("voxel_size", torch.tensor(voxel_size, dtype=torch.float32), persistent=False)
        self.register_buffer("origin", lo, persistent=False)
        self.register_buffer("range_centre", (lo + hi) / 2, persistent=False)
        self.register_buffer("range_half", (hi - lo) / 2, persistent=False)
        if norm == "batch":
            norm_layer: nn.Module = nn.BatchNorm1d(out_ch, eps=BN_EPS, momentum=BN_MOMENTUM)
        elif norm == "layer":
            norm_layer = nn.LayerNorm(out_ch)
        else:
            raise ValueError(f"VFE norm must be 'batch' or 'layer', got {norm!r}")
        # No Linear bias: the norm's shift makes it redundant.
        self.point_mlp = nn.Sequential(nn.Linear(self.aug_ch, out_ch, bias=False), norm_layer, nn.ReLU())

    def augment(self, points: Tensor, voxel_id: Tensor, num_points: Tensor, coords: Tensor) -> Tensor:
        """The MLP input of every point.

        Parameters
        ----------
        points : (M, C) the voxelized points, lidar frame, grouped by voxel.
        voxel_id : (M,) long, non-decreasing: the voxel (row of ``coords``) of each point.
        num_points : (V,) long, points per voxel (>= 1), summing to M.
        coords : (V, 4) long voxel index (b, z, y, x).

        Returns
        -------
        (M, C + 6) augmented points, in the order of ``points``.
        """
        M, C = points.shape
        if C != self.in_ch:
            raise ValueError(f"VFE expects {self.in_ch} channels per point, got {C}")
        xyz = points[:, :3]
        mean = torch.segment_reduce(xyz, "mean", lengths=num_points)  # (V, 3)
        vs, lo = self.voxel_size.to(points.dtype), self.origin.to(points.dtype)
        centre = (coords[:, [3, 2, 1]].to(points.dtype) + 0.5) * vs + lo  # (V, 3) x, y, z
        xyz_norm = (xyz - self.range_centre.to(points.dtype)) / self.range_half.to(points.dtype)
        extra = points[:, 3:] * self.extra_scale.to(points.dtype)
        return torch.cat([xyz_norm, extra, (xyz - mean[voxel_id]) / vs, (xyz - centre[voxel_id]) / vs], dim=1)

    def forward(self, points: Tensor, voxel_id: Tensor, num_points: Tensor, coords: Tensor) -> Tensor:
        """(M, C) points (lidar frame) grouped by voxel, as :func:`clfbev.ops.voxelize.voxelize`
        gives them (``voxel_id`` (M,), ``num_points`` (V,), ``coords`` (V, 4)) -> (V, out_ch)
        voxel features."""
        h = self.point_mlp(self.augment(points, voxel_id, num_points, coords))  # (M, out_ch)
        return torch.segment_reduce(h, "max", lengths=num_points)


class SparseEncoder(nn.Module):
    """SECOND-style 3D sparse backbone ending in a z-compressed BEV map.

    Stage 0 works at the voxel resolution: ``blocks_per_stage`` SubM blocks, the first mapping
    ``in_ch -> channels[0]``. Each later stage i first downsamples to ``channels[i]``, then runs
    ``blocks_per_stage`` SubM blocks. A block is conv -> BatchNorm1d (over active sites) -> ReLU.
    Every downsampling halves z; the first log2(``xy_stride``) also halve x and y
    (``SparseConv3d(k=3, stride=2, padding=1)``), the later ones halve z only
    (``SparseConv3d(k=(3, 1, 1), stride=(2, 1, 1), padding=(1, 0, 0))``). A z-only step keeps the
    BEV fine for the head (0.8 m cells from 0.4 m voxels) while the receptive field still grows
    through the SubM blocks; its (3, 1, 1) kernel does not dilate the active sites in x and y as
    a 3x3x3 kernel at stride 1 would (the number of sites, hence the cost, stays that of the
    previous stage or less).
    Optionally (``z_out_conv``, as SECOND's ``conv_out``) a last ``SparseConv3d`` with kernel
    (3, 1, 1), stride (2, 1, 1), no padding shrinks z once more. Finally ``.dense()`` and the
    z axis is folded into the channels: (B, C, nz, ny, nx) -> (B, C * nz, ny, nx).

    Parameters
    ----------
    in_ch : channels of the voxel features (the VFE output).
    channels : channels per stage; len(channels) - 1 downsamplings by 2.
    grid_shape : (nz, ny, nx) of the voxel grid; fixes the BEV size and ``out_channels``.
    blocks_per_stage : SubM blocks per stage (>= 1).
    z_out_conv : add the final z-only downsampling conv.
    xy_stride : the BEV's x/y stride over the voxel grid, a power of 2 up to
        2 ** (len(channels) - 1) (the default: every downsampling halves x and y).
    """

    def __init__(
        self,
        in_ch: int,
        channels: tuple[int, ...],
        grid_shape: Triple,
        blocks_per_stage: int = 1,
        z_out_conv: bool = True,
        xy_stride: int | None = None,
    ) -> None:
        super().__init__()
        if len(channels) < 1 or blocks_per_stage < 1:
            raise ValueError("SparseEncoder needs >= 1 stage and >= 1 block per stage")
        n_down = len(channels) - 1
        xy_stride = 2**n_down if xy_stride is None else xy_stride
        if xy_stride < 1 or xy_stride & (xy_stride - 1) or xy_stride > 2**n_down:
            raise ValueError(f"SparseEncoder: xy_stride must be a power of 2 up to {2 ** n_down}, got {xy_stride}")
        self.xy_stride = xy_stride
        self.in_ch, self.channels, self.grid_shape = in_ch, tuple(channels), tuple(grid_shape)
        # downs[i - 1] is the strided conv (and down_norms[i - 1] its BN) entering stage i >= 1.
        self.downs = nn.ModuleList()
        self.down_norms = nn.ModuleList()
        self.subms = nn.ModuleList()  # one ModuleList of (conv, norm) pairs per stage
        c_prev = in_ch
        for i, c in enumerate(channels):
            if i > 0:
                if 2**i <= xy_stride:
                    down = SparseConv3d(c_prev, c, 3, stride=2, padding=1, bias=False)
                else:
                    down = SparseConv3d(c_prev, c, (3, 1, 1), stride=(2, 1, 1), padding=(1, 0, 0), bias=False)
                self.downs.append(down)
                self.down_norms.append(_bn(c))
                c_prev = c
            stage = nn.ModuleList()
            for _ in range(blocks_per_stage):
                stage.append(nn.ModuleList([SubMConv3d(c_prev, c, 3, bias=False), _bn(c)]))
                c_prev = c
            self.subms.append(stage)
        self.z_out: SparseConv3d | None = None
        self.z_out_norm: nn.BatchNorm1d | None = None
        if z_out_conv:
            self.z_out = SparseConv3d(c_prev, c_prev, (3, 1, 1), stride=(2, 1, 1), padding=0, bias=False)
            self.z_out_norm = _bn(c_prev)
        nz, ny, nx = self.out_grid(self.grid_shape)
        if min(nz, ny, nx) < 1:
            raise ValueError(
                f"SparseEncoder: grid {self.grid_shape} is too small for {len(channels) - 1} "
                f"downsamplings{' and the z_out conv' if z_out_conv else ''} (output grid {(nz, ny, nx)})"
            )

    def _strided_convs(self) -> list[SparseConv3d]:
        return list(self.downs) + ([self.z_out] if self.z_out is not None else [])

    def out_grid(self, grid_shape: Triple) -> Triple:
        """(nz, ny, nx) of the last sparse grid for an input grid, read off the strided convs."""
        shape = tuple(grid_shape)
        for conv in self._strided_convs():
            shape = tuple(
                conv_out_size(n, k, s, p) for n, k, s, p in zip(shape, conv.kernel_size, conv.stride, conv.padding)
            )
        return shape  # type: ignore[return-value]

    def out_size(self, grid_shape: Triple | None = None) -> tuple[int, int]:
        """BEV (ny_out, nx_out) for ``grid_shape`` (default: the grid this encoder was built for)."""
        _, ny, nx = self.out_grid(self.grid_shape if grid_shape is None else grid_shape)
        return ny, nx

    @property
    def out_channels(self) -> int:
        """BEV channels: last stage channels times the remaining z cells."""
        return self.channels[-1] * self.out_grid(self.grid_shape)[0]

    def forward(self, x: SparseTensor) -> Tensor:
        """SparseTensor (N, in_ch) on ``grid_shape`` -> BEV (B, out_channels, ny_out, nx_out)."""
        if tuple(x.spatial_shape) != self.grid_shape:
            raise ValueError(f"SparseEncoder built for grid {self.grid_shape}, got {tuple(x.spatial_shape)}")
        for i, stage in enumerate(self.subms):
            if i > 0:
                x = _block(self.downs[i - 1], self.down_norms[i - 1], x)
            # SubM convs keep the sites, so one rulebook serves the whole stage.
            rb = subm_rulebook(x.coords, x.spatial_shape, 3)
            for conv, norm in stage:
                x = _block(conv, norm, x, rb)
        if self.z_out is not None:
            x = _block(self.z_out, self.z_out_norm, x)
        dense = x.dense()  # (B, C, nz, ny, nx)
        B, C, nz, ny, nx = dense.shape
        return dense.reshape(B, C * nz, ny, nx)


def _bn(c: int) -> nn.BatchNorm1d:
    return nn.BatchNorm1d(c, eps=BN_EPS, momentum=BN_MOMENTUM)


def _block(conv: nn.Module, norm: nn.Module, x: SparseTensor, rulebook=None) -> SparseTensor:
    """conv -> BatchNorm1d over the active sites -> ReLU."""
    y = conv(x, rulebook) if rulebook is not None else conv(x)
    return y.replace_features(torch.relu(norm(y.features)))


class LidarEncoder(nn.Module):
    """Points (lidar frame) -> lidar BEV: ``voxelize`` -> ``VFE`` -> ``SparseEncoder``, and with
    ``sweep_bands`` the per-band point counts of :func:`clfbev.sweep_bev.sweep_occupancy` (and
    with ``sweep_offsets`` their mean offsets in the cell, with ``trail_min_z`` the cells' fitted
    trails of :func:`clfbev.sweep_bev.sweep_trails`) as further channels.

    Parameters
    ----------
    point_ch : channels per point (5: x, y, z, intensity, time lag).
    vfe_ch : VFE output channels (512 in the paper).
    channels : ``SparseEncoder`` stage channels.
    pc_range : (xmin, ymin, zmin, xmax, ymax, zmax) metres, lidar frame.
    voxel_size : (dx, dy, dz) metres.
    max_voxels : the dynamic voxelization's cap per sample (a memory bound).
    blocks_per_stage, z_out_conv, xy_stride : see ``SparseEncoder``.
    vfe_norm, time_lag_span : see ``VFE``.
    sweep_bands : lag bands counted per BEV cell (0: none).
    sweep_offsets : the bands' mean offsets in their cells follow the counts (2 channels a band).
    trail_min_z : m, lidar frame, or None: the fitted trails of the points above it follow
        (``2 * len(TRAIL_WINDOWS)`` channels, m/s); None: no trails.
    trail_in_bev : the trails join the lidar BEV; False: only the motion features hold them.
    """

    def __init__(
        self,
        point_ch: int,
        vfe_ch: int,
        channels: tuple[int, ...],
        pc_range: tuple[float, ...],
        voxel_size: tuple[float, float, float],
        max_voxels: int,
        blocks_per_stage: int = 1,
        z_out_conv: bool = True,
        vfe_norm: str = "batch",
        xy_stride: int | None = None,
        time_lag_span: float = 1.0,
        sweep_bands: int = 0,
        sweep_offsets: bool = False,
        trail_min_z: float | None = None,
        trail_in_bev: bool = True,
    ) -> None:
        super().__init__()
        self.point_ch = point_ch
        self.time_lag_span, self.sweep_bands, self.sweep_offsets = time_lag_span, sweep_bands, sweep_offsets
        self.trail_min_z = trail_min_z
        trail_ch = 2 * len(TRAIL_WINDOWS) if trail_min_z is not None else 0
        self.sweep_channels = sweep_bands * (3 if sweep_offsets else 1) + trail_ch
        self.bev_sweep_channels = self.sweep_channels - (0 if trail_in_bev else trail_ch)
        self.pc_range, self.voxel_size = tuple(pc_range), tuple(voxel_size)
        self.max_voxels = max_voxels
        self.grid_shape = grid_shape_of(self.pc_range, self.voxel_size)  # (nz, ny, nx)
        self.vfe = VFE(point_ch, vfe_ch, self.voxel_size, self.pc_range, norm=vfe_norm, time_lag_span=time_lag_span)
        self.sparse = SparseEncoder(vfe_ch, channels, self.grid_shape, blocks_per_stage, z_out_conv, xy_stride)

    @property
    def out_channels(self) -> int:
        return self.sparse.out_channels + self.bev_sweep_channels

    @property
    def out_size(self) -> tuple[int, int]:
        """BEV (ny_out, nx_out)."""
        return self.sparse.out_size()

    def forward(
        self,
        points: Tensor | list[Tensor],
        batch_idx: Tensor | None = None,
        batch_size: int | None = None,
    ) -> Tensor:
        """Encode a batch of point clouds into the lidar BEV.

        Parameters
        ----------
        points : a list of B tensors (n_i, point_ch), or one (N, point_ch) tensor with
            ``batch_idx``; float, lidar frame (metres).
        batch_idx : (N,) long sample index, only with a tensor ``points``.
        batch_size : B, only with a tensor ``points``; default ``batch_idx.max() + 1``
            (pass it when trailing samples may have no points).

        Returns
        -------
        lidar_bev : (B, out_channels, ny_out, nx_out); zero where no voxel reaches a cell.
        """
        return self.encode(points, batch_idx, batch_size).bev

    def encode(
        self,
        points: Tensor | list[Tensor],
        batch_idx: Tensor | None = None,
        batch_size: int | None = None,
    ) -> LidarFeatures:
        """The lidar BEV and the motion features (:class:`LidarFeatures`); the parameters are
        those of :meth:`forward`."""
        if isinstance(points, (list, tuple)):
            if batch_idx is not None:
                raise ValueError("batch_idx is implied by a list of point clouds; pass one or the other")
            if len(points) == 0:
                raise ValueError("need at least one point cloud (an empty one is fine: a (0, C) tensor)")
            batch_size = len(points)
            batch_idx = torch.cat(
                [torch.full((len(p),), i, dtype=torch.long, device=p.device) for i, p in enumerate(points)]
            )
            points = torch.cat(list(points), dim=0)
        elif batch_idx is None:
            raise ValueError("a (N, C) points tensor needs batch_idx")
        if batch_size is None:
            batch_size = int(batch_idx.max()) + 1 if batch_idx.numel() else 1
        if points.ndim != 2 or points.shape[1] != self.point_ch:
            raise ValueError(f"points must be (N, {self.point_ch}), got {tuple(points.shape)}")
        vox = voxelize(points, batch_idx, self.pc_range, self.voxel_size, self.max_voxels)
        ny, nx = self.out_size
        if vox.coords.shape[0] == 0:
            # No point in range anywhere in the batch: the BEV is empty (BatchNorm cannot run on
            # zero rows in training mode, so short-cut it).
            bev = points.new_zeros((batch_size, self.out_channels, ny, nx))
            motion = points.new_zeros((batch_size, self.sweep_channels, ny, nx)) if self.sweep_channels else None
            return LidarFeatures(bev, motion)
        feats = self.vfe(points[vox.point_index], vox.voxel_id, vox.num_points, vox.coords)  # (V, vfe_ch)
        bev = self.sparse(SparseTensor(feats, vox.coords, vox.grid_shape, batch_size))
        if not self.sweep_bands:
            return LidarFeatures(bev, None)
        bands = sweep_occupancy(points, batch_idx, batch_size, self.pc_range, (ny, nx), self.sweep_bands,
                                self.time_lag_span, self.sweep_offsets).to(bev.dtype)
        if self.trail_min_z is not None:
            trails = sweep_trails(points, batch_idx, batch_size, self.pc_range, (ny, nx), self.trail_min_z)
            bands = torch.cat([bands, trails.to(bev.dtype)], dim=1)
        return LidarFeatures(torch.cat([bev, bands[:, :self.bev_sweep_channels]], dim=1), bands)
