"""Every training target of a batch, built with the batch in the loader, and the training loss
over them.

:class:`TrainingCollate` is the loader's ``collate_fn``: samples -> (:class:`clfbev.data.Batch`,
:class:`Targets`), so the anchor assignment, the lidar points re-projected into the cameras and
their classes are computed in the loader workers, beside the next step's training (the depth
targets are also the oracle lift's ``Batch.depth_bins``, :func:`with_targets`).
:func:`training_loss` takes the model's outputs and those targets:

    loss = detection loss (paper eq. 9) + depth weight x depth loss + semantic weight x semantic loss

the camera terms only for the variants with a camera (and the semantic one only with a
perspective head, ``cfg.loss.semantic > 0``); with ``cam_heatmap`` or ``cam_distill`` the camera
BEV's own terms too (:mod:`clfbev.supervision.camera_bev`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import torch
from torch import Tensor

from clfbev.anchors import make_anchors, match_thresholds
from clfbev.config import ModelConfig
from clfbev.data import Batch, Sample, collate
from clfbev.geometry import batch_nearest_lidar_points, bins_of
from clfbev.head import per_anchor
from clfbev.outputs import ModelOutputs
from clfbev.supervision.assign import AnchorTargets, assign_targets, stack_targets
from clfbev.supervision.attribute import still_loss, still_targets
from clfbev.supervision.camera_bev import add_camera_bev_losses, camera_bev_targets, wants_bev_targets
from clfbev.supervision.depth import depth_loss
from clfbev.supervision.distill import load_teacher
from clfbev.supervision.losses import detection_loss
from clfbev.supervision.perspective import cell_classes, semantic_loss


@dataclass(frozen=True)
class Targets:
    """The training targets of a batch of B samples with N cameras.

    anchor : :class:`AnchorTargets` with a leading B, anchors in the order ``(iy, ix, cls, rot)``.
    depth : (B, N, h, w) int64 depth bin of each camera feature cell's nearest key-frame lidar
        point, -1 where none (:mod:`clfbev.supervision.depth`); None without cameras.
    semantic : (B, N, h, w) int64 class of that point's box, n_classes for background, -1 where
        none (:mod:`clfbev.supervision.perspective`); None without a perspective head.
    heatmap : (B, n_classes, ny, nx) the boxes' centre heatmap on the camera BEV grid
        (:mod:`clfbev.supervision.heatmap`); None without ``cam_heatmap`` or ``cam_distill``.
    teacher : (B, C_teacher, ny, nx) the frozen lidar teacher's BEV features
        (:mod:`clfbev.supervision.distill`); None without ``cam_distill``.
    still : (B, N) int64 the still state of each positive anchor's object, -1 where none
        (:mod:`clfbev.supervision.attribute`); None without the still head (``loss.attribute``).
    """

    anchor: AnchorTargets
    depth: Tensor | None = None
    semantic: Tensor | None = None
    heatmap: Tensor | None = None
    teacher: Tensor | None = None
    still: Tensor | None = None

    def to(self, device: torch.device | str) -> "Targets":
        """A copy with every tensor on ``device``."""
        return Targets(self.anchor.to(device),
                       *(None if t is None else t.to(device) for t in (self.depth, self.semantic, self.heatmap,
                                                                       self.teacher, self.still)))


@torch.no_grad()
def build_targets(batch: Batch, cfg: ModelConfig, anchors: Tensor, cameras: bool = True,
                  teacher: torch.nn.Module | None = None) -> Targets:
    """The :class:`Targets` of ``batch`` (any device) for a model of ``cfg`` with ``anchors``
    (ny, nx, n_cls, n_rot, 7), :func:`clfbev.anchors.make_anchors` of the config; the camera
    targets only with ``cameras``; ``teacher`` (:func:`clfbev.supervision.distill.load_teacher`)
    with ``cfg.cam_distill > 0``."""
    thresholds = match_thresholds(cfg.class_names)
    anchor = stack_targets([
        assign_targets(anchors, boxes[:, : cfg.code_size], labels, thresholds, n_dir_bins=cfg.n_dir_bins,
                       min_positives=cfg.min_positives)
        for boxes, labels in zip(batch.gt_boxes, batch.gt_labels)
    ])
    still = still_targets(anchor, batch.gt_still) if cfg.loss.attribute > 0 else None
    if not cameras:
        return Targets(anchor, still=still)
    # Pasted points have no pixels: they are no camera's target.
    depth, nearest = batch_nearest_lidar_points(batch, cfg)
    semantic = None
    if cfg.loss.semantic > 0:
        semantic = cell_classes(nearest, batch.points, batch.gt_boxes, batch.gt_labels, len(cfg.class_names))
    heatmap = teacher_features = None
    if wants_bev_targets(cfg):
        heatmap, teacher_features = camera_bev_targets(batch, cfg, teacher)
    return Targets(anchor, bins_of(depth, cfg.depth_bins), semantic, heatmap, teacher_features, still)


def with_targets(batch: Batch, cfg: ModelConfig, anchors: Tensor, cameras: bool = True,
                 teacher: torch.nn.Module | None = None) -> tuple[Batch, Targets]:
    """``batch`` as the model of ``cfg`` reads it, and its :class:`Targets` (:func:`build_targets`).

    With ``cfg.cam_oracle_depth`` the batch carries the depth targets as ``Batch.depth_bins``: the
    oracle lifts with exactly the bins the depth loss trains (the same points, pasted ones left
    out, the same nearest point per cell, the same bins), so one projection serves both.
    """
    targets = build_targets(batch, cfg, anchors, cameras, teacher)
    if cfg.cam_oracle_depth and targets.depth is not None:
        batch = replace(batch, depth_bins=targets.depth)
    return batch, targets


class TrainingCollate:
    """The training loader's ``collate_fn``: samples -> (Batch, :class:`Targets`), the batch
    with the oracle's ``depth_bins`` where ``cfg.cam_oracle_depth`` asks for them (:func:`with_targets`).

    Picklable (the loader sends it to its workers); the anchors are made from ``cfg`` in each
    process on first use, and so is the distillation's teacher (``cfg.cam_distill_teacher``).
    ``cameras=False`` (the ``lidar`` variant) skips the camera targets.
    """

    def __init__(self, cfg: ModelConfig, cameras: bool = True) -> None:
        self.cfg, self.cameras = cfg, cameras
        self._anchors: Tensor | None = None
        self._teacher: torch.nn.Module | None = None
        if cameras and cfg.cam_distill > 0:
            # Loaded here, in the main process, so that a bad teacher file stops the run with one
            # line before any loader worker starts (each worker loads its own).
            self._teacher = load_teacher(cfg.cam_distill_teacher, cfg)

    def __call__(self, samples: list[Sample]) -> tuple[Batch, Targets]:
        return with_targets(collate(samples), self.cfg, self.anchors, self.cameras, self.teacher)

    @property
    def teacher(self) -> torch.nn.Module | None:
        """The frozen lidar teacher of ``cfg.cam_distill`` (loaded on first use), or None without."""
        if self._teacher is None and self.cameras and self.cfg.cam_distill > 0:
            self._teacher = load_teacher(self.cfg.cam_distill_teacher, self.cfg)
        return self._teacher

    @property
    def anchors(self) -> Tensor:
        """(ny, nx, n_cls, n_rot, 7) the anchors of the config, as the model makes them."""
        if self._anchors is None:
            cfg = self.cfg
            self._anchors = make_anchors(cfg.class_names, cfg.head_feature_size, cfg.pc_range, cfg.anchor_rotations)
        return self._anchors

    def __getstate__(self) -> dict:
        # The anchors and the teacher are rebuilt in each process, not shipped.
        return {"cfg": self.cfg, "cameras": self.cameras, "_anchors": None, "_teacher": None}


def training_loss(outputs: ModelOutputs, targets: Targets, cfg: ModelConfig) -> dict[str, Tensor]:
    """The training loss of a batch: the dict of :func:`clfbev.supervision.losses.detection_loss`
    (``loss``, ``loss_cls``, ``loss_reg``, ``loss_reg_theta``, ``loss_dir``, ``loss_vel``,
    ``num_pos``) with ``loss_still`` where the head has a still logit, where the model has a
    camera ``loss_depth`` (reported even at weight 0) and, with a perspective head,
    ``loss_semantic``, and with the camera BEV's aux heads ``loss_heatmap`` and ``loss_distill``,
    all unweighted; ``loss`` is the weighted total."""
    losses = detection_loss(outputs.head, targets.anchor, cfg.loss, cfg.velocity_balance, cfg.velocity_beta,
                            cfg.velocity_weight)
    if outputs.head.still_logits is not None:
        n_anchors = outputs.head.cls_logits.shape[1]
        losses["loss_still"] = still_loss(per_anchor(outputs.head.still_logits, n_anchors), targets.still)
        losses["loss"] = losses["loss"] + cfg.loss.attribute * losses["loss_still"]
    if outputs.depth is None:
        return losses
    losses["loss_depth"] = depth_loss(outputs.depth, targets.depth, cfg.depth_bins, cfg.loss.depth_range_power)
    if outputs.semantics is not None:
        losses["loss_semantic"] = semantic_loss(outputs.semantics, targets.semantic, cfg.loss.focal_alpha,
                                                cfg.loss.focal_gamma)
    if cfg.loss.depth > 0:
        losses["loss"] = losses["loss"] + cfg.loss.depth * losses["loss_depth"]
    if outputs.semantics is not None:
        losses["loss"] = losses["loss"] + cfg.loss.semantic * losses["loss_semantic"]
    return add_camera_bev_losses(losses, outputs.cam_heatmap, outputs.cam_distill, targets.heatmap, targets.teacher,
                                 cfg)


def batch_loss(model, batch: Batch) -> dict[str, Tensor]:
    """:func:`training_loss` of ``model`` (a :class:`clfbev.model.CLFusionBEV`) on ``batch``, its
    targets built here as :class:`TrainingCollate` builds them in the loader: for a single batch
    outside the training loop (tests, benchmarks)."""
    cameras = model.camera_encoder is not None
    teacher = load_teacher(model.cfg.cam_distill_teacher, model.cfg) if cameras and model.cfg.cam_distill > 0 else None
    batch, targets = with_targets(batch, model.cfg, model.anchors, cameras, teacher)
    return training_loss(model(batch), targets, model.cfg)
