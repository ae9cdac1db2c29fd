"""CL-FusionBEV: lidar BEV + camera BEV -> MCM -> fusion -> BSM -> BEV backbone -> anchor head.

Variants (the paper's ablation ladder, each one adds one part to the previous):

- ``lidar``  : lidar BEV -> backbone -> head (the camera encoder is not even built);
- ``camera`` : camera BEV -> backbone -> head (the lidar encoder is not built);
- ``concat`` : ConvFuser(lidar BEV, camera BEV), the BEVFusion-style baseline;
- ``mcm``    : the concat baseline with MCM in front of it;
- ``full``   : mcm + BSM on the fused BEV.

How MCM and the concat combine (``mcm``): the paper's MCM takes its queries from the lidar BEV
(``q = W1 F_lidar + PE``) and its keys and values from the camera BEV, and "updates the BEV
queries". So MCM is applied exactly so, ``F_lidar' = MCM(q = F_lidar, k = v = F_cam)`` (a
pre-norm transformer layer whose residual path carries the lidar features), and the updated
lidar BEV replaces the lidar BEV in the baseline's fuser: ``ConvFuser(F_lidar', F_cam)``. The
``mcm`` variant thus differs from ``concat`` by the MCM step alone (what the ablation measures),
and the query is never anything but the lidar BEV, as the paper says. Applying MCM to the
ConvFuser output instead would make the queries partly camera features.

At initialisation the fused variants are their lidar path exactly (see :mod:`clfbev.fusion`),
and the camera branch learns depth from the lidar from the first step
(:mod:`clfbev.supervision.depth`).

The forward returns :class:`clfbev.outputs.ModelOutputs`; the training targets are built with
the batch in the loader and the loss is taken outside the model (:mod:`clfbev.supervision`).

An absent sensor (modality dropout in training, a crashed sensor at evaluation): nothing is
lifted from a camera that delivered nothing (``Batch.camera_missing``), and a sample without any
camera gets an all-zero camera BEV (:func:`camera_absent`); one without its lidar has no points,
which the lidar encoder turns into an all-zero lidar BEV.

Frames: everything is in the key-frame lidar frame; BEV maps are (B, C, ny, nx) with rows along
y and columns along x over ``cfg.pc_range``. Predictions are boxes in that frame.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor, nn

from clfbev.anchors import make_anchors
from clfbev.camera_aux import CameraAuxOutputs, CameraBEVHeads
from clfbev.camera_encoder import CameraEncoder
from clfbev.config import VARIANTS, ModelConfig
from clfbev.data import Batch
from clfbev.fusion import BSM, MCM, ConvFuser
from clfbev.head import AnchorHead, Detections, decode
from clfbev.layers import BN_EPS, BN_MOMENTUM, conv_bn_relu
from clfbev.lidar_encoder import LidarEncoder
from clfbev.outputs import AttentionInputs, ModelOutputs


class Encoded(NamedTuple):
    """What :meth:`CLFusionBEV._encode` gives the backbone and the losses.

    bev : (B, cfg.bev_channels_of(variant), ny, nx) the backbone's input, lidar frame.
    depth : (B, N, D, h, w) the camera's depth distribution, None without a camera.
    semantics : (B, N, n_classes, h, w) the perspective head's logits, None without one.
    motion : (B, sweep_channels, ny, nx) the lidar's motion features for the velocity tower, None
        without a tower (or without sweep bands).
    attention : the attention modules' inputs.
    camera : (B, cam_bev_channels, ny, nx) the camera BEV (what the fusion or the backbone
        reads of the camera), None without a camera: the auxiliary heads' input.
    """

    bev: Tensor
    depth: Tensor | None
    semantics: Tensor | None
    motion: Tensor | None
    attention: AttentionInputs
    camera: Tensor | None = None


class BEVBackbone(nn.Module):
    """SECOND-style 2D BEV backbone with an FPN-like neck.

    Stage 0 keeps the resolution, each later stage first halves it (3x3 conv, stride 2); every
    stage has ``blocks`` conv-BN-ReLU layers. Each stage output is brought back to stride 1
    (1x1 conv at stage 0, transposed conv otherwise) with ``up_ch`` channels, and the results
    are concatenated: small objects keep the full-resolution detail, large ones get the wider
    receptive field of the coarse stage.

    Parameters
    ----------
    in_ch : channels of the input BEV.
    channels : channels per stage; stage i > 0 works at stride 2^i.
    blocks : conv layers per stage (>= 1).
    up_ch : channels of each upsampled stage output.
    """

    def __init__(self, in_ch: int, channels: tuple[int, ...], blocks: int, up_ch: int) -> None:
        super().__init__()
        self.stages = nn.ModuleList()
        self.ups = nn.ModuleList()
        c = in_ch
        for i, out in enumerate(channels):
            layers = conv_bn_relu(c, out, stride=1 if i == 0 else 2)
            for _ in range(blocks - 1):
                layers += conv_bn_relu(out, out)
            self.stages.append(nn.Sequential(*layers))
            s = 2**i
            up = nn.Conv2d(out, up_ch, 1, bias=False) if s == 1 else nn.ConvTranspose2d(out, up_ch, s, s, bias=False)
            self.ups.append(nn.Sequential(up, nn.BatchNorm2d(up_ch, eps=BN_EPS, momentum=BN_MOMENTUM), nn.ReLU(True)))
            c = out
        self.out_channels = len(channels) * up_ch
        self.to(memory_format=torch.channels_last)   # faster convolutions (see CameraEncoder)

    def forward(self, bev: Tensor) -> Tensor:
        """bev (B, in_ch, H, W) -> (B, out_channels, H, W)."""
        H, W = bev.shape[2:]
        outs, x = [], bev.contiguous(memory_format=torch.channels_last)
        for stage, up in zip(self.stages, self.ups):
            x = stage(x)
            # A stride-2 conv rounds odd sizes up, so the upsampled map may be 1 cell too big.
            outs.append(up(x)[:, :, :H, :W])
        return torch.cat(outs, dim=1)


class CLFusionBEV(nn.Module):
    """The detector. Built explicitly from ``cfg`` for one ``variant`` (see the module docstring).

    Parameters
    ----------
    cfg : :class:`clfbev.config.ModelConfig`.
    variant : 'lidar', 'camera', 'concat', 'mcm' or 'full'.
    """

    def __init__(self, cfg: ModelConfig, variant: str = "full") -> None:
        super().__init__()
        if variant not in VARIANTS:
            raise ValueError(f"variant must be one of {VARIANTS}, got {variant!r}")
        self.cfg, self.variant = cfg, variant
        uses_lidar, uses_camera = variant != "camera", variant != "lidar"

        # Encoders: a modality the variant does not use is not built, hence never run.
        self.lidar_encoder: LidarEncoder | None = None
        self.camera_encoder: CameraEncoder | None = None
        if uses_lidar:
            self.lidar_encoder = LidarEncoder(
                cfg.point_ch, cfg.vfe_ch, cfg.sparse_channels, cfg.pc_range, cfg.voxel_size,
                cfg.max_voxels, cfg.sparse_blocks, xy_stride=cfg.lidar_bev_stride,
                time_lag_span=cfg.time_lag_span, sweep_bands=cfg.sweep_bands,
                sweep_offsets=cfg.sweep_offsets, trail_min_z=cfg.sweep_trail_min_z if cfg.sweep_trail else None,
                trail_in_bev=cfg.sweep_trail_in_bev,
            )
        if uses_camera:
            self.camera_encoder = CameraEncoder.from_config(cfg)

        # Fusion.
        attn = dict(heads=cfg.attn_heads, mode=cfg.attn_mode, window=cfg.attn_window,
                    pool_stride=cfg.attn_pool_stride, ffn_ratio=cfg.attn_ffn_ratio,
                    query_chunk=cfg.attn_query_chunk)
        self.mcm: MCM | None = None
        self.fuser: ConvFuser | None = None
        self.bsm: BSM | None = None
        if variant in ("mcm", "full"):
            self.mcm = MCM(cfg.lidar_bev_channels, cfg.cam_bev_channels, cfg.fusion_dim, **attn)
        if variant in ("concat", "mcm", "full"):
            lidar_ch = cfg.fusion_dim if self.mcm is not None else cfg.lidar_bev_channels
            self.fuser = ConvFuser(lidar_ch, cfg.cam_bev_channels, cfg.fusion_dim)
        if variant == "full":
            self.bsm = BSM(cfg.fusion_dim, **attn)

        # BEV backbone and head; the velocity tower also reads the lidar's motion features.
        self.backbone = BEVBackbone(cfg.bev_channels_of(variant), cfg.bev_channels, cfg.bev_blocks, cfg.bev_up_ch)
        self.motion_ch = cfg.sweep_channels if uses_lidar and cfg.velocity_tower else 0
        self.head = AnchorHead(self.backbone.out_channels, len(cfg.class_names), len(cfg.anchor_rotations),
                               cfg.code_size, cfg.n_dir_bins, cfg.prior_prob, cfg.velocity_tower, self.motion_ch,
                               cfg.velocity_detach, cfg.velocity_gate, still_head=cfg.loss.attribute > 0)
        # For decoding; the training targets take theirs from the config (clfbev.supervision.targets).
        anchors = make_anchors(cfg.class_names, cfg.head_feature_size, cfg.pc_range, cfg.anchor_rotations)
        self.register_buffer("anchors", anchors, persistent=False)  # (ny, nx, n_cls, n_rot, 7)
        # The camera BEV's auxiliary heads, for training (clfbev.camera_aux); None unless asked
        # for. Built last, so every other module's seeded start is the same with them or without.
        self.camera_aux = CameraBEVHeads.from_config(cfg) if uses_camera else None

    # ------------------------------------------------------------------ forward

    def bev_features(self, batch: Batch) -> Tensor:
        """The BEV map the backbone sees, (B, cfg.bev_channels_of(variant), ny, nx), lidar frame."""
        return self._encode(batch).bev

    def _encode(self, batch: Batch) -> Encoded:
        """The BEV map and what the losses, the velocity tower and the attention picture read
        beside it (:class:`Encoded`)."""
        lidar = cam_bev = depth = semantics = motion = None
        if self.lidar_encoder is not None:
            lidar = self.lidar_encoder.encode(batch.points)                   # (B, Cl, ny, nx)
            if self.motion_ch:
                motion = lidar.motion                                      # (B, sweep_channels, ny, nx)
        if self.camera_encoder is not None:
            cam_bev, depth, semantics = self.camera_encoder.lift_splat(batch.images, batch.intrinsics,
                                                                       batch.T_lidar_from_cam, batch.img_aug,
                                                                       self._oracle_bins(batch), batch.image_features,
                                                                       batch.camera_missing)
            cam_bev = camera_absent(cam_bev, None if batch.camera_missing is None else batch.camera_missing.all(1))
        if self.variant == "lidar":
            return Encoded(lidar.bev, None, None, motion, AttentionInputs())
        if self.variant == "camera":
            return Encoded(cam_bev, depth, semantics, None, AttentionInputs(), cam_bev)
        fused, attention = self.fuse(lidar.bev, cam_bev)
        return Encoded(fused, depth, semantics, motion, attention, cam_bev)

    def _oracle_bins(self, batch: Batch) -> Tensor | None:
        """(B, N, h, w) the key-frame lidar's depth bin per camera cell (-1: none) with
        ``cfg.cam_oracle_depth``, else None: ``batch.depth_bins``, projected in the loader (the
        depth loss's targets where it trains)."""
        if not self.cfg.cam_oracle_depth:
            return None
        if batch.depth_bins is None:
            raise ValueError("cam_oracle_depth lifts with Batch.depth_bins, which this batch lacks: collate it "
                             "with the model's config (clfbev.data.collate(samples, cfg)) or TrainingCollate")
        return batch.depth_bins

    def fuse(self, lidar_bev: Tensor, cam_bev: Tensor) -> tuple[Tensor, AttentionInputs]:
        """MCM -> ConvFuser -> BSM, as the variant has them: (B, Cl, ny, nx), (B, Cc, ny, nx) ->
        (B, fusion_dim, ny, nx), and the inputs the attention modules were given."""
        attention = AttentionInputs()
        if self.mcm is not None:
            # MCM: lidar BEV queries attend to the camera BEV and are updated by it.
            attention = attention._replace(mcm_lidar=lidar_bev, mcm_camera=cam_bev)
            lidar_bev = self.mcm(lidar_bev, cam_bev)                          # (B, dim, ny, nx)
        fused = self.fuser(lidar_bev, cam_bev)                                # (B, dim, ny, nx)
        if self.bsm is not None:
            # BSM: self-attention over the fused BEV for global context.
            attention = attention._replace(bsm=fused)
            fused = self.bsm(fused)
        return fused, attention

    def forward(self, batch: Batch) -> ModelOutputs:
        """Batch -> :class:`clfbev.outputs.ModelOutputs`: the head maps on the BEV grid, the
        camera's depth distribution and class logits, and the attention modules' inputs."""
        enc = self._encode(batch)
        head = self.head(self.backbone(enc.bev), enc.motion)
        aux = self.camera_aux(enc.camera) if self.camera_aux is not None and self.training else CameraAuxOutputs()
        return ModelOutputs(head, enc.depth, enc.semantics, enc.attention, aux.heatmap, aux.distill)

    # ------------------------------------------------------------------ training and inference

    @torch.no_grad()
    def predict(
        self,
        batch: Batch,
        score_thr: float | None = None,
        nms_iou: float | None = None,
        max_per_sample: int | None = None,
    ) -> list[Detections]:
        """B Detections with boxes (K, code_size) ``x, y, z, l, w, h, yaw, vx, vy`` in the lidar
        frame, scores (K,), labels (K,). Defaults from ``cfg``. The caller picks train/eval mode
        (use ``model.eval()`` for BatchNorm running statistics)."""
        cfg = self.cfg
        out = self(batch).head
        return decode(
            out.cls_logits, out.box_deltas, out.dir_logits, self.anchors,
            score_thr=cfg.score_thr if score_thr is None else score_thr,
            nms_iou=cfg.nms_iou if nms_iou is None else nms_iou,
            max_per_sample=cfg.max_per_sample if max_per_sample is None else max_per_sample,
            pre_nms=cfg.pre_nms, heading_speed=cfg.heading_from_motion, moving_logits=out.moving_logits,
            heading_follow=tuple(cfg.class_names.index(c) for c in cfg.heading_follow_classes),
            still_logits=out.still_logits,
        )


def camera_absent(cam_bev: Tensor, dropped: Tensor | None) -> Tensor:
    """The camera BEV (B, C, ny, nx) with the samples whose cameras are all absent, ``dropped``
    (B,) bool (None: none), set to exactly 0: what the model takes a missing camera
    to give, as a missing lidar gives no points and so an all-zero lidar BEV. No gradient
    reaches the camera encoder through a dropped sample's BEV."""
    if dropped is None:
        return cam_bev
    return torch.where(dropped.view(-1, 1, 1, 1), torch.zeros((), dtype=cam_bev.dtype, device=cam_bev.device), cam_bev)


def count_parameters(module: nn.Module) -> int:
    """Number of trainable parameters."""
    return sum(p.numel() for p in module.parameters() if p.requires_grad)
