"""The camera BEV's own targets and losses (``cam_heatmap``, ``cam_distill``): what
:mod:`clfbev.supervision.targets` builds in the loader and adds to the training loss.

    loss += cam_heatmap x loss_heatmap + cam_distill x loss_distill

``loss_heatmap``: :func:`clfbev.supervision.heatmap.heatmap_loss` of the aux head against the
boxes' centre heatmap; ``loss_distill``: :func:`clfbev.supervision.distill.distill_loss` of the
adapted camera BEV against the frozen teacher's features, weighted by that heatmap.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from clfbev.config import ModelConfig
from clfbev.supervision.distill import distill_loss, foreground_weights
from clfbev.supervision.heatmap import bev_heatmap, heatmap_loss


def wants_bev_targets(cfg: ModelConfig) -> bool:
    """Whether ``cfg`` trains the camera BEV's aux heads (and so needs their targets)."""
    return cfg.cam_heatmap > 0 or cfg.cam_distill > 0


@torch.no_grad()
def camera_bev_targets(batch, cfg: ModelConfig, teacher: nn.Module | None) -> tuple[Tensor, Tensor | None]:
    """(heatmap (B, n_classes, ny, nx) of the batch's boxes on the camera BEV grid, the
    teacher's features (B, C_teacher, ny, nx) of its points or None without ``cam_distill``).

    batch : a :class:`clfbev.data.Batch`; teacher : :class:`clfbev.supervision.distill.Teacher`,
    needed with ``cfg.cam_distill > 0``."""
    heat = bev_heatmap(batch.gt_boxes, batch.gt_labels, len(cfg.class_names), cfg.pc_range, cfg.cam_bev_voxel[:2])
    if not cfg.cam_distill > 0:
        return heat, None
    if teacher is None:
        raise ValueError("cam_distill needs the teacher (clfbev.supervision.distill.load_teacher)")
    return heat, teacher(batch.points)


def add_camera_bev_losses(losses: dict[str, Tensor], heatmap_logits: Tensor | None, adapted: Tensor | None,
                          heatmap: Tensor | None, teacher: Tensor | None, cfg: ModelConfig) -> dict[str, Tensor]:
    """``losses`` with ``loss_heatmap`` and ``loss_distill`` (unweighted, for the log) where the
    model has the heads, and their weighted sum added to ``loss``.

    heatmap_logits, adapted : the aux heads' outputs (:class:`clfbev.camera_aux.CameraAuxOutputs`)
    or None; heatmap, teacher : the targets of :func:`camera_bev_targets`."""
    if heatmap_logits is None and adapted is None:
        return losses
    if heatmap is None or (adapted is not None and teacher is None):
        raise ValueError("the camera BEV's aux heads need their targets (TrainingCollate builds them)")
    out = dict(losses)
    if heatmap_logits is not None:
        out["loss_heatmap"] = heatmap_loss(heatmap_logits, heatmap)
        out["loss"] = out["loss"] + cfg.cam_heatmap * out["loss_heatmap"]
    if adapted is not None:
        out["loss_distill"] = distill_loss(adapted, teacher, foreground_weights(heatmap))
        out["loss"] = out["loss"] + cfg.cam_distill * out["loss_distill"]
    return out
