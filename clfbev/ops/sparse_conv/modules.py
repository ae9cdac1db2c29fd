"""Sparse tensors and the convolution modules, laid out like ``nn.Conv3d``.

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

from clfbev.ops.sparse_conv.function import apply_rulebook
from clfbev.ops.sparse_conv.rulebook import (
    Rulebook,
    Triple,
    as_triple,
    encode_coords,
    strided_rulebook,
    subm_rulebook,
)

try:  # optional GPU backend; any failure (missing, ABI mismatch, no CUDA libs) just disables it
    import spconv.pytorch  # noqa: F401

    SPCONV_AVAILABLE = True
except Exception:  # noqa: BLE001 - an import of a compiled extension can raise more than ImportError
    SPCONV_AVAILABLE = False


def use_spconv(device: torch.device | str) -> bool:
    """True only when ``device`` is CUDA and spconv imports (spconv cannot train on CPU)."""
    return SPCONV_AVAILABLE and torch.device(device).type == "cuda"


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
        c = self.features.shape[1]
        # One flat index_copy (not a 4-index put): faster on CPU, and its grad is one index_select.
        cells = self.features.new_zeros((self.batch_size * nz * ny * nx, c))
        cells = cells.index_copy(0, encode_coords(self.coords, self.spatial_shape), self.features)
        return cells.view(self.batch_size, nz, ny, nx, c).permute(0, 4, 1, 2, 3).contiguous()

    def replace_features(self, features: Tensor) -> SparseTensor:
        """Same sites, new (N, C') features (after BatchNorm1d, ReLU, ...)."""
        return dataclasses.replace(self, features=features)


class _SparseConvBase(nn.Module):
    """Parameters laid out and initialised exactly like ``nn.Conv3d`` (copyable both ways)."""

    def __init__(self, in_channels: int, out_channels: int, kernel_size: int | Triple, bias: bool):
        super().__init__()
        self.in_channels, self.out_channels = in_channels, out_channels
        self.kernel_size = as_triple(kernel_size)
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
        self.stride, self.padding = as_triple(stride), as_triple(padding)

    def forward(self, x: SparseTensor) -> SparseTensor:
        """(N_in, C_in) on spatial_shape -> (N_out, C_out) on the strided output grid."""
        self._check(x)
        rb = strided_rulebook(x.coords, x.spatial_shape, self.kernel_size, self.stride, self.padding)
        out = apply_rulebook(x.features, self.weight, self.bias, rb)
        return SparseTensor(out, rb.out_coords, rb.out_shape, x.batch_size)
