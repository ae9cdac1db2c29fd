"""Distillation of a trained ``lidar`` model's BEV features into the camera's BEV (BEVDistill,
Chen et al. 2023; DistillBEV, Wang et al. 2023).

The teacher is a frozen lidar detector of the same config (``cam_distill_teacher``: a training
checkpoint of a run with a lidar encoder, e.g. a ``lidar`` run's ``last.pt``); its features are
what its sparse encoder puts in each BEV cell (the lidar BEV without the sweep bands' counts,
offsets and trails: those are hand-made inputs, and motion, which one key frame of images does
not show). They are computed in the loader with the other targets, in eval mode and without
gradient, from the same augmented points the sample's cameras match, so a teacher cell and a
camera cell are one place.

The student is the camera BEV through a 1x1 adapter to the teacher's channels
(:class:`clfbev.camera_aux.CameraBEVHeads`): the camera BEV is not asked to be the lidar's
features, only to hold what a linear map turns into them. The loss is a mean squared error
weighted per cell, so that the few cells of objects are not drowned by the road (BEVDistill's
foreground-weighted dense distillation; DistillBEV's region weights):

    L = sum_cells w (sum_c (adapter(cam)_c - teacher_c)^2) / (C_teacher sum_cells w),
    w = max(BACKGROUND_WEIGHT, max over classes of the centre heatmap),

the heatmap being the CenterPoint Gaussians of the boxes' footprints
(:func:`clfbev.supervision.heatmap.bev_heatmap`): 1 at each box's centre cell, falling with the
distance to it, and ``BACKGROUND_WEIGHT`` (0.1) for every other cell.
"""

from __future__ import annotations

from pathlib import Path

import torch
from torch import Tensor, nn

from clfbev.camera_aux import teacher_channels
from clfbev.config import ModelConfig
from clfbev.errors import CheckpointError

# The weight of a cell far from every box: small, so the background is learned but does not
# decide the loss (in ``tiny`` the boxes' centre windows cover about 3% of the cells).
BACKGROUND_WEIGHT = 0.1


def foreground_weights(heatmap: Tensor, background: float = BACKGROUND_WEIGHT) -> Tensor:
    """(B, 1, ny, nx) per-cell weights of the distillation: ``max(background, max over classes
    of heatmap)``; heatmap (B, n_classes, ny, nx) of :func:`clfbev.supervision.heatmap.bev_heatmap`."""
    return heatmap.amax(dim=1, keepdim=True).clamp(min=background)


def distill_loss(student: Tensor, teacher: Tensor, weights: Tensor) -> Tensor:
    """The weighted mean squared error of the module docstring, 0-d.

    student, teacher : (B, C, ny, nx); weights : (B, 1, ny, nx) >= 0. The teacher is detached
    (no gradient reaches it, whatever it is)."""
    if student.shape != teacher.shape:
        raise ValueError(f"student {tuple(student.shape)} and teacher {tuple(teacher.shape)} features differ in shape")
    sq = (student.float() - teacher.detach().float()).pow(2).sum(dim=1, keepdim=True)      # (B, 1, ny, nx)
    return (weights * sq).sum() / (weights.sum().clamp_min(1e-12) * student.shape[1])


class Teacher(nn.Module):
    """The frozen lidar encoder of a trained detector: points -> its BEV features."""

    def __init__(self, lidar_encoder: nn.Module) -> None:
        super().__init__()
        self.lidar_encoder = lidar_encoder
        self.requires_grad_(False)
        self.eval()

    def train(self, mode: bool = True) -> "Teacher":
        # Always in eval mode: its BatchNorm keeps the teacher's statistics.
        return super().train(False)

    @property
    def out_channels(self) -> int:
        return self.lidar_encoder.sparse.out_channels

    @torch.no_grad()
    def forward(self, points: list[Tensor]) -> Tensor:
        """B point clouds (n_i, 5), lidar frame -> (B, out_channels, ny, nx) features."""
        return self.lidar_encoder.encode(points).bev[:, :self.out_channels]


def load_teacher(path: str | Path, cfg: ModelConfig) -> Teacher:
    """The teacher of ``cfg`` (the student's config) from the training checkpoint at ``path``:
    its lidar encoder, frozen. CheckpointError when the file is no such checkpoint, has no
    lidar encoder, or was trained for another lidar detector (a field of
    :data:`clfbev.run.lidar_init.LIDAR_FIELDS` differs: its features would be of another grid
    or input)."""
    from clfbev.run.checkpoint import config_of, load_checkpoint, load_model
    from clfbev.run.lidar_init import LIDAR_FIELDS

    path = Path(path)
    ckpt = load_checkpoint(path)
    if ckpt["variant"] == "camera":
        raise CheckpointError(f"cam_distill_teacher {path}: a 'camera' run has no lidar encoder to distil")
    theirs, mine = config_of(ckpt, path).to_dict(), cfg.to_dict()
    diff = [k for k in LIDAR_FIELDS if theirs[k] != mine[k]]
    if diff:
        differs = ", ".join(f"{k} {theirs[k]} != {mine[k]}" for k in diff)
        raise CheckpointError(f"cam_distill_teacher {path}: trained for another lidar detector (differs in: {differs})")
    model, _ = load_model(path)
    teacher = Teacher(model.lidar_encoder)
    if teacher.out_channels != teacher_channels(cfg):
        raise CheckpointError(f"cam_distill_teacher {path}: {teacher.out_channels} feature channels, the config's "
                              f"adapter has {teacher_channels(cfg)}")
    return teacher
