"""The sparse convolution through a rulebook, as an autograd function with its own backward.

The forward is an implicit GEMM, no scatter:

    out = [x_pad[neighbours[:, 0]], ..., x_pad[neighbours[:, K-1]]] @ [W_0; ...; W_{K-1}]

(x_pad = the features plus one zero row, which the missing taps read). Dense over the taps, so
it multiplies zeros where a tap has no input, but one deep GEMM per chunk of rows runs far
faster on CPU than K skinny ones followed by ``index_add_``, and a conv with C_in > C_out
multiplies first and gathers the narrow products instead (``embedding_bag``).

The backward is hand-written (``_RulebookConv``) so that it gathers too: the input grads read
the output grads through the *reverse* taps (which output each input feeds through tap k). For
a submanifold conv these are the neighbours themselves with the taps mirrored (offset d and -d
give the same pairs swapped), i.e. the same table with the weight flipped; for a strided conv
each input can only feed through the taps of its residue class ``(i + p) mod s``, and the
rulebook's reverse tables keep only those.

Determinism: nothing here accumulates through a scatter (every output value is one GEMM or
``embedding_bag`` sum in a fixed order), so results are bit-reproducible on CPU. No atomics are
used on CUDA either, but only the CPU is tested for it. Python loops run over chunks of rows and
residue classes, never over sites.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from clfbev.ops.sparse_conv.rulebook import Rulebook, TapGroup


# Rows are gathered in chunks of about this many values (1 MB of float32): the gathered block
# stays in cache for its GEMM, and memory does not grow with K * N.
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
    def forward(
        ctx, features: Tensor, weight: Tensor, neighbours: Tensor, reverse: tuple[TapGroup, ...] | None
    ) -> Tensor:
        ctx.save_for_backward(features, weight, neighbours)
        ctx.reverse = reverse  # index tensors, never differentiated
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
