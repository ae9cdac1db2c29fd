"""The settings a model config is made of and the facts it is checked against. A leaf: it
imports nothing of the project and no torch, so that :mod:`clfbev.config` and every module
can import it.

- the nuScenes detection classes, their anchor sizes and the anchor rotations;
- the attention modes of :mod:`clfbev.attention`;
- :class:`LossWeights` (the losses of :mod:`clfbev.supervision.losses`) and :class:`DataConfig`
  (what :mod:`clfbev.data` loads);
- the grid arithmetic the config and the modules share (:func:`grid_shape_of`,
  :func:`conv_out_size`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

# nuScenes detection classes in the devkit's order.
DETECTION_CLASSES: tuple[str, ...] = (
    "car", "truck", "construction_vehicle", "bus", "trailer",
    "barrier", "motorcycle", "bicycle", "pedestrian", "traffic_cone",
)

# Mean box size per class (l, w, h) in metres, over the nuScenes train set (the values
# PointPillars / SECOND use for their anchors).
ANCHOR_SIZES: dict[str, tuple[float, float, float]] = {
    "car": (4.61, 1.95, 1.72),
    "truck": (6.74, 2.46, 2.73),
    "bus": (11.19, 2.94, 3.47),
    "trailer": (12.01, 2.87, 3.82),
    "construction_vehicle": (6.38, 2.73, 3.13),
    "motorcycle": (2.10, 0.76, 1.44),
    "bicycle": (1.69, 0.60, 1.27),
    "pedestrian": (0.73, 0.66, 1.76),
    "traffic_cone": (0.40, 0.40, 1.06),
    "barrier": (0.49, 2.49, 0.98),
}

# Two anchor headings: along x and along y. Headings modulo pi are enough because the box
# regression is pi-periodic (sin-difference) and a direction classifier adds the last pi.
ANCHOR_ROTATIONS: tuple[float, ...] = (0.0, 0.5 * math.pi)

# How a BEV cell attends (clfbev.attention.BEVAttention).
ATTENTION_MODES = ("exact", "window", "pooled")

# The camera encoder's image backbones (clfbev.camera_encoder.CameraEncoder).
CAMERA_BACKBONES = ("resnet", "efficientnet_lite0")

# Points reach the model as x, y, z, intensity, time lag (clfbev.data); not a free choice.
POINT_CH = 5
# The lidar turns at 20 Hz (nuScenes and the HDL-32E alike): consecutive sweeps are 0.05 s apart.
LIDAR_SWEEP_PERIOD_S = 0.05
# Cells a side of the windows each BEV cell's sweep trail is fitted over (clfbev.sweep_bev): the
# cell alone (a walker), and its 3x3 neighbourhood (a walker crossing cells, a cyclist).
TRAIL_WINDOWS = (1, 3)


@dataclass(frozen=True)
class LossWeights:
    """Weights of eq. 9 and of the individual residuals.

    cls, reg, dir : l_cls, l_reg, l_dir.
    depth : weight of the camera's lidar-supervised depth loss
        (:mod:`clfbev.supervision.depth`; BEVDepth uses 3.0); 0 turns the supervision off (the
        ablation). Unused by the ``lidar`` variant.
    depth_range_power : p >= 0: each depth-supervised camera cell weighs in proportion to its
        target depth to the power p, normalised to a mean of 1 over the batch's cells with a
        target; 0 is BEVDepth's plain mean (``tiny``: 2). Under the plain mean the near cells decide the depth
        head (in ``tiny`` 55% of the lidar-seen cells lie within 10 m, 12% beyond 20 m), where
        a far cell's features spread over a wider strip of the BEV (its ray bundle's width
        grows with the depth).
    semantic : weight of the camera's perspective class loss
        (:mod:`clfbev.supervision.perspective`); 0 (the default) builds no perspective head.
        Unused by the ``lidar`` variant.
    attribute : weight of the still-state loss (a binary cross-entropy of the head's still
        logit on the positive anchors whose object rests in one of its class's two still
        states: stopped or parked, standing or sitting, with or without a rider;
        :mod:`clfbev.attributes`); 0 (the default) builds no still head, and a box at rest takes
        its class's common state.
    code_weights : per residual ``(dx, dy, dz, dl, dw, dh, dtheta, vx, vy)``; velocity is
        down-weighted (0.2) because it is noisy (from a few sweeps) and would otherwise pull
        the shared features away from localisation early in training.
    focal_alpha, focal_gamma : focal loss parameters (paper: 0.25 and 2).
    smooth_l1_beta : Smooth-L1 transition point; 1/9 is SECOND's ``sigma = 3``.
    """

    cls: float = 1.0
    reg: float = 2.0
    dir: float = 0.2
    depth: float = 3.0
    depth_range_power: float = 0.0
    semantic: float = 0.0
    attribute: float = 0.0
    code_weights: tuple[float, ...] = (1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 0.2, 0.2)
    focal_alpha: float = 0.25
    focal_gamma: float = 2.0
    smooth_l1_beta: float = 1.0 / 9.0


@dataclass(frozen=True)
class DataConfig:
    """What the loader produces.

    class_names : detection classes, in label order (label = index).
    image_size : (H, W) of the images the network sees (resized to W keeping the aspect
        ratio, then cropped or padded at the top to H; see :func:`clfbev.data.resize_and_crop`).
    n_sweeps : lidar sweeps per sample: the key frame plus n_sweeps - 1 previous sweeps.
    point_range : (xmin, ymin, zmin, xmax, ymax, zmax), key-frame lidar frame; points outside
        and boxes whose centre lies outside are dropped (min <= p < max).
    min_points : boxes with fewer lidar points are dropped. The devkit's DetectionEval drops
        GT boxes without lidar (and radar) points too, so 0-point boxes are never evaluated.
    """

    class_names: tuple[str, ...] = DETECTION_CLASSES
    image_size: tuple[int, int] = (192, 352)
    n_sweeps: int = 3
    point_range: tuple[float, ...] = (-51.2, -51.2, -5.0, 51.2, 51.2, 3.0)
    min_points: int = 1

    def __post_init__(self):
        if self.n_sweeps < 1:
            raise ValueError(f"n_sweeps must be >= 1, got {self.n_sweeps}")
        if len(self.point_range) != 6 or len(self.image_size) != 2:
            raise ValueError(f"point_range needs 6 values and image_size 2, got {self.point_range}, {self.image_size}")


def grid_shape_of(pc_range: tuple[float, ...], voxel_size: tuple[float, ...]) -> tuple[int, int, int]:
    """Grid size (nz, ny, nx) for a range (xmin, ymin, zmin, xmax, ymax, zmax) and voxel (dx, dy, dz).

    Rounded, not floored, so that e.g. a 102.4 m range over 0.1 m voxels gives 1024 despite
    floating-point error.
    """
    if len(pc_range) != 6 or len(voxel_size) != 3:
        raise ValueError(f"pc_range needs 6 values and voxel_size 3, got {pc_range}, {voxel_size}")
    n_xyz = [int(round((pc_range[i + 3] - pc_range[i]) / voxel_size[i])) for i in range(3)]
    if min(n_xyz) < 1:
        raise ValueError(f"empty voxel grid for pc_range={pc_range}, voxel_size={voxel_size}")
    return n_xyz[2], n_xyz[1], n_xyz[0]


def conv_out_size(n: int, kernel: int, stride: int, padding: int) -> int:
    """Output length of a conv along one axis, the ``nn.Conv3d`` formula the rulebooks use."""
    return (n + 2 * padding - kernel) // stride + 1
