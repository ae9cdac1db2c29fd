"""Lidar branch of CL-FusionBEV: points -> voxels -> VFE -> 3D sparse conv -> z-compress -> BEV.

Paper: "an MLP lifts the points to 512 dimensions, and max-pooling per voxel gives the voxel
feature" (VoxelNet style), then "a 3D sparse conv encoder, then compression along z gives the
lidar BEV" (SECOND style).

Points are ``(n, 5)`` float in the lidar frame (x forward, y left, z up, metres): columns
``x, y, z, intensity, time_lag``, where ``time_lag`` is the age in seconds of the sweep a point
comes from (0 for the key frame; multi-sweep lidar, as the nuScenes peers use for velocity).
Only columns 0..2 have a geometric meaning here; any further columns are passed to the MLP as
they are, so ``point_ch`` may be anything >= 3.

Grid convention: voxel index (b, z, y, x), as in ``clfbev.ops.voxelize``; BEV maps are
``(B, C, ny, nx)``, row = y index (increasing y = left), column = x index (increasing x = forward).
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from clfbev.ops.sparse_conv import SparseConv3d, SparseTensor, SubMConv3d, subm_rulebook
from clfbev.ops.voxelize import grid_shape_of, voxelize

Triple = tuple[int, int, int]

# BatchNorm settings of SECOND / spconv networks (small momentum: sparse batches are noisy).
BN_EPS, BN_MOMENTUM = 1e-3, 0.01


def conv_out_size(n: int, kernel: int, stride: int, padding: int) -> int:
    """Output length of a conv along one axis, the ``nn.Conv3d`` formula the rulebooks use."""
    return (n + 2 * padding - kernel) // stride + 1


class VFE(nn.Module):
    """VoxelNet-style voxel feature encoding: per-point MLP, then max over each voxel's points.

    Each real point is augmented with its offset to the mean of its voxel's points and its
    offset to the voxel centre (VoxelNet / PointPillars), so the MLP sees where the point lies
    inside its voxel as well as where the voxel is:

        aug = [p (C), xyz - mean_xyz (3), xyz - centre_xyz (3)]          (C + 6,)
        h = ReLU(Norm(Linear(aug)))                                       (out_ch,)
        voxel feature = max over the voxel's real points of h

    Padded slots (``slot >= num_points[v]``) are never read: the MLP runs on the gathered real
    points only, so their content cannot matter and they cannot win the max (nor pollute the
    BatchNorm statistics, as zero-padded slots do in the usual dense implementation). This is
    also cheaper: M real points instead of V * P slots.

    Parameters
    ----------
    in_ch : C, channels per point (5: x, y, z, intensity, time lag).
    out_ch : feature size per voxel (512 in the paper).
    voxel_size : (dx, dy, dz) metres.
    pc_range : (xmin, ymin, zmin, xmax, ymax, zmax) metres, lidar frame.
    norm : "batch" (BatchNorm1d over the real points of the batch) or "layer" (LayerNorm per
        point, batch independent).
    """

    def __init__(
        self,
        in_ch: int,
        out_ch: int,
        voxel_size: tuple[float, float, float],
        pc_range: tuple[float, ...],
        norm: str = "batch",
    ) -> None:
        super().__init__()
        if in_ch < 3:
            raise ValueError(f"VFE needs points with x, y, z (in_ch >= 3), got in_ch={in_ch}")
        self.in_ch, self.out_ch = in_ch, out_ch
        self.aug_ch = in_ch + 6
        self.register_buffer("voxel_size", torch.tensor(voxel_size, dtype=torch.float32), persistent=False)
        self.register_buffer("origin", torch.tensor(pc_range[:3], dtype=torch.float32), persistent=False)
        if norm == "batch":
            norm_layer: nn.Module = nn.BatchNorm1d(out_ch, eps=BN_EPS, momentum=BN_MOMENTUM)
        elif norm == "layer":
            norm_layer = nn.LayerNorm(out_ch)
        else:
            raise ValueError(f"VFE norm must be 'batch' or 'layer', got {norm!r}")
        # No Linear bias: the norm's shift makes it redundant.
        self.point_mlp = nn.Sequential(nn.Linear(self.aug_ch, out_ch, bias=False), norm_layer, nn.ReLU())

    def augment(self, features: Tensor, num_points: Tensor, coords: Tensor) -> tuple[Tensor, Tensor]:
        """Gather the real points and augment them.

        Parameters
        ----------
        features : (V, P, C) voxel points, lidar frame, padded after ``num_points[v]`` rows.
        num_points : (V,) long, in [1, P].
        coords : (V, 4) long voxel index (b, z, y, x).

        Returns
        -------
        aug : (M, C + 6) augmented real points, voxel by voxel, slots in order.
        voxel_id : (M,) long, the voxel of each row.
        """
        V, P, C = features.shape
        if C != self.in_ch:
            raise ValueError(f"VFE expects {self.in_ch} channels per point, got {C}")
        real = torch.arange(P, device=features.device) < num_points[:, None]  # (V, P)
        voxel_id, slot = torch.nonzero(real, as_tuple=True)  # (M,) each
        pts = features[voxel_id, slot]  # (M, C)
        xyz = pts[:, :3]
        n = num_points.to(pts.dtype)[:, None]  # (V, 1)
        mean = pts.new_zeros((V, 3)).index_add_(0, voxel_id, xyz) / n  # (V, 3)
        vs, lo = self.voxel_size.to(pts.dtype), self.origin.to(pts.dtype)
        centre = (coords[:, [3, 2, 1]].to(pts.dtype) + 0.5) * vs + lo  # (V, 3) x, y, z
        aug = torch.cat([pts, xyz - mean[voxel_id], xyz - centre[voxel_id]], dim=1)
        return aug, voxel_id

    def forward(self, features: Tensor, num_points: Tensor, coords: Tensor) -> Tensor:
        """(V, P, C) voxel points (lidar frame) -> (V, out_ch) voxel features.

        ``num_points`` (V,) and ``coords`` (V, 4) (b, z, y, x) as in ``Voxels``.
        """
        aug, voxel_id = self.augment(features, num_points, coords)
        h = self.point_mlp(aug)  # (M, out_ch), >= 0 after the ReLU
        index = voxel_id[:, None].expand(-1, self.out_ch)
        # include_self=False: the zeros are only storage, every voxel has >= 1 real point.
        return h.new_zeros((features.shape[0], self.out_ch)).scatter_reduce(
            0, index, h, reduce="amax", include_self=False
        )


class SparseEncoder(nn.Module):
    """SECOND-style 3D sparse backbone ending in a z-compressed BEV map.

    Stage 0 works at the voxel resolution: ``blocks_per_stage`` SubM blocks, the first mapping
    ``in_ch -> channels[0]``. Each later stage i first downsamples with a
    ``SparseConv3d(k=3, stride=2, padding=1)`` (x, y and z halved) to ``channels[i]``, then runs
    ``blocks_per_stage`` SubM blocks. A block is conv -> BatchNorm1d (over active sites) -> ReLU.
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
    """

    def __init__(
        self,
        in_ch: int,
        channels: tuple[int, ...],
        grid_shape: Triple,
        blocks_per_stage: int = 1,
        z_out_conv: bool = True,
    ) -> None:
        super().__init__()
        if len(channels) < 1 or blocks_per_stage < 1:
            raise ValueError("SparseEncoder needs >= 1 stage and >= 1 block per stage")
        self.in_ch, self.channels, self.grid_shape = in_ch, tuple(channels), tuple(grid_shape)
        # downs[i - 1] is the strided conv (and down_norms[i - 1] its BN) entering stage i >= 1.
        self.downs = nn.ModuleList()
        self.down_norms = nn.ModuleList()
        self.subms = nn.ModuleList()  # one ModuleList of (conv, norm) pairs per stage
        c_prev = in_ch
        for i, c in enumerate(channels):
            if i > 0:
                self.downs.append(SparseConv3d(c_prev, c, 3, stride=2, padding=1, bias=False))
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
    """Points (lidar frame) -> lidar BEV: ``voxelize`` -> ``VFE`` -> ``SparseEncoder``.

    Parameters
    ----------
    point_ch : channels per point (5: x, y, z, intensity, time lag).
    vfe_ch : VFE output channels (512 in the paper).
    channels : ``SparseEncoder`` stage channels.
    pc_range : (xmin, ymin, zmin, xmax, ymax, zmax) metres, lidar frame.
    voxel_size : (dx, dy, dz) metres.
    max_points_per_voxel, max_voxels : hard voxelization caps (``max_voxels`` per sample).
    blocks_per_stage, z_out_conv : see ``SparseEncoder``.
    vfe_norm : see ``VFE``.
    """

    def __init__(
        self,
        point_ch: int,
        vfe_ch: int,
        channels: tuple[int, ...],
        pc_range: tuple[float, ...],
        voxel_size: tuple[float, float, float],
        max_points_per_voxel: int,
        max_voxels: int,
        blocks_per_stage: int = 1,
        z_out_conv: bool = True,
        vfe_norm: str = "batch",
    ) -> None:
        super().__init__()
        self.point_ch = point_ch
        self.pc_range, self.voxel_size = tuple(pc_range), tuple(voxel_size)
        self.max_points_per_voxel, self.max_voxels = max_points_per_voxel, max_voxels
        self.grid_shape = grid_shape_of(self.pc_range, self.voxel_size)  # (nz, ny, nx)
        self.vfe = VFE(point_ch, vfe_ch, self.voxel_size, self.pc_range, norm=vfe_norm)
        self.sparse = SparseEncoder(vfe_ch, channels, self.grid_shape, blocks_per_stage, z_out_conv)

    @property
    def out_channels(self) -> int:
        return self.sparse.out_channels

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
            ``batch_idx``; float, lidar frame (x forward, y left, z up, metres).
        batch_idx : (N,) long sample index, only with a tensor ``points``.
        batch_size : B, only with a tensor ``points``; default ``batch_idx.max() + 1``
            (pass it when trailing samples may have no points).

        Returns
        -------
        lidar_bev : (B, out_channels, ny_out, nx_out); zero where no voxel reaches a cell.
        """
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
        vox = voxelize(points, batch_idx, self.pc_range, self.voxel_size, self.max_points_per_voxel, self.max_voxels)
        if vox.coords.shape[0] == 0:
            # No point in range anywhere in the batch: the BEV is empty (BatchNorm cannot run on
            # zero rows in training mode, so short-cut it).
            ny, nx = self.out_size
            return points.new_zeros((batch_size, self.out_channels, ny, nx))
        feats = self.vfe(vox.features, vox.num_points, vox.coords)  # (V, vfe_ch)
        return self.sparse(SparseTensor(feats, vox.coords, vox.grid_shape, batch_size))
