"""Rulebooks of a 3D sparse convolution: which input row each output row reads through each tap.

Sites are ``coords (N, 4) = (batch, z, y, x)`` rows. Rulebooks are built without sorting: on a
grid padded by the kernel's reach, the key of a site's tap cell is the site's key plus a constant
per tap, and a dense int64 table over the batch of padded grids maps cells to rows (sorted keys
and ``torch.searchsorted`` above ``DENSE_TABLE_MAX_CELLS`` cells). Python loops run over
residue classes, never over sites.

- ``subm_rulebook``: a submanifold conv (stride 1, padding k // 2, output sites = input sites).
- ``strided_rulebook``: a regular conv with any kernel, stride and padding; the output sites are
  exactly the positions that receive at least one active input. It also keeps the reverse taps
  (which output each input feeds) per residue class, for the backward.
"""

from __future__ import annotations

import functools
import itertools
import math
from dataclasses import dataclass

import torch
from torch import Tensor

Triple = tuple[int, int, int]


def as_triple(v: int | tuple[int, ...]) -> Triple:
    """An int or 3 ints -> (int, int, int) per axis (z, y, x)."""
    if isinstance(v, int):
        return (v, v, v)
    if len(v) != 3:
        raise ValueError(f"expected an int or 3 ints, got {v}")
    return (int(v[0]), int(v[1]), int(v[2]))


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
    ks = as_triple(kernel_size)
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
    ks, st, pd = as_triple(kernel_size), as_triple(stride), as_triple(padding)
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
