"""Camera + lidar BEV fusion: the concat baseline, MCM (cross-attention) and BSM (self-attention).

All modules take and return channel-first BEV maps ``(B, C, H, W)`` on one shared grid, so
they drop in between the encoders and the head. Inside, the attention blocks work per cell,
channel-last, because the projections, LayerNorm and FFN act on each cell's channels.

Paper (CL-FusionBEV):
    MCM: q = W1 F_lidar + PE, k = W2 F_cam, v = W3 F_cam, softmax(q k^T / sqrt(d)) v
    BSM: q, k, v from the fused BEV, softmax(q k^T / sqrt(d)) v for global context.
Both are wrapped as pre-norm residual transformer layers (``x + Wo attn(LN(x))``, then
``x + FFN(LN(x))``) whose output projection ``Wo`` and last FFN layer start at zero, and the
ConvFuser's camera weights start at zero too. So at initialisation every fused model is its
lidar path exactly: MCM and BSM pass their input through, the fuser sees only the lidar BEV, and
camera features enter only as fast as training opens these gates. A post-norm layer instead
re-normalises every BEV cell to RMS 1 at the start, the ~80% of cells without a lidar point
included: the empty / occupied contrast the detector lives on is gone, and untrained camera
features reach the backbone at full scale (the fused models then start, and end, below
lidar-only). Pre-norm is also the stable form of the transformer layer (Xiong et al. 2020).
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from clfbev.attention import BEVAttention, sinusoidal_pos_encoding_2d

# Initial RMS of the positional encoding added to the (layer-normalised, RMS 1) query content:
# enough for the weights to depend on relative position, never more than the content.
PE_INIT_RMS = 0.5


def _check_grid(a: Tensor, b: Tensor, names: str) -> None:
    if a.dim() != 4 or b.dim() != 4 or a.shape[0] != b.shape[0] or a.shape[2:] != b.shape[2:]:
        raise ValueError(
            f"{names}: need (B, C, H, W) maps on one grid, got {tuple(a.shape)} and {tuple(b.shape)}"
        )


def _ffn(dim: int, ffn_ratio: float) -> nn.Sequential:
    """Linear -> GELU -> Linear, the last layer zero: the residual branch starts as 0."""
    hidden = max(1, int(round(dim * ffn_ratio)))
    ffn = nn.Sequential(nn.Linear(dim, hidden), nn.GELU(), nn.Linear(hidden, dim))
    nn.init.zeros_(ffn[2].weight)
    nn.init.zeros_(ffn[2].bias)
    return ffn


def _zero_linear(dim_in: int, dim_out: int) -> nn.Linear:
    layer = nn.Linear(dim_in, dim_out)
    nn.init.zeros_(layer.weight)
    nn.init.zeros_(layer.bias)
    return layer


class _PosEncoding(nn.Module):
    """The fixed 2D sine encoding of :func:`sinusoidal_pos_encoding_2d` times a learned gain,
    channel-last: ``forward(H, W, like) -> (1, H, W, dim)``. The gain starts so that the
    encoding's RMS is :data:`PE_INIT_RMS` (the raw encoding's RMS is 1 / sqrt(2))."""

    def __init__(self, dim: int) -> None:
        super().__init__()
        self.dim = dim
        self.gain = nn.Parameter(torch.tensor(PE_INIT_RMS * 2**0.5))

    def forward(self, H: int, W: int, like: Tensor) -> Tensor:
        pe = sinusoidal_pos_encoding_2d(H, W, self.dim, like.device).to(like.dtype)
        return (self.gain * pe).reshape(1, H, W, self.dim)


class ConvFuser(nn.Module):
    """BEVFusion-style baseline: concat along channels -> 3x3 conv -> BN -> ReLU.

    The conv over the concatenation is written as the sum of a conv over each input (the same
    operator), so that the camera half of its weights can start at exactly zero: the fused BEV
    is then ``ReLU(BN(conv(F_lidar)))`` at initialisation, whatever the camera BEV holds.

    Parameters
    ----------
    lidar_ch, cam_ch : input channels of the lidar and camera BEV.
    out_ch : output channels.
    """

    def __init__(self, lidar_ch: int, cam_ch: int, out_ch: int) -> None:
        super().__init__()
        # No conv bias: BN's shift makes it redundant.
        self.conv_lidar = nn.Conv2d(lidar_ch, out_ch, 3, padding=1, bias=False)
        self.conv_cam = nn.Conv2d(cam_ch, out_ch, 3, padding=1, bias=False)
        nn.init.zeros_(self.conv_cam.weight)
        self.bn = nn.BatchNorm2d(out_ch)
        self.act = nn.ReLU(inplace=True)

    def forward(self, lidar_bev: Tensor, cam_bev: Tensor) -> Tensor:
        """lidar_bev (B, Cl, H, W), cam_bev (B, Cc, H, W) -> (B, out_ch, H, W)."""
        _check_grid(lidar_bev, cam_bev, "ConvFuser")
        return self.act(self.bn(self.conv_lidar(lidar_bev) + self.conv_cam(cam_bev)))


class MCM(nn.Module):
    """Multimodal cross-attention: lidar BEV queries attend to the camera BEV.

    ``x = W1 F_lidar`` (the residual stream; W1 starts as the identity on the first ``dim``
    channels when there are at least as many, and 0 on the rest: ``tiny``'s sweep bands follow
    its 64 sparse channels); ``q = LN(x) + PE``; ``k = Wk LN(F_cam)``, ``v = Wv LN(F_cam)`` (no
    positional encoding on k/v, as in the paper); ``y = x + Wo attn(q, k, v)``; ``out = y + FFN(LN(y))``.
    ``Wo`` and the FFN's last layer start at zero, so at initialisation ``out = x``.

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
        if lidar_ch >= dim:
            nn.init.eye_(self.q_proj.weight)
            nn.init.zeros_(self.q_proj.bias)
        self.pos = _PosEncoding(dim)
        self.norm_q = nn.LayerNorm(dim)
        self.norm_cam = nn.LayerNorm(cam_ch)
        self.k_proj = nn.Linear(cam_ch, dim)  # W2 (keys)
        self.v_proj = nn.Linear(cam_ch, dim)  # W2 (values)
        self.attn = BEVAttention(heads, mode, window, pool_stride, query_chunk)
        self.out_proj = _zero_linear(dim, dim)
        self.norm_ffn = nn.LayerNorm(dim)
        self.ffn = _ffn(dim, ffn_ratio)

    def _qkv(self, lidar_bev: Tensor, cam_bev: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """Channel-last x = W1 F_lidar, q = LN(x) + PE, k, v: each (B, H, W, dim)."""
        _check_grid(lidar_bev, cam_bev, "MCM")
        _, _, H, W = lidar_bev.shape
        x = self.q_proj(lidar_bev.permute(0, 2, 3, 1))
        cam = self.norm_cam(cam_bev.permute(0, 2, 3, 1))
        return x, self.norm_q(x) + self.pos(H, W, x), self.k_proj(cam), self.v_proj(cam)

    def forward(self, lidar_bev: Tensor, cam_bev: Tensor) -> Tensor:
        """lidar_bev (B, Cl, H, W), cam_bev (B, Cc, H, W) -> fused (B, dim, H, W)."""
        x, q, k, v = self._qkv(lidar_bev, cam_bev)
        y = x + self.out_proj(self.attn(q, k, v))
        y = y + self.ffn(self.norm_ffn(y))
        return y.permute(0, 3, 1, 2).contiguous()

    def attention_map(self, lidar_bev: Tensor, cam_bev: Tensor, cell: tuple[int, int]) -> Tensor:
        """Weights of lidar query ``cell`` (row, col) over the camera BEV: (B, heads, H, W)."""
        _, q, k, _ = self._qkv(lidar_bev, cam_bev)
        return self.attn.query_attention_map(q, k, cell)


class BSM(nn.Module):
    """BEV self-attention over the fused BEV, for global context.

    ``h = LN(x)``; ``q = Wq (h + PE)``, ``k = Wk (h + PE)``, ``v = Wv h``;
    ``y = x + Wo attn(q, k, v)``; ``out = y + FFN(LN(y))``. The positional encoding goes on q
    and k (DETR style) so that the weights can depend on relative position, while the values
    carry only content. ``Wo`` and the FFN's last layer start at zero: ``out = x`` at first.

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
        self.norm = nn.LayerNorm(ch)
        self.pos = _PosEncoding(ch)
        self.q_proj = nn.Linear(ch, ch)
        self.k_proj = nn.Linear(ch, ch)
        self.v_proj = nn.Linear(ch, ch)
        self.attn = BEVAttention(heads, mode, window, pool_stride, query_chunk)
        self.out_proj = _zero_linear(ch, ch)
        self.norm_ffn = nn.LayerNorm(ch)
        self.ffn = _ffn(ch, ffn_ratio)

    def _qkv(self, bev: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """Channel-last x, q, k, v: each (B, H, W, ch)."""
        if bev.dim() != 4 or bev.shape[1] != self.ch:
            raise ValueError(f"BSM: need (B, {self.ch}, H, W), got {tuple(bev.shape)}")
        _, _, H, W = bev.shape
        x = bev.permute(0, 2, 3, 1)
        h = self.norm(x)
        hp = h + self.pos(H, W, x)
        return x, self.q_proj(hp), self.k_proj(hp), self.v_proj(h)

    def forward(self, bev: Tensor) -> Tensor:
        """bev (B, C, H, W) -> (B, C, H, W)."""
        x, q, k, v = self._qkv(bev)
        y = x + self.out_proj(self.attn(q, k, v))
        y = y + self.ffn(self.norm_ffn(y))
        return y.permute(0, 3, 1, 2).contiguous()

    def attention_map(self, bev: Tensor, cell: tuple[int, int]) -> Tensor:
        """Weights of query ``cell`` (row, col) over the BEV: (B, heads, H, W)."""
        _, q, k, _ = self._qkv(bev)
        return self.attn.query_attention_map(q, k, cell)
