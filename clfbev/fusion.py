"""Camera + lidar BEV fusion: the concat baseline, MCM (cross-attention) and BSM (self-attention).

All modules take and return channel-first BEV maps ``(B, C, H, W)`` on one shared grid, so
they drop in between the encoders and the head. Inside, the attention blocks work per cell,
channel-last, because the projections, LayerNorm and FFN act on each cell's channels.

Paper (CL-FusionBEV):
    MCM: q = W1 F_lidar + PE, k = W2 F_cam, v = W3 F_cam, softmax(q k^T / sqrt(d)) v
    BSM: q, k, v from the fused BEV, softmax(q k^T / sqrt(d)) v for global context.
Both are wrapped as a post-norm transformer layer (residual + LayerNorm, FFN + residual +
LayerNorm), as in the standard encoder layer the paper builds on.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from clfbev.attention import BEVAttention, sinusoidal_pos_encoding_2d


def _check_grid(a: Tensor, b: Tensor, names: str) -> None:
    if a.dim() != 4 or b.dim() != 4 or a.shape[0] != b.shape[0] or a.shape[2:] != b.shape[2:]:
        raise ValueError(
            f"{names}: need (B, C, H, W) maps on one grid, got {tuple(a.shape)} and {tuple(b.shape)}"
        )


def _ffn(dim: int, ffn_ratio: float) -> nn.Sequential:
    hidden = max(1, int(round(dim * ffn_ratio)))
    return nn.Sequential(nn.Linear(dim, hidden), nn.GELU(), nn.Linear(hidden, dim))


class ConvFuser(nn.Module):
    """BEVFusion-style baseline: concat along channels -> 3x3 conv -> BN -> ReLU.

    Parameters
    ----------
    lidar_ch, cam_ch : input channels of the lidar and camera BEV.
    out_ch : output channels.
    """

    def __init__(self, lidar_ch: int, cam_ch: int, out_ch: int) -> None:
        super().__init__()
        # No conv bias: BN's shift makes it redundant.
        self.conv = nn.Conv2d(lidar_ch + cam_ch, out_ch, 3, padding=1, bias=False)
        self.bn = nn.BatchNorm2d(out_ch)
        self.act = nn.ReLU(inplace=True)

    def forward(self, lidar_bev: Tensor, cam_bev: Tensor) -> Tensor:
        """lidar_bev (B, Cl, H, W), cam_bev (B, Cc, H, W) -> (B, out_ch, H, W)."""
        _check_grid(lidar_bev, cam_bev, "ConvFuser")
        return self.act(self.bn(self.conv(torch.cat([lidar_bev, cam_bev], dim=1))))


class MCM(nn.Module):
    """Multimodal cross-attention: lidar BEV queries attend to the camera BEV.

    ``x = W1 F_lidar``; ``q = x + PE``; ``k = Wk F_cam``, ``v = Wv F_cam`` (no positional
    encoding on k/v, as in the paper); ``y = LN(x + Wo attn(q, k, v))``;
    ``out = LN(y + FFN(y))``.

    Parameters
    ----------
    lidar_ch, cam_ch : input channels.
    dim : model/output channels, divisible by ``heads`` and by 4 (positional encoding).
    heads : attention heads.
    mode, window, pool_stride : see :class:`clfbev.attention.BEVAttention`.
    ffn_ratio : FFN hidden width over ``dim``.
    query_chunk : optional query chunking for exact/pooled modes (memory only).
    """

    def __init__(
        self,
        lidar_ch: int,
        cam_ch: int,
        dim: int = 128,
        heads: int = 8,
        mode: str = "window",
        window: int = 8,
        pool_stride: int = 4,
        ffn_ratio: float = 2.0,
        query_chunk: int | None = None,
    ) -> None:
        super().__init__()
        if dim % heads or dim % 4:
            raise ValueError(f"MCM dim {dim} must be divisible by heads {heads} and by 4")
        self.dim = dim
        self.q_proj = nn.Linear(lidar_ch, dim)  # W1
        self.k_proj = nn.Linear(cam_ch, dim)  # W2 (keys)
        self.v_proj = nn.Linear(cam_ch, dim)  # W2 (values)
        self.attn = BEVAttention(heads, mode, window, pool_stride, query_chunk)
        self.out_proj = nn.Linear(dim, dim)
        self.norm1 = nn.LayerNorm(dim)
        self.ffn = _ffn(dim, ffn_ratio)
        self.norm2 = nn.LayerNorm(dim)

    def _qkv(self, lidar_bev: Tensor, cam_bev: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """Channel-last x = W1 F_lidar, q = x + PE, k, v: each (B, H, W, dim)."""
        _check_grid(lidar_bev, cam_bev, "MCM")
        B, _, H, W = lidar_bev.shape
        x = self.q_proj(lidar_bev.permute(0, 2, 3, 1))
        pe = sinusoidal_pos_encoding_2d(H, W, self.dim, x.device).to(x.dtype).reshape(1, H, W, self.dim)
        cam = cam_bev.permute(0, 2, 3, 1)
        return x, x + pe, self.k_proj(cam), self.v_proj(cam)

    def forward(self, lidar_bev: Tensor, cam_bev: Tensor) -> Tensor:
        """lidar_bev (B, Cl, H, W), cam_bev (B, Cc, H, W) -> fused (B, dim, H, W)."""
        x, q, k, v = self._qkv(lidar_bev, cam_bev)
        y = self.norm1(x + self.out_proj(self.attn(q, k, v)))
        y = self.norm2(y + self.ffn(y))
        return y.permute(0, 3, 1, 2).contiguous()

    def attention_map(self, lidar_bev: Tensor, cam_bev: Tensor, cell: tuple[int, int]) -> Tensor:
        """Weights of lidar query ``cell`` (row, col) over the camera BEV: (B, heads, H, W)."""
        _, q, k, _ = self._qkv(lidar_bev, cam_bev)
        return self.attn.query_attention_map(q, k, cell)


class BSM(nn.Module):
    """BEV self-attention over the fused BEV, for global context.

    ``q = Wq (x + PE)``, ``k = Wk (x + PE)``, ``v = Wv x``; ``y = LN(x + Wo attn(q, k, v))``;
    ``out = LN(y + FFN(y))``. The positional encoding goes on q and k (DETR style) so that the
    weights can depend on relative position, while the values carry only content.

    Parameters
    ----------
    ch : channels in and out, divisible by ``heads`` and by 4.
    heads, mode, window, pool_stride, ffn_ratio, query_chunk : as in :class:`MCM`.
    """

    def __init__(
        self,
        ch: int,
        heads: int = 8,
        mode: str = "window",
        window: int = 8,
        pool_stride: int = 4,
        ffn_ratio: float = 2.0,
        query_chunk: int | None = None,
    ) -> None:
        super().__init__()
        if ch % heads or ch % 4:
            raise ValueError(f"BSM ch {ch} must be divisible by heads {heads} and by 4")
        self.ch = ch
        self.q_proj = nn.Linear(ch, ch)
        self.k_proj = nn.Linear(ch, ch)
        self.v_proj = nn.Linear(ch, ch)
        self.attn = BEVAttention(heads, mode, window, pool_stride, query_chunk)
        self.out_proj = nn.Linear(ch, ch)
        self.norm1 = nn.LayerNorm(ch)
        self.ffn = _ffn(ch, ffn_ratio)
        self.norm2 = nn.LayerNorm(ch)

    def _qkv(self, bev: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """Channel-last x, q, k, v: each (B, H, W, ch)."""
        if bev.dim() != 4 or bev.shape[1] != self.ch:
            raise ValueError(f"BSM: need (B, {self.ch}, H, W), got {tuple(bev.shape)}")
        _, _, H, W = bev.shape
        x = bev.permute(0, 2, 3, 1)
        pe = sinusoidal_pos_encoding_2d(H, W, self.ch, x.device).to(x.dtype).reshape(1, H, W, self.ch)
        return x, self.q_proj(x + pe), self.k_proj(x + pe), self.v_proj(x)

    def forward(self, bev: Tensor) -> Tensor:
        """bev (B, C, H, W) -> (B, C, H, W)."""
        x, q, k, v = self._qkv(bev)
        y = self.norm1(x + self.out_proj(self.attn(q, k, v)))
        y = self.norm2(y + self.ffn(y))
        return y.permute(0, 3, 1, 2).contiguous()

    def attention_map(self, bev: Tensor, cell: tuple[int, int]) -> Tensor:
        """Weights of query ``cell`` (row, col) over the BEV: (B, heads, H, W)."""
        _, q, k, _ = self._qkv(bev)
        return self.attn.query_attention_map(q, k, cell)
