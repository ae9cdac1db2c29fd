"""Tests for clfbev.attention (BEVAttention core) and clfbev.fusion (ConvFuser, MCM, BSM)."""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F

from clfbev.attention import BEVAttention, avg_pool_cells, sinusoidal_pos_encoding_2d
from clfbev.fusion import BSM, MCM, ConvFuser

ATOL = 1e-5


@pytest.fixture(autouse=True)
def _seed():
    torch.manual_seed(0)


def heads_to_bev(x: torch.Tensor, H: int, W: int) -> torch.Tensor:
    """(B, heads, H*W, d) -> channel-last BEV (B, H, W, heads*d), head h on channels [h*d, (h+1)*d)."""
    B, h, L, d = x.shape
    return x.transpose(1, 2).reshape(B, H, W, h * d)


def bev_to_heads(x: torch.Tensor, heads: int) -> torch.Tensor:
    """(B, H, W, C) -> (B, heads, H*W, C/heads)."""
    B, H, W, C = x.shape
    return x.reshape(B, H * W, heads, C // heads).transpose(1, 2)


def rand_qkv(B=2, H=5, W=7, C=16, Cv=8):
    return torch.randn(B, H, W, C), torch.randn(B, H, W, C), torch.randn(B, H, W, Cv)


# ----------------------------------------------------------------------------- positional encoding


def test_pos_encoding_values():
    H, W, dim = 3, 5, 8
    pe = sinusoidal_pos_encoding_2d(H, W, dim)
    assert pe.shape == (H * W, dim)
    # Cell (0, 0): sin(0) = 0, cos(0) = 1 on every frequency.
    torch.testing.assert_close(pe[0], torch.tensor([0.0, 1, 0, 1, 0, 1, 0, 1]))
    # Cell (i, j): the row half depends on i only, the column half on j only.
    grid = pe.reshape(H, W, dim)
    torch.testing.assert_close(grid[2, 4, :4], grid[2, 0, :4])
    torch.testing.assert_close(grid[2, 4, 4:], grid[0, 4, 4:])
    # Lowest frequency is 1: channel 0 is sin(row), channel 4 is sin(col).
    torch.testing.assert_close(grid[2, 3, 0], torch.tensor(math.sin(2.0)))
    torch.testing.assert_close(grid[2, 3, 4], torch.tensor(math.sin(3.0)))
    # All cells are distinct.
    assert torch.cdist(pe, pe).add(torch.eye(H * W)).min() > 1e-3
    with pytest.raises(ValueError):
        sinusoidal_pos_encoding_2d(2, 2, 6)


# ----------------------------------------------------------------------------- exact


@pytest.mark.parametrize("Hk,Wk", [(5, 7), (3, 4)])
def test_exact_matches_torch_sdpa(Hk, Wk):
    B, heads, d, dv, H, W = 2, 4, 8, 6, 5, 7
    q = torch.randn(B, heads, H * W, d)
    k = torch.randn(B, heads, Hk * Wk, d)
    v = torch.randn(B, heads, Hk * Wk, dv)
    ref = F.scaled_dot_product_attention(q, k, v)
    attn = BEVAttention(heads, "exact")
    out, a = attn(heads_to_bev(q, H, W), heads_to_bev(k, Hk, Wk), heads_to_bev(v, Hk, Wk), return_attn=True)
    assert out.shape == (B, H, W, heads * dv)
    torch.testing.assert_close(bev_to_heads(out, heads), ref, atol=ATOL, rtol=0)
    assert a.shape == (B, heads, H * W, Hk * Wk)
    torch.testing.assert_close(a.sum(-1), torch.ones(B, heads, H * W), atol=ATOL, rtol=0)
    torch.testing.assert_close(a @ v, ref, atol=ATOL, rtol=0)
    # The one-query map is the matching row of the full map.
    qb, kb = heads_to_bev(q, H, W), heads_to_bev(k, Hk, Wk)
    m = attn.query_attention_map(qb, kb, (3, 2))
    torch.testing.assert_close(m.reshape(B, heads, -1), a[:, :, 3 * W + 2], atol=ATOL, rtol=0)


def test_query_chunk_same_result():
    q, k, v = rand_qkv()
    for mode in ("exact", "pooled"):
        full, a_full = BEVAttention(4, mode, pool_stride=2)(q, k, v, return_attn=True)
        chunked, a_chunk = BEVAttention(4, mode, pool_stride=2, query_chunk=6)(q, k, v, return_attn=True)
        torch.testing.assert_close(chunked, full, atol=ATOL, rtol=0)
        torch.testing.assert_close(a_chunk, a_full, atol=ATOL, rtol=0)


@pytest.mark.parametrize("mode", ["exact", "window", "pooled"])
def test_the_fused_kernel_gives_the_explicit_output_and_gradient(mode):
    """Without weights the attention runs torch's fused kernel; with them, matmul + softmax.
    Same output and input gradients, padded windows (7 x 10 in windows of 4) included."""
    q, k, v = (t.requires_grad_() for t in rand_qkv(B=2, H=7, W=10, C=8, Cv=6))
    attn = BEVAttention(2, mode, window=4, pool_stride=3)
    fused = attn(q, k, v)
    explicit, _ = attn(q, k, v, return_attn=True)
    torch.testing.assert_close(fused, explicit, atol=ATOL, rtol=0)
    g = torch.randn_like(fused)
    grads_fused = torch.autograd.grad(fused, (q, k, v), g)
    grads_explicit = torch.autograd.grad(explicit, (q, k, v), g)
    for a, b in zip(grads_fused, grads_explicit):
        torch.testing.assert_close(a, b, atol=1e-5, rtol=1e-4)


# ----------------------------------------------------------------------------- window


@pytest.mark.parametrize("window", [7, 16])
def test_window_covering_grid_equals_exact(window):
    q, k, v = rand_qkv(H=5, W=7)
    exact = BEVAttention(4, "exact")(q, k, v)
    win = BEVAttention(4, "window", window=window)(q, k, v)
    torch.testing.assert_close(win, exact, atol=ATOL, rtol=0)


def test_window_padded_keys_get_zero_weight():
    B, H, W, w, heads = 2, 7, 10, 4, 2  # padded to 8 x 12: 2 x 3 windows, the edge ones padded
    q, k, v = rand_qkv(B=B, H=H, W=W, C=8, Cv=6)
    attn = BEVAttention(heads, "window", window=w)
    out, a = attn(q, k, v, return_attn=True)
    assert out.shape == (B, H, W, 6)
    assert a.shape == (B, 2, 3, heads, w * w, w * w)
    # Which (padded) window cells are real.
    rows = torch.arange(2 * w)[:, None].expand(2 * w, 3 * w)
    cols = torch.arange(3 * w)[None, :].expand(2 * w, 3 * w)
    real = ((rows < H) & (cols < W)).reshape(2, w, 3, w).permute(0, 2, 1, 3).reshape(2, 3, w * w)
    real_keys = real[None, :, :, None, None, :].expand_as(a)
    assert (a[~real_keys] == 0).all()  # exactly zero, not just small
    assert (a[real_keys] > 0).all()
    torch.testing.assert_close(a.sum(-1), torch.ones(a.shape[:-1]), atol=ATOL, rtol=0)
    # Each window's output is plain attention among that window's real cells.
    for r0 in range(0, H, w):
        for c0 in range(0, W, w):
            sl = (slice(None), slice(r0, r0 + w), slice(c0, c0 + w))
            qs, ks, vs = q[sl], k[sl], v[sl]
            hh, ww = qs.shape[1:3]
            qh, kh, vh = (bev_to_heads(t, heads) for t in (qs, ks, vs))
            ref = F.scaled_dot_product_attention(qh, kh, vh)
            torch.testing.assert_close(out[sl], heads_to_bev(ref, hh, ww), atol=ATOL, rtol=0)
    # The one-query map agrees with the window weights and is zero outside the window.
    m = attn.query_attention_map(q, k, (6, 9))  # last window: rows 4..6, cols 8..9
    assert (m[:, :, :4].abs().sum() == 0) and (m[:, :, :, :8].abs().sum() == 0)
    torch.testing.assert_close(m.sum((-1, -2)), torch.ones(B, heads), atol=ATOL, rtol=0)
    win_row = a[:, 1, 2, :, (6 - 4) * w + (9 - 8)].reshape(B, heads, w, w)[:, :, : H - 4, : W - 8]
    torch.testing.assert_close(m[:, :, 4:, 8:], win_row, atol=ATOL, rtol=0)


@pytest.mark.parametrize("window_rc", [(0, 0), (1, 2)])
def test_window_output_ignores_other_windows(window_rc):
    H, W, w = 7, 10, 4
    q, k, v = rand_qkv(H=H, W=W)
    attn = BEVAttention(4, "window", window=w)
    out = attn(q, k, v)
    inside = torch.zeros(H, W, dtype=torch.bool)
    r, c = window_rc
    inside[r * w : (r + 1) * w, c * w : (c + 1) * w] = True
    outside = ~inside[None, :, :, None]
    q2, k2, v2 = (t + 5 * torch.randn_like(t) * outside for t in (q, k, v))
    out2 = attn(q2, k2, v2)
    torch.testing.assert_close(out2[:, inside], out[:, inside], atol=1e-6, rtol=0)
    assert (out2[:, ~inside] - out[:, ~inside]).abs().max() > 1e-2  # the change did reach the rest


# ----------------------------------------------------------------------------- pooled


def test_pooled_stride1_equals_exact():
    q, k, v = rand_qkv(H=6, W=5)
    exact, a_exact = BEVAttention(4, "exact")(q, k, v, return_attn=True)
    pooled, a_pooled = BEVAttention(4, "pooled", pool_stride=1)(q, k, v, return_attn=True)
    torch.testing.assert_close(pooled, exact, atol=ATOL, rtol=0)
    torch.testing.assert_close(a_pooled, a_exact, atol=ATOL, rtol=0)


def test_avg_pool_cells_averages_real_cells_only():
    x = torch.randn(2, 7, 5, 3)
    p = avg_pool_cells(x, 3)
    assert p.shape == (2, 3, 2, 3)
    torch.testing.assert_close(p[:, 0, 0], x[:, 0:3, 0:3].mean((1, 2)))
    torch.testing.assert_close(p[:, 2, 1], x[:, 6:7, 3:5].mean((1, 2)))  # 1 x 2 real cells at the corner
    # On a divisible grid it is torch's average pooling.
    y = torch.randn(2, 6, 8, 3)
    ref = F.avg_pool2d(y.permute(0, 3, 1, 2), 2).permute(0, 2, 3, 1)
    torch.testing.assert_close(avg_pool_cells(y, 2), ref)


def test_pooled_is_exact_attention_to_pooled_keys():
    q, k, v = rand_qkv(H=7, W=5)
    pooled, a = BEVAttention(4, "pooled", pool_stride=3)(q, k, v, return_attn=True)
    ref = BEVAttention(4, "exact")(q, avg_pool_cells(k, 3), avg_pool_cells(v, 3))
    torch.testing.assert_close(pooled, ref, atol=ATOL, rtol=0)
    assert a.shape == (2, 4, 35, 3 * 2)
    # The visualisation map spreads each pooled weight over its real cells and sums to 1.
    m = BEVAttention(4, "pooled", pool_stride=3).query_attention_map(q, k, (4, 1))
    assert m.shape == (2, 4, 7, 5)
    torch.testing.assert_close(m.sum((-1, -2)), torch.ones(2, 4), atol=ATOL, rtol=0)
    torch.testing.assert_close(m[:, :, 6:7, 3:5].sum((-1, -2)), a[:, :, 4 * 5 + 1, 5], atol=ATOL, rtol=0)
    torch.testing.assert_close(m[:, :, 0, 0] * 9, a[:, :, 4 * 5 + 1, 0], atol=ATOL, rtol=0)


# ----------------------------------------------------------------------------- modules


def test_attention_rejects_bad_args():
    with pytest.raises(ValueError):
        BEVAttention(4, "global")
    with pytest.raises(ValueError):
        BEVAttention(3, "exact")(*rand_qkv())  # 16 channels, 3 heads
    with pytest.raises(ValueError):
        MCM(8, 8, dim=12, heads=8)
    with pytest.raises(ValueError):
        MCM(8, 6, dim=16, heads=4)(torch.randn(1, 8, 4, 5), torch.randn(1, 6, 5, 4))


def opened(module: torch.nn.Module, seed: int = 1) -> torch.nn.Module:
    """The module as training leaves it: its zero-initialised gates (the attention's output
    projection, the FFN's last layer, the ConvFuser's camera weights) set to random values, so
    that the tests of what attention computes are not vacuous."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for name, p in module.named_parameters():
            if not p.any():
                p.copy_(torch.randn(p.shape, generator=g) * 0.3)
    return module


def _permute_cells(x: torch.Tensor, perm: torch.Tensor) -> torch.Tensor:
    """Permute the cells of (B, C, H, W) by a permutation of the H*W flat indices."""
    B, C, H, W = x.shape
    return x.reshape(B, C, H * W)[:, :, perm].reshape(B, C, H, W)


@pytest.mark.parametrize("mode", ["exact", "pooled"])
def test_mcm_invariant_to_permuting_camera_cells(mode):
    # Keys/values carry no positional encoding, so global cross-attention sees the camera BEV
    # as a set: any spatial shuffle of it leaves every output cell unchanged.
    H, W = 5, 6
    mcm = opened(MCM(6, 10, dim=16, heads=4, mode=mode, pool_stride=1)).eval()
    lidar, cam = torch.randn(2, 6, H, W), torch.randn(2, 10, H, W)
    out = mcm(lidar, cam)
    out_perm = mcm(lidar, _permute_cells(cam, torch.randperm(H * W)))
    torch.testing.assert_close(out_perm, out, atol=ATOL, rtol=0)
    # Not vacuous: the camera content does matter.
    assert (mcm(lidar, cam + torch.randn_like(cam)) - out).abs().max() > 1e-2


def test_mcm_window_invariant_to_permuting_inside_windows_only():
    H, W, w = 6, 5, 3  # windows: rows {0-2, 3-5} x cols {0-2, 3-4}
    mcm = opened(MCM(6, 10, dim=16, heads=4, mode="window", window=w)).eval()
    lidar, cam = torch.randn(2, 6, H, W), torch.randn(2, 10, H, W)
    out = mcm(lidar, cam)
    window_id = (torch.arange(H)[:, None] // w * 10 + torch.arange(W)[None, :] // w).reshape(-1)
    perm = torch.arange(H * W)
    for wid in window_id.unique():  # shuffle cells within each window
        idx = (window_id == wid).nonzero()[:, 0]
        perm[idx] = idx[torch.randperm(len(idx))]
    torch.testing.assert_close(mcm(lidar, _permute_cells(cam, perm)), out, atol=ATOL, rtol=0)
    # Swapping two cells of different windows changes both windows' outputs.
    swap = torch.arange(H * W)
    swap[0], swap[H * W - 1] = H * W - 1, 0
    assert (mcm(lidar, _permute_cells(cam, swap)) - out).abs().max() > 1e-3


def test_bsm_window_locality():
    # LN and FFN act per cell, so a window's BSM output depends only on that window's input.
    H, W, w = 7, 5, 4
    bsm = opened(BSM(16, heads=4, mode="window", window=w)).eval()
    x = torch.randn(2, 16, H, W)
    x2 = x.clone()
    x2[:, :, 4:] += torch.randn(2, 16, 3, W)  # rows 4..6 are other windows
    torch.testing.assert_close(bsm(x2)[:, :, :4], bsm(x)[:, :, :4], atol=1e-6, rtol=0)


@pytest.mark.parametrize("mode", ["exact", "window", "pooled"])
@pytest.mark.parametrize("B,H,W", [(2, 6, 9), (1, 11, 4)])
def test_shapes(mode, B, H, W):
    lidar, cam = torch.randn(B, 12, H, W), torch.randn(B, 20, H, W)
    mcm = MCM(12, 20, dim=16, heads=4, mode=mode, window=4, pool_stride=2, ffn_ratio=2.0)
    fused = mcm(lidar, cam)
    assert fused.shape == (B, 16, H, W) and torch.isfinite(fused).all()
    bsm = BSM(16, heads=2, mode=mode, window=4, pool_stride=2, ffn_ratio=1.5)
    assert bsm(fused).shape == (B, 16, H, W)
    assert ConvFuser(12, 20, 24)(lidar, cam).shape == (B, 24, H, W)
    for m in (mcm.attention_map(lidar, cam, (H - 1, 1)), bsm.attention_map(fused, (0, W - 1))):
        assert m.shape[0] == B and m.shape[2:] == (H, W)
        torch.testing.assert_close(m.sum((-1, -2)), torch.ones(m.shape[:2]), atol=ATOL, rtol=0)


def _assert_all_grads(module: torch.nn.Module) -> None:
    for name, p in module.named_parameters():
        assert p.grad is not None, f"{name}: no gradient"
        assert torch.isfinite(p.grad).all(), f"{name}: non-finite gradient"
        assert p.grad.abs().max() > 0, f"{name}: all-zero gradient"


@pytest.mark.parametrize("mode", ["exact", "window", "pooled"])
def test_gradients_reach_every_parameter(mode):
    B, H, W = 2, 6, 7
    lidar = torch.randn(B, 8, H, W, requires_grad=True)
    cam = torch.randn(B, 12, H, W, requires_grad=True)
    mcm = opened(MCM(8, 12, dim=16, heads=4, mode=mode, window=4, pool_stride=2))
    bsm = opened(BSM(16, heads=4, mode=mode, window=4, pool_stride=2))
    fuser = opened(ConvFuser(8, 12, 16))
    out = bsm(mcm(lidar, cam)) + fuser(lidar, cam)
    # Random weights: a plain sum would give LayerNorm's input zero gradient (its output sums to
    # a constant), hiding missing paths.
    (out * torch.randn_like(out)).sum().backward()
    for m in (mcm, bsm, fuser):
        _assert_all_grads(m)
    assert cam.grad.abs().max() > 0 and lidar.grad.abs().max() > 0


# ----------------------------------------------------------------------------- identity at init


@pytest.mark.parametrize("mode", ["exact", "window", "pooled"])
def test_mcm_and_bsm_start_as_the_identity(mode):
    """At initialisation MCM passes the lidar BEV through (W1 = identity, zero output gates) and
    BSM its input, exactly, whatever the camera BEV holds; the gates still get gradients."""
    B, H, W = 2, 6, 7
    lidar, cam = torch.randn(B, 16, H, W), torch.randn(B, 12, H, W)
    mcm = MCM(16, 12, dim=16, heads=4, mode=mode, window=4, pool_stride=2)
    bsm = BSM(16, heads=4, mode=mode, window=4, pool_stride=2)
    assert torch.equal(mcm(lidar, cam), lidar)
    assert torch.equal(mcm(lidar, torch.randn_like(cam) * 100), lidar)
    assert torch.equal(bsm(lidar), lidar)
    (mcm(lidar, cam) * torch.randn(B, 16, H, W)).sum().backward()
    assert mcm.out_proj.weight.grad.abs().max() > 0


def test_convfuser_starts_blind_to_the_camera():
    lidar, cam = torch.randn(2, 8, 5, 6), torch.randn(2, 12, 5, 6)
    fuser = ConvFuser(8, 12, 16)
    out = fuser(lidar, cam)
    assert torch.equal(fuser(lidar, torch.randn_like(cam) * 100), out)
    # And it is a concat + conv: the same as one conv over [lidar, cam] with the stacked weights.
    opened(fuser).eval()
    w = torch.cat([fuser.conv_lidar.weight, fuser.conv_cam.weight], dim=1)
    ref = torch.relu(fuser.bn(F.conv2d(torch.cat([lidar, cam], 1), w, padding=1)))
    torch.testing.assert_close(fuser(lidar, cam), ref, atol=1e-5, rtol=0)


def test_positional_encoding_does_not_dominate_the_query():
    """The query content is layer-normalised (RMS 1); the encoding starts at RMS PE_INIT_RMS."""
    from clfbev.fusion import PE_INIT_RMS
    mcm = MCM(16, 12, dim=16, heads=4)
    pe = mcm.pos(40, 40, torch.zeros(1))
    torch.testing.assert_close(pe.pow(2).mean().sqrt(), torch.tensor(PE_INIT_RMS), atol=0.02, rtol=0)
    assert PE_INIT_RMS < 1.0
