"""One frozen config for the CL-FusionBEV model (nanoGPT style) and its presets.

Only independent choices are fields. Every size that follows from them (voxel grid, lidar and
camera BEV shapes and channels, anchors per cell) is a property computed from the fields by the
arithmetic of the encoders' convolutions (:func:`sparse_out_grid`), so it is never typed twice;
the tests build the modules and check that they agree.

A leaf of the package: it imports only :mod:`clfbev.settings` and :mod:`clfbev.errors`.

The camera BEV voxel is derived too: its x/y size is chosen so that the camera BEV has exactly
the (ny, nx) of the lidar BEV (the fusion concatenates them cell by cell), and it spans the
whole z range in ``cam_z_slabs`` slabs.

Presets are plain functions: :func:`tiny` (a 2-core CPU) and :func:`paper` (the paper's sizes).
:func:`clfbev.config_file.load_config` takes a preset name or a YAML file of overrides.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

from clfbev.errors import ConfigError
from clfbev.settings import (ANCHOR_ROTATIONS, ANCHOR_SIZES, ATTENTION_MODES, CAMERA_BACKBONES, DETECTION_CLASSES,
                             LIDAR_SWEEP_PERIOD_S, POINT_CH, TRAIL_WINDOWS, DataConfig, LossWeights, conv_out_size,
                             grid_shape_of)

VARIANTS = ("lidar", "camera", "concat", "mcm", "full")
CAMERA_LIFTS = ("splat", "bilinear")


@dataclass(frozen=True)
class ModelConfig:
    """Every choice that shapes a CL-FusionBEV model. Lengths in metres, lidar frame.

    Data: ``class_names`` (label order), ``pc_range`` (xmin, ymin, zmin, xmax, ymax, zmax),
    ``n_sweeps`` (lidar sweeps per sample, time-lag channel), ``image_size`` (H, W).
    Lidar: ``voxel_size`` (dx, dy, dz), ``max_voxels`` (per sample; dynamic voxelization keeps
    every point of a kept voxel), ``vfe_ch`` (VFE MLP width, 512 in the paper),
    ``sparse_channels`` (one entry per sparse stage; each stage after the first halves z),
    ``lidar_bev_stride`` (the x/y stride of the lidar BEV over the voxels: the first
    log2(stride) downsamplings also halve x and y), ``sparse_blocks``, ``sweep_bands`` (lag
    bands whose point counts per BEV cell join the lidar BEV, :mod:`clfbev.sweep_bev`; 0: none),
    ``sweep_offsets`` (each band's mean offset in its cell joins them too: a walker's sub-cell trail),
    ``sweep_trail`` (each cell's least-squares velocity of its points above ``sweep_trail_min_z``,
    m in the lidar frame, over the cell and its 3x3 neighbourhood joins them too,
    :func:`clfbev.sweep_bev.sweep_trails`), ``sweep_trail_in_bev`` (False: only the velocity
    tower reads the trails, not the backbone).
    Camera: ``cam_backbone`` (``resnet``, or ``efficientnet_lite0`` for the ImageNet experiment,
    :mod:`clfbev.efficientnet_lite`), ``cam_depth`` / ``cam_width`` (ResNet), ``fpn_ch``,
    ``context_ch``, ``depth_bins`` (d_min, d_max, d_step of camera z), ``feature_stride`` (8 or 16), ``cam_z_slabs``,
    ``cam_semantic_lift`` (lift the perspective head's class probabilities with the context, so
    the camera BEV carries them; needs ``loss.semantic > 0``, see :mod:`clfbev.supervision.perspective`),
    ``cam_oracle_depth`` (a diagnostic, never a recipe: lift every camera cell that a key-frame
    lidar point reaches with that point's depth bin in place of the predicted distribution,
    :func:`clfbev.camera_encoder.oracle_depth`, in training and evaluation alike),
    ``cam_lift`` (``splat``: lift-splat's depth bins; ``bilinear``: every BEV cell samples the
    image features where its column of points at the heights ``cam_lift_heights`` (lidar z, m; at
    least one in each z slab) projects, Simple-BEV, :mod:`clfbev.bilinear_lift`),
    ``cam_heatmap`` (>= 0, the weight of an auxiliary class-centre heatmap head on the camera BEV,
    CenterPoint's Gaussians and CenterNet's focal loss; 0: no head, :mod:`clfbev.camera_aux`),
    ``cam_distill`` (>= 0, the weight of the distillation of a frozen lidar teacher's BEV
    features into the camera BEV through a 1x1 adapter; 0: none) and ``cam_distill_teacher``
    (that teacher: a training checkpoint with a lidar detector of this config,
    :mod:`clfbev.supervision.distill`).
    Fusion: ``fusion_dim`` (ConvFuser / MCM / BSM channels), ``attn_heads``, ``attn_mode``
    (exact | window | pooled), ``attn_window``, ``attn_pool_stride``, ``attn_query_chunk``,
    ``attn_ffn_ratio``.
    BEV backbone: ``bev_channels`` (per stage; stage i > 0 has stride 2), ``bev_blocks`` (3x3
    convs per stage), ``bev_up_ch`` (channels of each stage after upsampling to stride 1).
    Head / decoding: ``anchor_rotations``, ``code_size``, ``n_dir_bins``, ``prior_prob``,
    ``velocity_tower`` (0: the velocity is two of the head's 1x1 residuals; else the width of
    the :class:`clfbev.head.VelocityTower` that predicts it from the BEV and the sweep bands),
    ``velocity_detach`` (the tower's gradient stops at the shared BEV features),
    ``velocity_gate`` (the tower also classifies each box as moving or still; the speed is
    regressed on the moving boxes only, or with ``velocity_balance`` on all of them balanced, and
    decoded only where the gate fires,
    :func:`clfbev.supervision.losses.gated_velocity_loss`; needs ``velocity_tower``),
    ``heading_from_motion`` (m/s, >= 0: decoding turns a box's yaw by pi where it points against
    its predicted velocity and the predicted speed is above this; 0: off),
    ``heading_follow_classes`` (class names whose yaw is instead set to the predicted velocity's
    direction above that speed: a walker's near-square footprint shows no axis), ``score_thr``,
    ``nms_iou``, ``max_per_sample``, ``pre_nms``.
    Loss: ``loss``; ``velocity_balance`` (the velocity residuals leave the shared box loss for
    their own, in which the moving and the still positives weigh the same in total,
    :func:`clfbev.supervision.losses.velocity_loss`), ``velocity_beta`` (its Smooth-L1 beta in
    m/s, >= 0) and ``velocity_weight`` (its weight beside ``loss.reg``, >= 0);
    ``min_positives`` (1-4: each GT also trains the anchors of its class nearest its centre up
    to this many, :func:`clfbev.supervision.assign.assign_targets`; 1: SECOND's matching).
    """

    class_names: tuple[str, ...] = DETECTION_CLASSES
    pc_range: tuple[float, ...] = (-51.2, -51.2, -5.0, 51.2, 51.2, 3.0)
    n_sweeps: int = 3
    image_size: tuple[int, int] = (192, 352)
    # lidar
    voxel_size: tuple[float, float, float] = (0.4, 0.4, 0.4)
    max_voxels: int = 60000
    vfe_ch: int = 32
    sparse_channels: tuple[int, ...] = (8, 16, 32)
    lidar_bev_stride: int = 2
    sparse_blocks: int = 1
    sweep_bands: int = 0
    sweep_offsets: bool = False
    sweep_trail: bool = False
    sweep_trail_min_z: float = -1.4      # 0.44 m above the road under a lidar 1.84 m up (the rig's)
    sweep_trail_in_bev: bool = True
    # camera
    cam_backbone: str = "resnet"
    cam_depth: int = 18
    cam_width: int = 16
    fpn_ch: int = 64
    context_ch: int = 32
    depth_bins: tuple[float, float, float] = (1.0, 52.0, 1.0)
    feature_stride: int = 8
    cam_z_slabs: int = 1
    cam_semantic_lift: bool = False
    cam_oracle_depth: bool = False
    cam_lift: str = "splat"
    cam_lift_heights: tuple[float, ...] = (-1.4, -0.6)  # 0.44 and 1.24 m above the road (the rig's lidar 1.84 m up)
    cam_heatmap: float = 0.0
    cam_distill: float = 0.0
    cam_distill_teacher: str = ""
    # fusion
    fusion_dim: int = 64
    attn_heads: int = 4
    attn_mode: str = "window"
    attn_window: int = 8
    attn_pool_stride: int = 4
    attn_query_chunk: int | None = None
    attn_ffn_ratio: float = 2.0
    # BEV backbone
    bev_channels: tuple[int, ...] = (32, 64)
    bev_blocks: int = 2
    bev_up_ch: int = 32
    # head and decoding
    anchor_rotations: tuple[float, ...] = ANCHOR_ROTATIONS
    code_size: int = 9
    n_dir_bins: int = 2
    prior_prob: float = 0.01
    velocity_tower: int = 0
    velocity_detach: bool = False
    velocity_gate: bool = False
    heading_from_motion: float = 0.0
    heading_follow_classes: tuple[str, ...] = ()
    score_thr: float = 0.1
    nms_iou: float = 0.2
    max_per_sample: int = 500
    pre_nms: int = 1000
    loss: LossWeights = field(default_factory=LossWeights)
    velocity_balance: bool = False
    velocity_beta: float = 1.0
    velocity_weight: float = 0.2
    min_positives: int = 1

    def __post_init__(self) -> None:
        # Cheap checks with a clear message; the modules check the rest when they are built.
        unknown = [c for c in self.class_names if c not in ANCHOR_SIZES]
        if not self.class_names or unknown:
            raise ConfigError(f"class_names {unknown or '()'} have no anchors; known: {sorted(ANCHOR_SIZES)}")
        if len(self.pc_range) != 6 or len(self.voxel_size) != 3 or len(self.image_size) != 2:
            raise ConfigError("pc_range needs 6 values, voxel_size 3 and image_size 2")
        if not all(lo < hi for lo, hi in zip(self.pc_range[:3], self.pc_range[3:])):
            raise ConfigError(f"pc_range {self.pc_range} must have min < max on every axis")
        positive = {"voxel_size": self.voxel_size, "image_size": self.image_size, "depth_bins": self.depth_bins,
                    "sparse_channels": self.sparse_channels, "bev_channels": self.bev_channels,
                    "n_sweeps": (self.n_sweeps,), "cam_z_slabs": (self.cam_z_slabs,)}
        for name, values in positive.items():
            if not all(v > 0 for v in values):
                raise ConfigError(f"{name} must be > 0, got {values}")
        non_negative = {"heading_from_motion": self.heading_from_motion, "velocity_beta": self.velocity_beta,
                        "velocity_weight": self.velocity_weight, "loss.depth_range_power": self.loss.depth_range_power,
                        "cam_heatmap": self.cam_heatmap, "cam_distill": self.cam_distill,
                        "loss.attribute": self.loss.attribute}
        for name, value in non_negative.items():
            if not value >= 0:
                raise ConfigError(f"{name} must be >= 0, got {value}")
        stray = [c for c in self.heading_follow_classes if c not in self.class_names]
        if stray:
            raise ConfigError(f"heading_follow_classes {stray} are not in class_names {list(self.class_names)}")
        if self.velocity_gate and not self.velocity_tower:
            raise ConfigError("velocity_gate needs velocity_tower > 0")
        if not 1 <= self.min_positives <= 4:
            raise ConfigError(f"min_positives must be in [1, 4], got {self.min_positives}")
        if self.cam_backbone not in CAMERA_BACKBONES:
            raise ConfigError(f"cam_backbone must be one of {CAMERA_BACKBONES}, got {self.cam_backbone!r}")
        if self.attn_mode not in ATTENTION_MODES:
            raise ConfigError(f"attn_mode must be one of {ATTENTION_MODES}, got {self.attn_mode!r}")
        if self.fusion_dim % self.attn_heads or self.fusion_dim % 4:
            raise ConfigError(f"fusion_dim {self.fusion_dim} must be divisible by attn_heads {self.attn_heads} and 4")
        if self.feature_stride not in (8, 16) or any(s % self.feature_stride for s in self.image_size):
            raise ConfigError(f"image_size {self.image_size} must be a multiple of feature_stride (8 or 16)")
        if (self.sweep_offsets or self.sweep_trail) and not self.sweep_bands > 0:
            raise ConfigError("sweep_offsets and sweep_trail need sweep_bands > 0 (they join the bands)")
        if self.sweep_trail and not self.sweep_trail_in_bev and not self.velocity_tower:
            raise ConfigError("sweep_trail_in_bev false needs a velocity_tower (nothing else would read the trails)")
        if self.cam_lift not in CAMERA_LIFTS:
            raise ConfigError(f"cam_lift must be one of {CAMERA_LIFTS}, got {self.cam_lift!r}")
        slab_of = [int((z - self.pc_range[2]) // self.cam_bev_voxel[2]) for z in self.cam_lift_heights]
        if self.cam_lift == "bilinear" and sorted(set(slab_of)) != list(range(self.cam_z_slabs)):
            raise ConfigError(f"cam_lift_heights {self.cam_lift_heights} must lie in pc_range's z [{self.pc_range[2]}, "
                              f"{self.pc_range[5]}) with at least one in each of the {self.cam_z_slabs} cam_z_slabs")
        if self.cam_oracle_depth and self.cam_lift != "splat":
            raise ConfigError("cam_oracle_depth replaces the splat's depth: it needs cam_lift 'splat'")
        if (self.cam_distill > 0) != bool(self.cam_distill_teacher):
            raise ConfigError("cam_distill > 0 and cam_distill_teacher (a lidar run's checkpoint) go together, "
                              f"got cam_distill {self.cam_distill} and cam_distill_teacher {self.cam_distill_teacher!r}")
        if self.cam_semantic_lift and not self.loss.semantic > 0:
            raise ConfigError("cam_semantic_lift needs the perspective head: set loss.semantic > 0")
        if len(self.loss.code_weights) < self.code_size:
            raise ConfigError(f"loss.code_weights needs {self.code_size} values")
        if min(self._sparse_grid) < 1:
            raise ConfigError(f"the voxel grid {self.lidar_grid_shape} is too small for {len(self.sparse_channels)} "
                              f"sparse stages (last grid {self._sparse_grid})")
        if self.cam_bev_shape != self.lidar_bev_shape:
            raise ConfigError(f"camera BEV {self.cam_bev_shape} != lidar BEV {self.lidar_bev_shape}")

    # ------------------------------------------------------------------ derived sizes

    @property
    def point_ch(self) -> int:
        return POINT_CH

    @property
    def time_lag_span(self) -> float:
        """Seconds, the time lag of the oldest of ``n_sweeps`` sweeps (the VFE's lag scale)."""
        return max(self.n_sweeps - 1, 1) * LIDAR_SWEEP_PERIOD_S

    @property
    def lidar_grid_shape(self) -> tuple[int, int, int]:
        """(nz, ny, nx) of the lidar voxel grid."""
        return grid_shape_of(self.pc_range, self.voxel_size)

    @property
    def _sparse_grid(self) -> tuple[int, int, int]:
        """(nz, ny, nx) of the sparse encoder's last grid."""
        return sparse_out_grid(self.lidar_grid_shape, len(self.sparse_channels), self.lidar_bev_stride)

    @property
    def lidar_bev_shape(self) -> tuple[int, int]:
        """(ny, nx) of the lidar BEV (after the sparse encoder's downsamplings)."""
        return self._sparse_grid[1:]

    @property
    def lidar_bev_channels(self) -> int:
        """Lidar BEV channels: last sparse stage channels x remaining z cells, and the sweep bands
        (their trails only with ``sweep_trail_in_bev``)."""
        trail_out = 0 if self.sweep_trail_in_bev else self.trail_channels
        return self.sparse_channels[-1] * self._sparse_grid[0] + self.sweep_channels - trail_out

    @property
    def sweep_channels(self) -> int:
        """The sweep bands' channels: a count per band, its x and y offsets with ``sweep_offsets``,
        and with ``sweep_trail`` the fitted ``vx, vy`` per trail window."""
        return self.sweep_bands * (3 if self.sweep_offsets else 1) + self.trail_channels

    @property
    def trail_channels(self) -> int:
        """With ``sweep_trail``, the fitted ``vx, vy`` per trail window; else 0."""
        return 2 * len(TRAIL_WINDOWS) if self.sweep_trail else 0

    @property
    def cam_bev_voxel(self) -> tuple[float, float, float]:
        """(dx, dy, dz) of the camera voxel grid: the lidar BEV's cells, z in cam_z_slabs slabs."""
        ny, nx = self.lidar_bev_shape
        xmin, ymin, zmin, xmax, ymax, zmax = self.pc_range
        return ((xmax - xmin) / nx, (ymax - ymin) / ny, (zmax - zmin) / self.cam_z_slabs)

    @property
    def cam_bev_shape(self) -> tuple[int, int]:
        """(ny, nx) of the camera BEV; equal to ``lidar_bev_shape`` by construction."""
        return grid_shape_of(self.pc_range, self.cam_bev_voxel)[1:]

    @property
    def cam_bev_channels(self) -> int:
        """Camera BEV channels: the lifted channels (context_ch, plus one per class with
        cam_semantic_lift) per z slab (CameraEncoder.out_channels)."""
        lifted = self.context_ch + (len(self.class_names) if self.cam_semantic_lift else 0)
        return lifted * grid_shape_of(self.pc_range, self.cam_bev_voxel)[0]

    @property
    def fused_channels(self) -> int:
        """Channels of the fused BEV of the concat / mcm / full variants."""
        return self.fusion_dim

    def bev_channels_of(self, variant: str) -> int:
        """Channels of the BEV map entering the 2D backbone for ``variant``."""
        if variant == "lidar":
            return self.lidar_bev_channels
        if variant == "camera":
            return self.cam_bev_channels
        if variant in VARIANTS:
            return self.fused_channels
        raise ConfigError(f"variant must be one of {VARIANTS}, got {variant!r}")

    @property
    def head_in_channels(self) -> int:
        """Backbone output: every stage upsampled to stride 1 with bev_up_ch, concatenated."""
        return len(self.bev_channels) * self.bev_up_ch

    @property
    def head_feature_size(self) -> tuple[int, int]:
        """(ny, nx) of the head maps and anchors: the BEV grid (the backbone keeps stride 1)."""
        return self.lidar_bev_shape

    @property
    def num_depth_bins(self) -> int:
        d_min, d_max, d_step = self.depth_bins
        return int(round((d_max - d_min) / d_step))

    def data_config(self) -> DataConfig:
        """The loader settings this model expects."""
        return DataConfig(class_names=self.class_names, image_size=self.image_size,
                          n_sweeps=self.n_sweeps, point_range=self.pc_range)

    def to_dict(self) -> dict:
        """Plain YAML/JSON-safe dict of the fields (tuples as lists); ``clfbev.config_file.config_from_dict`` reads it back."""
        return _plain(dataclasses.asdict(self))


def sparse_out_grid(grid_shape: tuple[int, int, int], n_stages: int, xy_stride: int) -> tuple[int, int, int]:
    """(nz, ny, nx) of the last grid of :class:`clfbev.lidar_encoder.SparseEncoder` with
    ``n_stages`` stages, the z_out conv and ``xy_stride``: each of the ``n_stages - 1``
    downsamplings is a k 3, stride 2, padding 1 conv along z, and along x and y too while the
    stride reached stays within ``xy_stride`` (else k 1, stride 1, padding 0 there); the z_out
    conv is k 3, stride 2, padding 0 along z."""
    nz, ny, nx = grid_shape
    for i in range(1, n_stages):
        nz = conv_out_size(nz, 3, 2, 1)
        if 2**i <= xy_stride:
            ny, nx = conv_out_size(ny, 3, 2, 1), conv_out_size(nx, 3, 2, 1)
    return conv_out_size(nz, 3, 2, 0), ny, nx


def _plain(x):
    if isinstance(x, dict):
        return {k: _plain(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_plain(v) for v in x]
    return x


# ---------------------------------------------------------------------- presets


def tiny() -> ModelConfig:
    """For a 2-core CPU (the measurements behind each choice: docs/benchmarks.md).

    - Grid: +-51.2 m, 0.4 m voxels -> 256 x 256 x 20; the second sparse downsampling halves z
      only, so the BEV is 128 x 128 (0.8 m cells, 64 channels), the grid on which anchor heads are
      known to work (SECOND / OpenPCDet use 0.8 m or finer).
    - Camera: ResNet-18 width 16 on 192 x 352 images (704 x 396 resized keeping the aspect, then
      cropped) at stride 8; 51 depth bins of 1 m from 1 m; the depth loss weighs each cell by its
      target depth squared (``loss.depth_range_power`` 2), so the far cells count.
    - Camera BEV: an auxiliary class-centre heatmap head (``cam_heatmap`` 1.0) supervises the
      camera's own BEV with every box's centre, so the camera learns where objects are from more
      than the anchors its few positives train.
    - Attention: 8 x 8 windows (exact attention over 16,384 cells would be the slowest part).
    - Lidar: 10 sweeps (0.45 s, as the nuScenes peers); per BEV cell the point counts of 5 lag
      bands with their mean offsets and each cell's fitted trail (``sweep_trail``: the
      least-squares velocity of its points above the road, over the cell and its 3 x 3
      neighbourhood) join the lidar BEV (:mod:`clfbev.sweep_bev`).
    - Head: the direction loss at 1.0 (the box regression's sin-difference is blind to a half
      turn); each GT trains at least its 4 nearest anchors of its class (``min_positives``).
    - Velocity: CenterPoint's separate regression, gated: a detached tower of width 16 on the BEV
      and the sweep features classifies each box as moving (above 0.5 m/s) or still and
      regresses its speed, moving and still positives balanced, Smooth-L1 with beta 0.1 m/s; a
      walker's heading is its predicted velocity's direction where it walks
      (``heading_follow_classes``), other boxes' yaw turns by pi where it points against a
      velocity above 0.5 m/s.
    - Attributes: a still logit per anchor (``loss.attribute`` 1.0) learns which of its class's
      two resting states a box is in (parked or stopped, standing or sitting, with or without a
      rider); the moving state follows from the predicted speed (:mod:`clfbev.attributes`).
    """
    return ModelConfig(n_sweeps=10, sweep_bands=5, sweep_offsets=True,
                       loss=LossWeights(dir=1.0, depth_range_power=2.0, attribute=1.0),
                       min_positives=4,
                       velocity_tower=16, velocity_detach=True, velocity_gate=True, velocity_balance=True,
                       velocity_beta=0.1, sweep_trail=True, heading_from_motion=0.5,
                       heading_follow_classes=("pedestrian",), cam_heatmap=1.0)


def paper() -> ModelConfig:
    """The paper's sizes: ResNet-101 (width 64) on 640 x 1600 images, VFE 512, 0.075 x 0.075 x
    0.2 m voxels. +-54 m (as BEVFusion / TransFusion) makes the grid 1440 x 1440 x 40, which
    three downsamplings bring to a 180 x 180 BEV of 0.6 m cells. ``max_voxels`` caps the grid's
    occupancy at 120k per sample (BEVFusion's training cap). Camera features at stride 16 with
    0.5 m depth bins keep the frustum at 2.8 M points per sample. At 32400 BEV cells exact
    attention needs ~4 GB of weights per head, so MCM/BSM use keys pooled by 4 (global reach,
    2025 keys) with chunked queries."""
    return ModelConfig(
        pc_range=(-54.0, -54.0, -5.0, 54.0, 54.0, 3.0),
        n_sweeps=10,
        image_size=(640, 1600),
        voxel_size=(0.075, 0.075, 0.2),
        max_voxels=120000,
        vfe_ch=512,
        sparse_channels=(16, 32, 64, 128),
        lidar_bev_stride=8,
        sparse_blocks=2,
        cam_depth=101,
        cam_width=64,
        fpn_ch=256,
        context_ch=80,
        depth_bins=(1.0, 60.0, 0.5),
        feature_stride=16,
        fusion_dim=256,
        attn_heads=8,
        attn_mode="pooled",
        attn_pool_stride=4,
        attn_query_chunk=4096,
        bev_channels=(128, 256),
        bev_blocks=5,
        bev_up_ch=256,
    )


PRESETS = {"tiny": tiny, "paper": paper}
