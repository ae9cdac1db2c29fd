"""What :meth:`clfbev.model.CLFusionBEV.forward` returns: the head's maps, what the camera
losses read, and the inputs of the attention modules. Shapes (B samples, N cameras) and frames
per field; BEV maps are (B, C, ny, nx) in the key-frame lidar frame.
"""

from __future__ import annotations

from typing import NamedTuple

from torch import Tensor

from clfbev.head import HeadOutput


class AttentionInputs(NamedTuple):
    """The inputs of the attention modules, as the forward gave them (None where the variant has
    no such module), so that a picture of the attention needs no second forward.

    mcm_lidar : (B, Cl, ny, nx) the lidar BEV whose cells are MCM's queries.
    mcm_camera : (B, Cc, ny, nx) the camera BEV MCM's keys and values come from.
    bsm : (B, fusion_dim, ny, nx) the fused BEV BSM attends over.
    """

    mcm_lidar: Tensor | None = None
    mcm_camera: Tensor | None = None
    bsm: Tensor | None = None


class ModelOutputs(NamedTuple):
    """head : the anchor head's maps (:class:`clfbev.head.HeadOutput`): cls (B, A, ny, nx), box
        (B, A * code_size, ny, nx), dir (B, A * n_dir_bins, ny, nx), A = n_classes * n_rotations.
    depth : (B, N, D, h, w) the camera's depth distribution, None without a camera.
    semantics : (B, N, n_classes, h, w) the perspective head's logits, None without one.
    attention : :class:`AttentionInputs`.
    cam_heatmap : (B, n_classes, ny, nx) the camera BEV's auxiliary centre logits, in training with
        ``cam_heatmap > 0`` only (:mod:`clfbev.camera_aux`); else None.
    cam_distill : (B, teacher channels, ny, nx) the camera BEV through the distillation adapter,
        in training with ``cam_distill > 0`` only; else None.
    """

    head: HeadOutput
    depth: Tensor | None
    semantics: Tensor | None
    attention: AttentionInputs
    cam_heatmap: Tensor | None = None
    cam_distill: Tensor | None = None
