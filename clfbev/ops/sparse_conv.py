"""Pure-torch 3D sparse convolution (submanifold and strided), for CPU and GPU.

A sparse tensor is a list of active sites ``coords (N, 4) = (batch, z, y, x)`` with features
``(N, C)``. A convolution is driven by a *rulebook*: for every kernel offset k, the pairs
(input row, output row) it connects. Building it needs a coordinate lookup; we encode
(b, z, y, x) into one int64 key, sort the keys once and look neighbours up with
``torch.searchsorted``. The convolution is then, per offset,

    out[out_rows] += features[in_rows] @ W_k            (gather -> GEMM -> index_add_)

all ordinary differentiable torch ops, so autograd gives the backward pass. Python loops run
over the k^3 kernel offsets only, never over sites.

Semantics match ``nn.Conv3d`` (cross-correlation, weight ``(out, in, kz, ky, kx)``, same init):

- ``SubMConv3d``: stride 1, padding k // 2, and the output sites are the input sites. Its output
  at an active site equals a dense conv of the zero-filled input there.
- ``SparseConv3d``: any kernel/stride/padding; output spatial shape
  ``(n + 2 p - k) // s + 1`` as in torch; output sites are exactly the positions that receive at
  least one active input. At all other positions a dense conv would give just the bias.

Building a network: normalisation and activation act on the features only, e.g.::

    x = conv(x)                                   # SparseTensor
    x = x.replace_features(torch.relu(bn(x.features)))   # bn = nn.BatchNorm1d(C)

(BatchNorm1d over active sites is what spconv networks do; inactive sites stay empty.) Several
SubMConv3d layers on the same sites can share one rulebook: build it once with
``subm_rulebook`` and pass it to each ``forward``.

Note on CUDA: ``index_add_`` uses atomics there, so float results are not bit-reproducible on
GPU (they are on CPU).

Optional backend: spconv 2.x is much faster on CUDA, but it cannot train on CPU (its backward
calls torch.cuda), which is why this pure-torch path exists. ``use_spconv(device)`` tells a caller
whether that backend could be used; the modules here always run the pure-torch path.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import torch
from torch import Tensor, nn

try:  # optional GPU backend; any failure (missing, ABI mismatch, no CUDA libs) just disables it
    import spconv.pytorch  # noqa: F401

    SPCONV_AVAILABLE = True
except Exception:  # noqa: BLE001 - an import of a compiled extension can raise more than ImportError
    SPCONV_AVAILABLE = False


def use_spconv(device: torch.device | str) -> bool:
    """True only when ``device`` is CUDA and spconv imports (spconv cannot train on CPU)."""
    return SPCONV_AVAILABLE and torch.device(device).type == "cuda"


Triple = tuple[int, int, int]


def _triple(v: int | tuple[int, ...]) -> Triple:
    if isinstance(v, int):
        return (v, v, v)
    if len(v) != 3:
        raise ValueError(f"expected an int or 3 ints, got {v}")
    return (int(v[0]), int(v[1]), int(v[2]))


@dataclass(frozen=True)
class SparseTensor:
    """Active sites of a batch of 3D grids.

    Attributes
    ----------
    features : (N, C) float; one row per active site.
    coords : (N, 4) long; (batch, z, y, x) of each site, unique rows, each inside the grid.
    spatial_shape : (nz, ny, nx).
    batch_size : B.
    """

    features: Tensor
    coords: Tensor
    spatial_shape: Triple
    batch_size: int

    def dense(self) -> Tensor:
        """The zero-filled dense grid, (B, C, nz, ny, nx); differentiable w.r.t. the features."""
        nz, ny, nx = self.spatial_shape
        c = self.coords
        out = self.features.new_zeros((self.batch_size, nz, ny, nx, self.features.shape[1]))
        out[c[:, 0], c[:, 1], c[:, 2], c[:, 3]] = self.features
        return out.permute(0, 4, 1, 2, 3).contiguous()

    def replace_features(self, features: Tensor) -> SparseTensor:
        """Same sites, new (N, C') features (after BatchNorm1d, ReLU, ...)."""
        return dataclasses.replace(self, features=features)


def encode_coords(coords: Tensor, spatial_shape: Triple) -> Tensor:
    """(N, 4) (b, z, y, x) long -> (N,) int64 keys, ordered like (b, z, y, x) lexicographically."""
    nz, ny, nx = spatial_shape
    return ((coords[:, 0] * nz + coords[:, 1]) * ny + coords[:, 2]) * nx + coords[:, 3]


def _kernel_offsets(kernel_size: Triple, device: torch.device) -> Tensor:
    """(K, 3) offsets (kz, ky, kx) in the order of ``weight[:, :, kz, ky, kx]`` flattened."""
    kz, ky, kx = kernel_size
    grid = torch.meshgrid(
        torch.arange(kz, device=device), torch.arange(ky, device=device), torch.arange(kx, device=device),
        indexing="ij",
    )
    return torch.stack([g.reshape(-1) for g in grid], dim=1)


@dataclass(frozen=True)
class Rulebook:
    """Which input rows feed which output rows, per kernel offset.

    Attributes
    ----------
    in_rows, out_rows : (M,) long; pairs sorted by kernel offset.
    offset_counts : K ints; how many pairs each offset (in weight order) has.
    out_coords : (N_out, 4) long; (b, z, y, x) of the output sites.
    out_shape : (nz, ny, nx) of the output grid.
    """

    in_rows: Tensor
    out_rows: Tensor
    offset_counts: list[int]
    out_coords: Tensor
    out_shape: Triple


def _pairs_by_offset(in_rows: Tensor, out_rows: Tensor, offset_id: Tensor, n_offsets: int):
    """Sort flat pairs by kernel offset so that each offset's pairs are one contiguous slice."""
    order = torch.argsort(offset_id, stable=True)
    counts = torch.bincount(offset_id, minlength=n_offsets).tolist()  # one host sync per rulebook
    return in_rows[order], out_rows[order], counts


def subm_rulebook(coords: Tensor, spatial_shape: Triple, kernel_size: int | Triple) -> Rulebook:
    """Rulebook of a submanifold conv: output sites = input sites, padding k // 2.

    Parameters
    ----------
    coords : (N, 4) long (b, z, y, x), unique.
    spatial_shape : (nz, ny, nx).
    kernel_size : odd ints.
    """
    ks = _triple(kernel_size)
    if any(k % 2 == 0 for k in ks):
        raise ValueError(f"SubMConv3d needs odd kernel sizes, got {ks}")
    device = coords.device
    coords = coords.long()
    if coords.shape[0] == 0:
        empty = torch.zeros(0, dtype=torch.long, device=device)
        return Rulebook(empty, empty, [0] * math.prod(ks), coords, tuple(spatial_shape))
    keys = encode_coords(coords, spatial_shape)
    keys_sorted, key_order = torch.sort(keys)
    offsets = _kernel_offsets(ks, device) - torch.tensor([k // 2 for k in ks], device=device)  # (K, 3)
    # Neighbour of output site o through offset k is the input at o + (k - k//2).
    nb = coords[None, :, 1:] + offsets[:, None, :]  # (K, N, 3)
    shape = torch.tensor(spatial_shape, device=device)
    valid = ((nb >= 0) & (nb < shape)).all(dim=2)  # (K, N)
    nb_coords = torch.cat([coords[None, :, :1].expand(len(offsets), -1, -1), nb], dim=2)
    nb_keys = encode_coords(nb_coords.reshape(-1, 4), spatial_shape).view(len(offsets), -1)
    pos = torch.searchsorted(keys_sorted, nb_keys).clamp(max=keys_sorted.numel() - 1)
    found = valid & (keys_sorted[pos] == nb_keys)
    off_id, out_rows = torch.nonzero(found, as_tuple=True)
    in_rows = key_order[pos[off_id, out_rows]]
    in_rows, out_rows, counts = _pairs_by_offset(in_rows, out_rows, off_id, len(offsets))
    return Rulebook(in_rows, out_rows, counts, coords, tuple(spatial_shape))


def strided_rulebook(
    coords: Tensor,
    spatial_shape: Triple,
    kernel_size: int | Triple,
    stride: int | Triple,
    padding: int | Triple,
) -> Rulebook:
    """Rulebook of a regular (strided) sparse conv; output sites = positions hit by any input.

    Input i reaches output o through kernel offset k when ``o * s - p + k = i`` (torch's
    cross-correlation), i.e. ``i + p - k`` is a non-negative multiple of s below s * n_out.
    Output sites come out sorted by (b, z, y, x).
    """
    ks, st, pd = _triple(kernel_size), _triple(stride), _triple(padding)
    device = coords.device
    coords = coords.long()
    out_shape = tuple((n + 2 * p - k) // s + 1 for n, k, s, p in zip(spatial_shape, ks, st, pd))
    if min(out_shape) < 1:
        raise ValueError(f"conv output would be empty: input {spatial_shape}, kernel {ks}, stride {st}")
    offsets = _kernel_offsets(ks, device)  # (K, 3)
    s = torch.tensor(st, device=device)
    num = coords[None, :, 1:] + torch.tensor(pd, device=device) - offsets[:, None, :]  # (K, N, 3)
    o = torch.div(num, s, rounding_mode="floor")
    valid = ((num >= 0) & (num % s == 0) & (o < torch.tensor(out_shape, device=device))).all(dim=2)
    off_id, in_rows = torch.nonzero(valid, as_tuple=True)
    out_all = torch.cat([coords[in_rows, :1], o[off_id, in_rows]], dim=1)  # (M, 4)
    out_keys, out_rows = torch.unique(encode_coords(out_all, out_shape), return_inverse=True)
    ox = out_keys % out_shape[2]
    oy = (out_keys // out_shape[2]) % out_shape[1]
    oz = (out_keys // (out_shape[2] * out_shape[1])) % out_shape[0]
    ob = out_keys // (out_shape[2] * out_shape[1] * out_shape[0])
    out_coords = torch.stack([ob, oz, oy, ox], dim=1)
    in_rows, out_rows, counts = _pairs_by_offset(in_rows, out_rows, off_id, len(offsets))
    return Rulebook(in_rows, out_rows, counts, out_coords, out_shape)


def apply_rulebook(features: Tensor, weight: Tensor, bias: Tensor | None, rb: Rulebook) -> Tensor:
    """Sparse conv given its rulebook.

    Parameters
    ----------
    features : (N_in, C_in).
    weight : (C_out, C_in, kz, ky, kx), the nn.Conv3d layout.
    bias : (C_out,) or None.

    Returns
    -------
    (N_out, C_out) features at ``rb.out_coords``.
    """
    c_out = weight.shape[0]
    w = weight.reshape(c_out, weight.shape[1], -1)  # (C_out, C_in, K)
    out = features.new_zeros((rb.out_coords.shape[0], c_out))
    start = 0
    for k, count in enumerate(rb.offset_counts):
        if count == 0:
            continue
        sl = slice(start, start + count)
        start += count
        out.index_add_(0, rb.out_rows[sl], features[rb.in_rows[sl]] @ w[:, :, k].t())
    if bias is not None:
        out = out + bias
    return out


class _SparseConvBase(nn.Module):
    """Parameters laid out and initialised exactly like ``nn.Conv3d`` (copyable both ways)."""

    def __init__(self, in_channels: int, out_channels: int, kernel_size: int | Triple, bias: bool):
        super().__init__()
        self.in_channels, self.out_channels = in_channels, out_channels
        self.kernel_size = _triple(kernel_size)
        self.weight = nn.Parameter(torch.empty(out_channels, in_channels, *self.kernel_size))
        self.bias = nn.Parameter(torch.empty(out_channels)) if bias else None
        self.reset_parameters()

    def reset_parameters(self) -> None:
        # Same as nn.Conv3d.reset_parameters.
        nn.init.kaiming_uniform_(self.weight, a=math.sqrt(5))
        if self.bias is not None:
            fan_in = self.in_channels * math.prod(self.kernel_size)
            bound = 1 / math.sqrt(fan_in) if fan_in > 0 else 0
            nn.init.uniform_(self.bias, -bound, bound)

    def _check(self, x: SparseTensor) -> None:
        if x.features.ndim != 2 or x.features.shape[1] != self.in_channels:
            raise ValueError(f"expected features (N, {self.in_channels}), got {tuple(x.features.shape)}")


class SubMConv3d(_SparseConvBase):
    """Submanifold sparse conv: stride 1, padding k // 2, output sites = input sites."""

    def __init__(self, in_channels: int, out_channels: int, kernel_size: int | Triple = 3, bias: bool = True):
        super().__init__(in_channels, out_channels, kernel_size, bias)
        if any(k % 2 == 0 for k in self.kernel_size):
            raise ValueError(f"SubMConv3d needs odd kernel sizes, got {self.kernel_size}")

    def forward(self, x: SparseTensor, rulebook: Rulebook | None = None) -> SparseTensor:
        """(N, C_in) at x.coords -> (N, C_out) at the same coords; ``rulebook`` may be shared."""
        self._check(x)
        rb = rulebook if rulebook is not None else subm_rulebook(x.coords, x.spatial_shape, self.kernel_size)
        return x.replace_features(apply_rulebook(x.features, self.weight, self.bias, rb))


class SparseConv3d(_SparseConvBase):
    """Regular (usually strided) sparse conv; output sites = positions receiving any input."""

    def __init__(
        self,
        in_channels: int,
        out_channels: int,
        kernel_size: int | Triple,
        stride: int | Triple = 1,
        padding: int | Triple = 0,
        bias: bool = True,
    ):
        super().__init__(in_channels, out_channels, kernel_size, bias)
        self.stride, self.padding = _triple(stride), _triple(padding)

    def forward(self, x: SparseTensor) -> SparseTensor:
        """(N_in, C_in) on spatial_shape -> (N_out, C_out) on the strided output grid."""
        self._check(x)
        rb = strided_rulebook(x.coords, x.spatial_shape, self.kernel_size, self.stride, self.padding)
        out = apply_rulebook(x.features, self.weight, self.bias, rb)
        return SparseTensor(out, rb.out_coords, rb.out_shape, x.batch_size)
