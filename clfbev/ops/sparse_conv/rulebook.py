"""Pure-torch 3D sparse convolution (submanifold and strided), for CPU and GPU.

A sparse tensor is a list of active sites ``coords (N, 4) = (batch, z, y, x)`` with features
``(N, C)``. A convolution is driven by a *rulebook*: for every output row and kernel tap k, the
input row it reads (``neighbours``, (N_out, K), with N_in standing for "none"). The convolution
is then an implicit GEMM, no scatter:

    out = [x_pad[neighbours[:, 0]], ..., x_pad[neighbours[:, K-1]]] @ [W_0; ...; W_{K-1}]

(x_pad = the features plus one zero row, which the missing taps read). Dense over the taps, so
it multiplies zeros where a tap has no input, but one deep GEMM per chunk of rows runs far
faster on CPU than K skinny ones followed by ``index_add_``, and a conv with C_in > C_out
multiplies first and gathers the narrow products instead (``embedding_bag``).

The backward is hand-written (``_RulebookConv``) so that it gathers too: the input grads read
the output grads through the *reverse* taps (which output each input feeds through tap k). For
a submanifold conv these are the neighbours themselves with the taps mirrored (offset d and -d
give the same pairs swapped), i.e. the same table with the weight flipped; for a strided conv
each input can only feed through the taps of its residue class ``(i + p) mod s`` (1 in 8 of a
3^3 kernel of stride 2), and the reverse tables keep only those.

Rulebooks are built without sorting: on a grid padded by the kernel's reach, the key of a
site's tap cell is the site's key plus a constant per tap, and a dense int64 table over the
batch of padded grids maps cells to rows (sorted keys and ``torch.searchsorted`` above
``DENSE_TABLE_MAX_CELLS`` cells). Python loops run over chunks of rows and residue classes,
never over sites.

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

Determinism: nothing in the convolution accumulates through a scatter (every output value is
one GEMM or ``embedding_bag`` sum in a fixed order), so results are bit-reproducible on CPU. The
same holds by construction on CUDA, where no atomics are used either; that has not been tested.

Optional backend: spconv 2.x is much faster on CUDA, but it cannot train on CPU (its backward
calls torch.cuda), which is why this pure-torch path exists. ``use_spconv(device)`` tells a caller
whether that backend could be used; the modules here always run the pure-torch path.
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
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
        c = self.features.shape[1]
        # One flat index_copy (not a 4-index put): faster on CPU, and its grad is one index_select.
        cells = self.features.new_zeros((self.batch_size * nz * ny * nx, c))
        cells = cells.index_copy(0, encode_coords(self.coords, self.spatial_shape), self.features)
        return cells.view(self.batch_size, nz, ny, nx, c).permute(0, 4, 1, 2, 3).contiguous()

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

    Keys index the cells of a batch of (padded) grids, ``[0, n_cells)``. A cell without an active
    site gets the row ``n_rows``: the index of the zero row that the convolution appends to its
    input.

    Small grids use a dense table (one gather per query, no sort); large ones the sorted keys and
    ``torch.searchsorted``. Both give the same rows. (``index_select`` rather than ``table[q]``:
    advanced indexing is several times slower on CPU.)
    """

    def __init__(self, keys: Tensor, n_cells: int):
        self.n_rows = keys.numel()
        rows = torch.arange(self.n_rows, device=keys.device)
        if n_cells <= DENSE_TABLE_MAX_CELLS:
            self.table = torch.full((n_cells,), self.n_rows, dtype=torch.long, device=keys.device)
            self.table.index_copy_(0, keys, rows)
        else:
            self.table = None
            self.sorted_keys, self.order = torch.sort(keys)

    def rows(self, query: Tensor) -> Tensor:
        """Keys of any shape, in ``[0, n_cells)`` -> rows of the same shape, ``n_rows`` if missing."""
        flat = query.reshape(-1)
        if self.table is not None:
            return self.table.index_select(0, flat).view(query.shape)
        if self.n_rows == 0:
            return torch.zeros_like(query)
        pos = torch.searchsorted(self.sorted_keys, flat).clamp_(max=self.n_rows - 1)
        hit = self.sorted_keys.index_select(0, pos) == flat
        return torch.where(hit, self.order.index_select(0, pos), self.n_rows).view(query.shape)


def _unique_keys(keys: Tensor, n_cells: int) -> Tensor:
    """Sorted distinct values of ``keys`` (any shape, in ``[0, n_cells)``)."""
    if n_cells <= DENSE_TABLE_MAX_CELLS:
        hit = torch.zeros(n_cells, dtype=torch.bool, device=keys.device)
        hit.index_fill_(0, keys.reshape(-1), True)
        return torch.nonzero(hit).squeeze(1)
    return torch.unique(keys)


class _PaddedGrid:
    """A batch of ``shape`` grids with margins of ``lo`` / ``hi`` cells per axis.

    The margins are wide enough for every kernel tap of every site to land on a cell, so a tap's
    key is the site's key plus a constant per tap, with no range checks; margin cells never hold
    a site, so a look-up there finds nothing, as it should. Keys are lexicographic in
    (b, z, y, x), like ``encode_coords``.
    """

    def __init__(self, shape: Triple, n_batch: int, lo: Triple, hi: Triple):
        self.shape, self.lo = shape, lo
        self.dims = tuple(n + a + b for n, a, b in zip(shape, lo, hi))
        self.n_cells = n_batch * math.prod(self.dims)

    def keys(self, coords: Tensor) -> Tensor:
        """(N, 4) (b, z, y, x) in the unpadded grid (margins allowed) -> (N,) keys."""
        (pz, py, px), (lz, ly, lx) = self.dims, self.lo
        return ((coords[:, 0] * pz + coords[:, 1] + lz) * py + coords[:, 2] + ly) * px + coords[:, 3] + lx

    def tap_offsets(self, steps: list[tuple[int, int, int]], device: torch.device) -> Tensor:
        """(T,) key offsets of (dz, dy, dx) steps."""
        _, py, px = self.dims
        return torch.tensor([(dz * py + dy) * px + dx for dz, dy, dx in steps], dtype=torch.long, device=device)

    def coords(self, keys: Tensor) -> Tensor:
        """(N,) keys -> (N, 4) (b, z, y, x) in the unpadded grid."""
        return decode_keys(keys, self.dims) - keys.new_tensor([0, *self.lo])

    def inside(self, keys: Tensor) -> Tensor:
        """(N,) bool: the key's cell lies in the grid, not in a margin."""
        c = self.coords(keys)[:, 1:]
        return ((c >= 0) & (c < c.new_tensor(self.shape))).all(dim=1)


def _batch_count(coords: Tensor) -> int:
    return int(coords[:, 0].max()) + 1 if coords.shape[0] else 1


AxisTaps = tuple[range, range, range]


@dataclass(frozen=True)
class TapGroup:
    """Input rows of one residue class (``(i + p) mod s`` per axis) and the taps they can feed.

    Attributes
    ----------
    rows : (n,) long; the input rows of the class.
    taps : (t,) long; the kernel taps (weight order) through which such an input can reach an
        output: ``k = (i + p) mod s`` per axis. The classes split the taps between them.
    outputs : (n, t) long; the output row that ``rows[j]`` feeds through ``taps[m]``, ``N_out``
        where none (only at the grid edge: an input always reaches an output through these taps).
    """

    rows: Tensor
    taps: Tensor
    outputs: Tensor


@dataclass(frozen=True)
class Rulebook:
    """Which input row each output row reads through each kernel tap.

    Attributes
    ----------
    neighbours : (N_out, K) long; the input row that output row o reads through tap k (taps in
        the order of ``weight[:, :, kz, ky, kx]`` flattened), or ``N_in`` where there is none.
    reverse : the output rows each input feeds, per tap, as ``TapGroup``s: a strided conv's
        (N_in, K) table is mostly empty, as an input only reaches outputs through the taps of its
        residue class (1 of 8 on average for a 3^3 kernel of stride 2), and the groups keep only
        those. None for a submanifold rulebook: there the reverse table is ``neighbours`` with the
        taps reversed (o reads i through tap k exactly when i reads o through tap K - 1 - k).
    out_coords : (N_out, 4) long; (b, z, y, x) of the output sites.
    out_shape : (nz, ny, nx) of the output grid.
    n_in : N_in, the number of input rows.

    ``in_rows``, ``out_rows`` and ``offset_counts`` give the same connections as a flat list of
    (input row, output row) pairs sorted by tap.
    """

    neighbours: Tensor
    reverse: tuple[TapGroup, ...] | None
    out_coords: Tensor
    out_shape: Triple
    n_in: int

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
    grid = _PaddedGrid(shape, _batch_count(coords), pd, pd)
    own = grid.keys(coords)  # (N,)
    # Tap k of site o reads the cell o + k - k // 2.
    steps = [tuple(k - p for k, p in zip(tap, pd)) for tap in itertools.product(*map(range, ks))]
    neighbours = _SiteLookup(own, grid.n_cells).rows(own[:, None] + grid.tap_offsets(steps, coords.device))
    return Rulebook(neighbours, None, coords, shape, coords.shape[0])


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
    # Margins: a class's taps reach up to ceil(k / s) - 1 cells below its base output, and the
    # base output of the last inputs may lie past the grid (when the conv drops them).
    lo = tuple(-(-k // s) - 1 for k, s in zip(ks, st))
    hi = tuple(max(0, (n - 1 + p) // s - (m - 1)) for n, p, s, m in zip(spatial_shape, pd, st, out_shape))
    grid = _PaddedGrid(out_shape, _batch_count(coords), lo, hi)
    classes = _residue_classes(coords, ks, st, pd)
    keys = [_class_tap_keys(coords, grid, rows, r, taps, st, pd) for rows, r, taps in classes]
    candidates = _unique_keys(torch.cat([coords.new_zeros(0)] + [k.reshape(-1) for k in keys]), grid.n_cells)
    out_keys = candidates[grid.inside(candidates)]  # sorted: output sites in (b, z, y, x) order
    lookup = _SiteLookup(out_keys, grid.n_cells)
    groups = tuple(
        TapGroup(rows, _flat_taps(ks, taps, coords.device), lookup.rows(k))
        for (rows, _, taps), k in zip(classes, keys)
    )
    neighbours = _invert_taps(groups, out_keys.numel(), coords.shape[0], math.prod(ks), coords.device)
    return Rulebook(neighbours, groups, grid.coords(out_keys), out_shape, coords.shape[0])


def _class_tap_keys(
    coords: Tensor, grid: _PaddedGrid, rows: Tensor, r: Triple, taps: AxisTaps, st: Triple, pd: Triple
) -> Tensor:
    """(n, T) output cell that each input of a residue class feeds through each of the class's taps.

    Tap ``k = r + j s`` (per axis) of input i reaches ``o = (i + p - r) / s - j``: a base cell
    (an exact division, by the choice of r) minus j.
    """
    c = coords.index_select(0, rows)
    base = torch.cat([c[:, :1], (c[:, 1:] + c.new_tensor(pd) - c.new_tensor(r)) // c.new_tensor(st)], dim=1)
    steps = [(-jz, -jy, -jx) for jz, jy, jx in itertools.product(*(range(len(t)) for t in taps))]
    return grid.keys(base)[:, None] + grid.tap_offsets(steps, coords.device)


def _residue_classes(coords: Tensor, ks: Triple, st: Triple, pd: Triple) -> list[tuple[Tensor, Triple, AxisTaps]]:
    """Input rows by residue class r, with r and the taps the class can feed through.

    Along an axis, input i reaches an output through tap k only if ``i + p - k`` is a multiple of
    s, i.e. ``k = r (mod s)`` with the class ``r = (i + p) mod s``. Classes without inputs or
    without taps (kernel smaller than the stride) are left out: those inputs feed nothing.
    """
    cls = torch.zeros(coords.shape[0], dtype=torch.long, device=coords.device)
    for axis in range(3):
        cls = cls * st[axis] + (coords[:, 1 + axis] + pd[axis]) % st[axis]
    order = torch.argsort(cls, stable=True)
    counts = torch.bincount(cls, minlength=math.prod(st)).tolist()
    classes, start = [], 0
    for c, count in enumerate(counts):
        rows, start = order[start:start + count], start + count
        r = (c // (st[1] * st[2]), (c // st[2]) % st[1], c % st[2])
        taps = tuple(range(r[axis], ks[axis], st[axis]) for axis in range(3))
        if count and all(len(t) for t in taps):
            classes.append((rows, r, taps))
    return classes


def _flat_taps(ks: Triple, taps: AxisTaps, device: torch.device) -> Tensor:
    """(T,) flat tap indices (weight order) of the product of per-axis taps."""
    tap_ids = torch.arange(math.prod(ks), device=device).view(ks)
    return tap_ids[tuple(slice(t.start, None, t.step) for t in taps)].reshape(-1)


def _invert_taps(groups: tuple[TapGroup, ...], n_out: int, n_in: int, K: int, device: torch.device) -> Tensor:
    """The reverse taps (output row each input feeds) -> (N_out, K) input row each output reads
    through each tap (``n_in`` if none).

    Through one tap an output reads at most one input, so every real slot is written once; the
    taps into a margin (no output) all land in an extra row that is dropped (whichever write wins
    there does not matter).
    """
    table = torch.full(((n_out + 1) * K,), n_in, dtype=torch.long, device=device)
    for g in groups:
        slots = g.outputs * K + g.taps
        table.index_copy_(0, slots.reshape(-1), g.rows[:, None].expand_as(slots).reshape(-1))
    return table.view(n_out + 1, K)[:n_out]


# Rows are gathered in chunks of about this many values (1 MB of float32): the gathered block
# stays in cache for its GEMM (2^18 was faster than 2^16, 2^20 and 2^22 on a 3^3, 32-channel
# layer), and memory does not grow with K * N.
CHUNK_VALUES = 1 << 18


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
    - C_in > C_out: first every input through every tap, (N_in, K * C_out), then sum tap k's
      block of each neighbour (one ``embedding_bag``).
    """
    c_out, c_in, K = weight.shape
    n_out = neighbours.shape[0]
    if c_in <= c_out:
        out = x.new_empty((n_out, c_out))
        x_pad = _with_zero_row(x)
        w = weight.permute(2, 1, 0).reshape(K * c_in, c_out)
        for rows in _row_chunks(n_out, K * c_in):
            gathered = x_pad.index_select(0, neighbours[rows].reshape(-1)).view(-1, K * c_in)
            torch.mm(gathered, w, out=out[rows])
    else:
        # (N_in + 1, K * C_out) with a zero last row, written in place (a cat would copy it all).
        y = x.new_empty((x.shape[0] + 1, K * c_out))
        torch.mm(x, weight.permute(1, 2, 0).reshape(c_in, K * c_out), out=y[:-1])
        y[-1].zero_()
        y = y.view(-1, c_out)
        taps = torch.arange(K, device=x.device)
        # embedding_bag sums the K gathered rows of each bag without materialising (N_out, K, C_out).
        out = F.embedding_bag(neighbours * K + taps, y, mode="sum")
    return out


def _conv_backward(
    x: Tensor, grad_out: Tensor, weight: Tensor, reverse: Tensor, need_x: bool, need_w: bool
) -> tuple[Tensor | None, Tensor | None]:
    """Gradients of ``_conv_forward`` from reverse taps, without any scatter.

    x (n, C_in) are input rows, ``reverse`` (n, K) the output row each feeds through each of the
    K taps of ``weight`` (C_out, C_in, K) (``N_out`` where none). With G = the output grads
    gathered through ``reverse``, (n, K * C_out) (block k holds grad_out[reverse[i, k]]):
        grad_x = G @ [W_0; ...; W_{K-1}]   (each W_k (C_out, C_in))
        grad_W_k = x^T @ G_k
    Returns grad_x (n, C_in) and grad_w (C_out, C_in, K) (None where not needed).
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
    def forward(ctx, features: Tensor, weight: Tensor, neighbours: Tensor, reverse) -> Tensor:
        ctx.save_for_backward(features, weight, neighbours)
        ctx.reverse = reverse  # tuple[TapGroup, ...] | None; index tensors, never differentiated
        return _conv_forward(features, weight, neighbours)

    @staticmethod
    def backward(ctx, grad_out: Tensor):
        features, weight, neighbours = ctx.saved_tensors
        need_x, need_w = ctx.needs_input_grad[:2]
        grad_out = grad_out.contiguous()
        if ctx.reverse is None:
            grad_x, grad_w = _conv_backward(features, grad_out, weight.flip(2), neighbours, need_x, need_w)
            return grad_x, grad_w.flip(2) if need_w else None, None, None
        # Each residue class owns its taps, so its rows and weight taps are written once each.
        grad_x = torch.zeros_like(features) if need_x else None
        grad_w = torch.zeros_like(weight) if need_w else None
        for group in ctx.reverse:
            x = features.index_select(0, group.rows)
            gx, gw = _conv_backward(x, grad_out, weight.index_select(2, group.taps), group.outputs, need_x, need_w)
            if need_x:
                grad_x.index_copy_(0, group.rows, gx)
            if need_w:
                grad_w.index_copy_(2, group.taps, gw)
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
