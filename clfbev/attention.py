"""Multi-head attention over BEV cells: the core shared by MCM and BSM.

BEV maps are handled channel-last here, ``(B, H, W, C)``, because the modules around the
core (linear projections, LayerNorm, FFN) work per cell on the last axis. A head ``h`` owns
channels ``[h * d, (h + 1) * d)`` with ``d = C // heads``.

The attention is ``softmax(q k^T / sqrt(d)) v``. When the weights are asked for (visualisation,
tests) it is computed explicitly (matmul + softmax); otherwise by torch's fused
``scaled_dot_product_attention``, the same function without materialising the weights for the
backward (on the CPU its flash kernel is faster than the explicit form, forward and backward).

Complexity, with ``N = H * W`` BEV cells, ``h`` heads and ``C`` channels:

============  ===========================  ===============================================
mode          time                         peak memory of the attention weights
============  ===========================  ===============================================
``exact``     O(N^2 C)                     O(B h N^2), or O(B h q N) with ``query_chunk=q``
``window``    O(N w^2 C)                   O(B h N w^2)
``pooled``    O(N (N / s^2) C)             O(B h N^2 / s^2), or O(B h q N / s^2) chunked
============  ===========================  ===============================================

``exact`` is global attention, as in the paper. ``window`` restricts each cell to the
non-overlapping ``w x w`` window it lies in (linear in N). ``pooled`` keeps every query at
full resolution but attends to keys/values average-pooled with stride ``s`` (global reach,
``s^2`` times cheaper than exact). At the paper's 180 x 180 BEV grid exact attention needs about
4 GB per head and sample for the weights alone; that is why the scalable modes exist.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from clfbev.settings import ATTENTION_MODES



def sinusoidal_pos_encoding_2d(
    H: int, W: int, dim: int, device: torch.device | str | None = None
) -> Tensor:
    """Fixed 2D sine/cosine encoding of the BEV cell index (DETR style).

    The first ``dim / 2`` channels encode the row ``i``, the last ``dim / 2`` the column ``j``;
    each half is ``[sin(p * f_0), cos(p * f_0), sin(p * f_1), cos(p * f_1), ...]`` with
    ``f_k = 10000^(-2k / (dim / 2))``.

    Parameters
    ----------
    H, W : grid size (rows, columns).
    dim : channels, divisible by 4.
    device : where to build it.

    Returns
    -------
    (H * W, dim) float32, row-major over the cells (cell ``i * W + j``).
    """
    if dim % 4 != 0:
        raise ValueError(f"positional encoding dim must be divisible by 4, got {dim}")
    half = dim // 2
    freq = 10000.0 ** (-torch.arange(0, half, 2, device=device, dtype=torch.float32) / half)
    rows = torch.arange(H, device=device, dtype=torch.float32)[:, None] * freq  # (H, half/2)
    cols = torch.arange(W, device=device, dtype=torch.float32)[:, None] * freq  # (W, half/2)
    # Interleave sin/cos so that channel 2k is sin and 2k+1 is cos of the same frequency.
    pe_row = torch.stack([rows.sin(), rows.cos()], dim=-1).reshape(H, half)
    pe_col = torch.stack([cols.sin(), cols.cos()], dim=-1).reshape(W, half)
    pe = torch.cat(
        [pe_row[:, None, :].expand(H, W, half), pe_col[None, :, :].expand(H, W, half)], dim=-1
    )
    return pe.reshape(H * W, dim)


def _split_heads(x: Tensor, heads: int) -> Tensor:
    """(B, L, C) -> (B, heads, L, C / heads)."""
    B, L, C = x.shape
    return x.reshape(B, L, heads, C // heads).transpose(1, 2)


def _merge_heads(x: Tensor) -> Tensor:
    """(B, heads, L, d) -> (B, L, heads * d)."""
    B, h, L, d = x.shape
    return x.transpose(1, 2).reshape(B, L, h * d)


def _weights(q: Tensor, k: Tensor, key_mask: Tensor | None = None) -> Tensor:
    """softmax(q k^T / sqrt(d)) for q (..., Lq, d), k (..., Lk, d) -> (..., Lq, Lk).

    ``key_mask`` (broadcastable to (..., Lq, Lk), True = real key) gives masked keys a logit of
    -inf, hence a weight of exactly 0. Every query must keep at least one real key.
    """
    logits = (q @ k.transpose(-1, -2)) * (1.0 / math.sqrt(q.shape[-1]))
    if key_mask is not None:
        logits = logits.masked_fill(~key_mask, float("-inf"))
    return logits.softmax(dim=-1)


def _attend(
    q: Tensor, k: Tensor, v: Tensor, key_mask: Tensor | None = None, need_weights: bool = True
) -> tuple[Tensor, Tensor | None]:
    """softmax(q k^T / sqrt(d)) v with v (..., Lk, dv) -> output (..., Lq, dv), weights (..., Lq, Lk)
    (None unless ``need_weights``: then the fused kernel computes the output)."""
    if not need_weights:
        return F.scaled_dot_product_attention(q, k, v, attn_mask=key_mask), None
    attn = _weights(q, k, key_mask)
    return attn @ v, attn


def _pad_to_multiple(x: Tensor, mh: int, mw: int) -> Tensor:
    """Zero-pad (B, H, W, C) at the bottom/right so H, W become multiples of mh, mw."""
    H, W = x.shape[1:3]
    return F.pad(x, (0, 0, 0, (-W) % mw, 0, (-H) % mh))


def avg_pool_cells(x: Tensor, s: int) -> Tensor:
    """Average-pool (B, H, W, C) with stride and kernel ``s`` -> (B, ceil(H/s), ceil(W/s), C).

    Edge cells that hang over the grid average only the real cells they cover (zero padding
    would otherwise bias them towards 0).
    """
    B, H, W, C = x.shape
    xp = _pad_to_multiple(x, s, s)
    Hs, Ws = xp.shape[1] // s, xp.shape[2] // s
    total = xp.reshape(B, Hs, s, Ws, s, C).sum(dim=(2, 4))
    return total / _cell_counts(H, W, s, x)[..., None]


def _cell_counts(H: int, W: int, s: int, like: Tensor) -> Tensor:
    """(1, ceil(H/s), ceil(W/s)): how many real cells of an H x W grid each s x s block covers."""
    ones = _pad_to_multiple(like.new_ones(1, H, W, 1), s, s)[..., 0]
    return ones.reshape(1, ones.shape[1] // s, s, ones.shape[2] // s, s).sum(dim=(2, 4))


def _to_windows(x: Tensor, wh: int, ww: int) -> Tensor:
    """(B, Hp, Wp, C), Hp % wh == Wp % ww == 0 -> (B * nH * nW, wh * ww, C), windows row-major."""
    B, Hp, Wp, C = x.shape
    nH, nW = Hp // wh, Wp // ww
    x = x.reshape(B, nH, wh, nW, ww, C).permute(0, 1, 3, 2, 4, 5)
    return x.reshape(B * nH * nW, wh * ww, C)


def _from_windows(x: Tensor, B: int, Hp: int, Wp: int, wh: int, ww: int) -> Tensor:
    """Inverse of :func:`_to_windows`: (B * nH * nW, wh * ww, C) -> (B, Hp, Wp, C)."""
    nH, nW = Hp // wh, Wp // ww
    C = x.shape[-1]
    x = x.reshape(B, nH, nW, wh, ww, C).permute(0, 1, 3, 2, 4, 5)
    return x.reshape(B, Hp, Wp, C)


class BEVAttention(nn.Module):
    """Parameter-free multi-head ``softmax(q k^T / sqrt(d_head)) v`` over BEV cells.

    Parameters
    ----------
    heads : number of heads; the q/k and v channels must be divisible by it.
    mode : ``"exact"`` (global), ``"window"`` (non-overlapping ``window x window`` windows) or
        ``"pooled"`` (keys/values average-pooled with stride ``pool_stride``). See the module
        docstring for how time and memory grow with each.
    window : window side in cells (``window`` mode). The grid needs not be divisible by it: it
        is zero-padded and the padded keys are masked to weight 0. A window larger than the grid
        is clipped to the grid, so ``window >= max(H, W)`` is exactly global attention.
    pool_stride : pooling stride ``s`` (``pooled`` mode); ``s = 1`` is exactly global attention.
    query_chunk : if set, exact/pooled modes process this many queries at a time, bounding the
        weight memory to O(B h query_chunk N_k) (same result; time unchanged).
    """

    def __init__(
        self,
        heads: int,
        mode: str = "exact",
        window: int = 8,
        pool_stride: int = 4,
        query_chunk: int | None = None,
    ) -> None:
        super().__init__()
        if mode not in ATTENTION_MODES:
            raise ValueError(f"attention mode must be one of {ATTENTION_MODES}, got {mode!r}")
        if heads < 1 or window < 1 or pool_stride < 1:
            raise ValueError(
                f"heads, window and pool_stride must be >= 1, got {heads}, {window}, {pool_stride}"
            )
        if query_chunk is not None and query_chunk < 1:
            raise ValueError(f"query_chunk must be >= 1 or None, got {query_chunk}")
        self.heads = heads
        self.mode = mode
        self.window = window
        self.pool_stride = pool_stride
        self.query_chunk = query_chunk

    def extra_repr(self) -> str:
        return f"heads={self.heads}, mode={self.mode}, window={self.window}, pool_stride={self.pool_stride}"

    def _keys(self, k: Tensor, v: Tensor) -> tuple[Tensor, Tensor]:
        """Key/value grids the queries attend to: the input, or its pooled version."""
        if self.mode == "pooled" and self.pool_stride > 1:
            return avg_pool_cells(k, self.pool_stride), avg_pool_cells(v, self.pool_stride)
        return k, v

    def forward(
        self, q: Tensor, k: Tensor, v: Tensor, return_attn: bool = False
    ) -> Tensor | tuple[Tensor, Tensor]:
        """Attend from every query cell to the key cells.

        Parameters
        ----------
        q : (B, H, W, C) queries, channel-last.
        k : (B, Hk, Wk, C) keys; ``window`` mode needs (Hk, Wk) == (H, W).
        v : (B, Hk, Wk, Cv) values.
        return_attn : also return the weights.

        Returns
        -------
        out : (B, H, W, Cv).
        attn (if ``return_attn``) :
            exact: (B, heads, H * W, Hk * Wk);
            pooled: (B, heads, H * W, ceil(Hk / s) * ceil(Wk / s));
            window: (B, nH, nW, heads, wh * ww, wh * ww) over the cells of each (padded) window,
            row-major inside the window; padded keys have weight exactly 0.
        """
        B, H, W, C = q.shape
        if k.shape[:1] != q.shape[:1] or k.shape[-1] != C or k.shape[:3] != v.shape[:3]:
            raise ValueError(f"incompatible q {tuple(q.shape)}, k {tuple(k.shape)}, v {tuple(v.shape)}")
        if C % self.heads or v.shape[-1] % self.heads:
            raise ValueError(f"channels q/k {C}, v {v.shape[-1]} not divisible by heads {self.heads}")
        if self.mode == "window":
            return self._window(q, k, v, return_attn)

        k, v = self._keys(k, v)
        qh = _split_heads(q.reshape(B, H * W, C), self.heads)  # (B, h, N, d)
        kh = _split_heads(k.reshape(B, -1, C), self.heads)  # (B, h, Nk, d)
        vh = _split_heads(v.reshape(B, -1, v.shape[-1]), self.heads)  # (B, h, Nk, dv)
        chunk = self.query_chunk or H * W
        outs, attns = [], []
        # Chunking queries only bounds memory; each row of the softmax is independent.
        for start in range(0, H * W, chunk):
            o, a = _attend(qh[:, :, start : start + chunk], kh, vh, need_weights=return_attn)
            outs.append(o)
            if return_attn:
                attns.append(a)
        out = _merge_heads(torch.cat(outs, dim=2)).reshape(B, H, W, -1)
        return (out, torch.cat(attns, dim=2)) if return_attn else out

    def _window_sizes(self, H: int, W: int) -> tuple[int, int]:
        # Clipping the window to the grid changes no partition, only avoids needless padding.
        return min(self.window, H), min(self.window, W)

    def _window(self, q: Tensor, k: Tensor, v: Tensor, return_attn: bool) -> Tensor | tuple[Tensor, Tensor]:
        B, H, W, _ = q.shape
        if k.shape[1:3] != (H, W):
            raise ValueError(f"window mode needs keys on the query grid {(H, W)}, got {tuple(k.shape[1:3])}")
        wh, ww = self._window_sizes(H, W)
        qp, kp, vp = (_pad_to_multiple(t, wh, ww) for t in (q, k, v))
        Hp, Wp = qp.shape[1:3]
        qw, kw, vw = (_split_heads(_to_windows(t, wh, ww), self.heads) for t in (qp, kp, vp))
        key_mask = None
        if (Hp, Wp) != (H, W):
            # Padded cells are zeros; without the mask they would still take exp(q . 0) of the
            # softmax mass. Each window holds >= 1 real cell (padding < window), so no NaN.
            real = _pad_to_multiple(q.new_ones(1, H, W, 1), wh, ww) > 0
            real = _to_windows(real, wh, ww)[..., 0]  # (nH * nW, wh * ww)
            key_mask = real.repeat(B, 1)[:, None, None, :]  # (B * nWin, 1, 1, wh * ww)
        o, a = _attend(qw, kw, vw, key_mask, need_weights=return_attn)
        out = _from_windows(_merge_heads(o), B, Hp, Wp, wh, ww)[:, :H, :W]
        if not return_attn:
            return out
        return out, a.reshape(B, Hp // wh, Wp // ww, *a.shape[1:])

    def query_attention_map(self, q: Tensor, k: Tensor, cell: tuple[int, int]) -> Tensor:
        """Weights of one query cell over the key grid, for visualisation, in any mode.

        Costs O(N_k C): only the one query row is computed.

        Parameters
        ----------
        q : (B, H, W, C) queries; k : (B, Hk, Wk, C) keys.
        cell : (row, col) of the query.

        Returns
        -------
        (B, heads, Hk, Wk) weights summing to 1 over the key cells. ``window``: zero outside the
        query's window. ``pooled``: a pooled key's weight is spread evenly over the cells it
        averages.
        """
        B, H, W, C = q.shape
        Hk, Wk = k.shape[1:3]
        i, j = cell
        q1 = _split_heads(q[:, i, j][:, None, :], self.heads)  # (B, h, 1, d)
        if self.mode == "pooled" and self.pool_stride > 1:
            s = self.pool_stride
            kp = avg_pool_cells(k, s)  # (B, Hs, Ws, C)
            a = _weights(q1, _split_heads(kp.reshape(B, -1, C), self.heads))
            a = a.reshape(B, self.heads, *kp.shape[1:3])
            # Number of real cells under each pooled key, so that the spread weights sum to 1.
            n_cells = _cell_counts(Hk, Wk, s, k)  # (1, Hs, Ws)
            spread = (a / n_cells[:, None]).repeat_interleave(s, dim=2).repeat_interleave(s, dim=3)
            return spread[:, :, :Hk, :Wk]
        kh = _split_heads(k.reshape(B, Hk * Wk, C), self.heads)
        mask = None
        if self.mode == "window":
            wh, ww = self._window_sizes(H, W)
            r0, c0 = (i // wh) * wh, (j // ww) * ww
            inside = torch.zeros(Hk, Wk, dtype=torch.bool, device=k.device)
            inside[r0 : r0 + wh, c0 : c0 + ww] = True
            mask = inside.reshape(1, 1, 1, Hk * Wk)
        a = _weights(q1, kh, mask)  # (B, h, 1, Nk)
        return a.reshape(B, self.heads, Hk, Wk)
