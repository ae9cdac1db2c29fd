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
import functools
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


def decode_keys(keys: Tensor, spatial_shape: Triple) -> Tensor:
    """(N,) int64 keys -> (N, 4) long (b, z, y, x); the inverse of ``encode_coords``."""
    nz, ny, nx = spatial_shape
    x, rest = keys % nx, keys // nx
    y, rest = rest % ny, rest // ny
    z, b = rest % nz, rest // nz
    return torch.stack([b, z, y, x], dim=1)


# A dense lookup table costs 8 bytes per grid cell; above this many cells (256 MB) the lookup
# falls back to sorted keys and a binary search.
DENSE_TABLE_MAX_CELLS = 1 << 25


class _SiteLookup:
    """Row of an active site from its cell key.

    Keys index the cells of a batch of grids, ``[0, n_cells)``; the key ``n_cells`` stands for
    "no cell" (a neighbour outside the grid). A cell without an active site, and "no cell", get
    the row ``n_rows``: the index of the zero row that the convolution appends to its input.

    Small grids use a dense table (one gather per query, no sort); large ones the sorted keys and
    ``torch.searchsorted``. Both give the same rows.
    """

    def __init__(self, keys: Tensor, n_cells: int):
        self.n_rows = keys.numel()
        rows = torch.arange(self.n_rows, device=keys.device)
        if n_cells <= DENSE_TABLE_MAX_CELLS:
            self.table = torch.full((n_cells + 1,), self.n_rows, dtype=torch.long, device=keys.device)
            self.table[keys] = rows
        else:
            self.table = None
            self.sorted_keys, self.order = torch.sort(keys)

    def rows(self, query: Tensor) -> Tensor:
        """Keys of any shape, in ``[0, n_cells]`` -> rows of the same shape, ``n_rows`` if missing."""
        if self.table is not None:
            return self.table[query]
        if self.n_rows == 0:
            return torch.zeros_like(query)
        pos = torch.searchsorted(self.sorted_keys, query).clamp_(max=self.n_rows - 1)
        return torch.where(self.sorted_keys[pos] == query, self.order[pos], self.n_rows)


def _unique_keys(keys: Tensor, n_cells: int) -> Tensor:
    """Sorted distinct values of ``keys`` in ``[0, n_cells)``; the value ``n_cells`` is dropped."""
    if n_cells <= DENSE_TABLE_MAX_CELLS:
        hit = torch.zeros(n_cells + 1, dtype=torch.bool, device=keys.device)
        hit[keys.reshape(-1)] = True
        return torch.nonzero(hit[:n_cells]).squeeze(1)
    uniq = torch.unique(keys)
    return uniq[uniq < n_cells]


def _axis_taps(c: Tensor, kernel: int, stride: int, padding: int, n_dst: int, to_input: bool) -> Tensor:
    """(N,) coordinates along one axis -> (N, kernel): the coordinate at the other end of each tap.

    ``to_input``: from an output site o to the input it reads through tap k, ``o * s - p + k``.
    Otherwise from an input site i to the output it feeds through tap k, ``(i + p - k) / s`` when
    that is an integer (torch's cross-correlation). -1 where the tap leaves the grid ``[0, n_dst)``.
    """
    k = torch.arange(kernel, device=c.device)
    if to_input:
        t = c[:, None] * stride - padding + k
        ok = (t >= 0) & (t < n_dst)
    else:
        num = c[:, None] + padding - k
        t = torch.div(num, stride, rounding_mode="floor")
        ok = (num >= 0) & (num % stride == 0) & (t < n_dst)
    return torch.where(ok, t, -1)


def _tap_keys(
    coords: Tensor, dst_shape: Triple, n_batch: int, ks: Triple, st: Triple, pd: Triple, to_input: bool
) -> tuple[Tensor, int]:
    """Cell key at the other end of every kernel tap of every site.

    Returns ``keys (N, K)`` into the batch of ``dst_shape`` grids (taps in weight order) and
    ``n_cells``, the key used for taps that leave the grid.

    The key is separable, ``b * nz * ny * nx + z * ny * nx + y * nx + x``, so the taps are found
    per axis ((N, k) each) and only the final sum is (N, K). An axis whose tap leaves the grid
    contributes ``n_cells``, which pushes the sum to ``>= n_cells``; the clamp maps it to
    ``n_cells`` exactly.
    """
    nz, ny, nx = dst_shape
    n_cells = n_batch * nz * ny * nx
    parts = []
    for axis, step in enumerate((ny * nx, nx, 1)):
        t = _axis_taps(coords[:, 1 + axis], ks[axis], st[axis], pd[axis], dst_shape[axis], to_input)
        parts.append(torch.where(t >= 0, t * step, n_cells))
    base = (coords[:, 0] * (nz * ny * nx))[:, None, None, None]
    keys = base + parts[0][:, :, None, None] + parts[1][:, None, :, None] + parts[2][:, None, None, :]
    return keys.reshape(coords.shape[0], math.prod(ks)).clamp_(max=n_cells), n_cells


def _batch_count(coords: Tensor) -> int:
    return int(coords[:, 0].max()) + 1 if coords.shape[0] else 1


def _invert_taps(reverse: Tensor, n_out: int) -> Tensor:
    """(N_in, K) output row of each input tap (``n_out`` if none) -> (N_out, K) input row of each
    output tap (``N_in`` if none).

    Through one tap an input feeds at most one output and an output reads at most one input, so
    every real slot is written once; the taps without an output all land in an extra row that is
    dropped (whichever write wins there does not matter).
    """
    n_in, K = reverse.shape
    table = torch.full(((n_out + 1) * K,), n_in, dtype=torch.long, device=reverse.device)
    slots = reverse * K + torch.arange(K, device=reverse.device)
    table[slots.reshape(-1)] = torch.arange(n_in, device=reverse.device).repeat_interleave(K)
    return table.view(n_out + 1, K)[:n_out]


@dataclass(frozen=True)
class Rulebook:
    """Which input row each output row reads through each kernel tap.

    Attributes
    ----------
    neighbours : (N_out, K) long; the input row that output row o reads through tap k (taps in
        the order of ``weight[:, :, kz, ky, kx]`` flattened), or ``N_in`` where there is none.
    reverse : (N_in, K) long; the output row that input row i feeds through tap k, or ``N_out``.
        None for a submanifold rulebook: there it is ``neighbours`` with the taps reversed
        (o reads i through tap k exactly when i reads o through tap K - 1 - k).
    out_coords : (N_out, 4) long; (b, z, y, x) of the output sites.
    out_shape : (nz, ny, nx) of the output grid.

    ``in_rows``, ``out_rows`` and ``offset_counts`` give the same connections as a flat list of
    (input row, output row) pairs sorted by tap.
    """

    neighbours: Tensor
    reverse: Tensor | None
    out_coords: Tensor
    out_shape: Triple

    @property
    def n_in(self) -> int:
        return (self.neighbours if self.reverse is None else self.reverse).shape[0]

    @functools.cached_property
    def _pairs(self) -> tuple[Tensor, Tensor, list[int]]:
        tap, out_rows = torch.nonzero(self.neighbours.t() < self.n_in, as_tuple=True)
        in_rows = self.neighbours[out_rows, tap]
        counts = torch.bincount(tap, minlength=self.neighbours.shape[1]).tolist()
        return in_rows, out_rows, counts

    @property
    def in_rows(self) -> Tensor:
        """(M,) long input rows of the pairs, sorted by tap."""
        return self._pairs[0]

    @property
    def out_rows(self) -> Tensor:
        """(M,) long output rows of the pairs, sorted by tap."""
        return self._pairs[1]

    @property
    def offset_counts(self) -> list[int]:
        """K ints; how many pairs each tap has."""
        return self._pairs[2]


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
    coords, shape = coords.long(), tuple(spatial_shape)
    pd = tuple(k // 2 for k in ks)
    keys, n_cells = _tap_keys(coords, shape, _batch_count(coords), ks, (1, 1, 1), pd, to_input=True)
    neighbours = _SiteLookup(encode_coords(coords, shape), n_cells).rows(keys)
    return Rulebook(neighbours, None, coords, shape)


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
    coords = coords.long()
    out_shape = tuple((n + 2 * p - k) // s + 1 for n, k, s, p in zip(spatial_shape, ks, st, pd))
    if min(out_shape) < 1:
        raise ValueError(f"conv output would be empty: input {spatial_shape}, kernel {ks}, stride {st}")
    keys, n_cells = _tap_keys(coords, out_shape, _batch_count(coords), ks, st, pd, to_input=False)
    out_keys = _unique_keys(keys, n_cells)
    reverse = _SiteLookup(out_keys, n_cells).rows(keys)  # (N_in, K)
    neighbours = _invert_taps(reverse, out_keys.numel())  # (N_out, K)
    return Rulebook(neighbours, reverse, decode_keys(out_keys, out_shape), out_shape)


# Rows are gathered in chunks of about this many values (4 MB of float32): the gathered block
# stays in cache for its GEMM, and memory does not grow with K * N.
CHUNK_VALUES = 1 << 20


def _row_chunks(n_rows: int, row_values: int) -> list[slice]:
    step = max(1, CHUNK_VALUES // max(1, row_values))
    return [slice(i, min(i + step, n_rows)) for i in range(0, n_rows, step)]


def _with_zero_row(x: Tensor) -> Tensor:
    """(N, C) -> (N + 1, C); row N is what a missing neighbour (index N) reads."""
    return torch.cat([x, x.new_zeros((1, x.shape[1]))])


def _conv_forward(x: Tensor, weight: Tensor, neighbours: Tensor) -> Tensor:
    """(N_in, C_in) features, weight (C_out, C_in, K), neighbours (N_out, K) -> (N_out, C_out).

    out[o] = sum_k x[neighbours[o, k]] @ W_k^T, computed as dense GEMMs over all K taps (missing
    taps read a zero row) so that nothing is scattered. The gather runs on the narrower side:
    - C_in <= C_out: gather x rows into (n, K * C_in), one GEMM with the (K * C_in, C_out) weight;
    - C_in > C_out: first every input through every tap, (N_in, K * C_out), then gather tap k's
      block of each neighbour and sum over the taps.
    """
    c_out, c_in, K = weight.shape
    n_out = neighbours.shape[0]
    out = x.new_empty((n_out, c_out))
    if c_in <= c_out:
        x_pad = _with_zero_row(x)
        w = weight.permute(2, 1, 0).reshape(K * c_in, c_out)
        for rows in _row_chunks(n_out, K * c_in):
            gathered = x_pad.index_select(0, neighbours[rows].reshape(-1)).view(-1, K * c_in)
            torch.mm(gathered, w, out=out[rows])
    else:
        y = _with_zero_row(x @ weight.permute(1, 2, 0).reshape(c_in, K * c_out)).view(-1, c_out)
        taps = torch.arange(K, device=x.device)
        for rows in _row_chunks(n_out, K * c_out):
            gathered = y.index_select(0, (neighbours[rows] * K + taps).reshape(-1)).view(-1, K, c_out)
            torch.sum(gathered, dim=1, out=out[rows])
    return out


def _conv_backward(
    x: Tensor, grad_out: Tensor, weight: Tensor, reverse: Tensor, need_x: bool, need_w: bool
) -> tuple[Tensor | None, Tensor | None]:
    """Gradients of ``_conv_forward`` from the reverse taps (N_in, K), without any scatter.

    With G = the output grads gathered through ``reverse``, (N_in, K * C_out) (block k holds
    grad_out[reverse[i, k]]):
        grad_x = G @ [W_0; ...; W_{K-1}]   (each W_k (C_out, C_in))
        grad_W_k = x^T @ G_k
    Returns grad_x (N_in, C_in) and grad_w (C_out, C_in, K) (None where not needed).
    """
    c_out, c_in, K = weight.shape
    n_in = x.shape[0]
    g_pad = _with_zero_row(grad_out)
    w = weight.permute(2, 0, 1).reshape(K * c_out, c_in)
    grad_x = x.new_empty((n_in, c_in)) if need_x else None
    grad_w = x.new_zeros((c_in, K * c_out)) if need_w else None
    for rows in _row_chunks(n_in, K * c_out):
        gathered = g_pad.index_select(0, reverse[rows].reshape(-1)).view(-1, K * c_out)
        if need_x:
            torch.mm(gathered, w, out=grad_x[rows])
        if need_w:
            grad_w.addmm_(x[rows].t(), gathered)
    if need_w:
        grad_w = grad_w.view(c_in, K, c_out).permute(2, 0, 1)
    return grad_x, grad_w


class _RulebookConv(torch.autograd.Function):
    """features (N_in, C_in), weight (C_out, C_in, K) -> (N_out, C_out) through a rulebook.

    A custom backward because autograd of gather -> GEMM would scatter (index_add) the input
    grads; the reverse taps turn that scatter into a gather. For a submanifold rulebook the
    reverse taps are the neighbours read with the taps reversed, i.e. with the weight flipped.
    """

    @staticmethod
    def forward(ctx, features: Tensor, weight: Tensor, neighbours: Tensor, reverse: Tensor | None) -> Tensor:
        ctx.save_for_backward(features, weight, neighbours, reverse)
        return _conv_forward(features, weight, neighbours)

    @staticmethod
    def backward(ctx, grad_out: Tensor):
        features, weight, neighbours, reverse = ctx.saved_tensors
        need_x, need_w = ctx.needs_input_grad[:2]
        submanifold = reverse is None
        if submanifold:
            reverse, weight = neighbours, weight.flip(2)
        grad_x, grad_w = _conv_backward(features, grad_out.contiguous(), weight, reverse, need_x, need_w)
        if submanifold and grad_w is not None:
            grad_w = grad_w.flip(2)
        return grad_x, grad_w, None, None


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
    w = weight.reshape(weight.shape[0], weight.shape[1], -1)  # (C_out, C_in, K)
    out = _RulebookConv.apply(features.contiguous(), w, rb.neighbours, rb.reverse)
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
