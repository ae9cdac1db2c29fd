"""``clfbev train --camera-init RUN/last.pt``: a fused run whose camera branch starts from a
trained run's, the camera stage of the staged recipe (``scripts/staged.sh``).

BEVFusion trains its camera and lidar detectors apart and then fuses them in a short stage that
starts from both. ``--lidar-init`` (:mod:`clfbev.run.lidar_init`) gives the lidar half; this
gives the camera half: the camera encoder (ResNet, FPN, depth net, the lift and the semantic
head where the config has one) and the camera BEV's auxiliary heads where the config asks for
them (:mod:`clfbev.camera_aux`) load whole from a training checkpoint of a variant with a camera
(a ``camera`` run, usually one trained on cached features with the image encoder frozen). Its
BEV backbone and head are a camera detector's and stay behind: the fused model's come from
``--lidar-init`` or its seed. The two combine: each loads only its own modules.

A checkpoint trained for another camera branch is refused, field by field: the encoder's fields,
the camera BEV's grid (``cam_bev_voxel``, which follows the lidar BEV's shape) and whether a
semantic head exists; then every tensor's name and shape.
"""

from __future__ import annotations

from pathlib import Path

from torch import nn

from clfbev.config import ModelConfig
from clfbev.errors import CheckpointError
from clfbev.run.checkpoint import check_fields, check_tensors, config_of, load_checkpoint
from clfbev.run.image_init import CAMERA_FIELDS

# The model config fields that decide what the camera branch computes, beside the encoder's own
# (CAMERA_FIELDS); a checkpoint that differs in one holds another camera branch, whatever its shapes.
CAMERA_BRANCH_FIELDS = CAMERA_FIELDS + ("class_names", "pc_range", "cam_z_slabs", "cam_semantic_lift",
                                        "cam_oracle_depth", "cam_lift", "cam_lift_heights", "cam_heatmap",
                                        "cam_distill", "cam_distill_teacher")
# The modules that make up the camera branch, each loaded whole.
CAMERA_MODULES = ("camera_encoder", "camera_aux")


def camera_branch(cfg: ModelConfig) -> dict:
    """{name: value} of what decides ``cfg``'s camera branch: :data:`CAMERA_BRANCH_FIELDS`, the
    camera voxel (m; its x/y size is the lidar BEV's cell, so it follows the lidar grid's fields)
    and whether the encoder has a semantic head (``loss.semantic > 0``). YAML/JSON-safe."""
    plain = cfg.to_dict()
    return {**{k: plain[k] for k in CAMERA_BRANCH_FIELDS}, "cam_bev_voxel": list(cfg.cam_bev_voxel),
            "semantic_head": cfg.loss.semantic > 0}


def init_from_camera_run(model: nn.Module, path: str | Path, cfg: ModelConfig) -> str:
    """Load every tensor of :data:`CAMERA_MODULES` of the training checkpoint at ``path`` into
    ``model`` (a :class:`clfbev.model.CLFusionBEV` with a camera encoder, built from ``cfg``).
    Returns what was loaded, in words, for the log."""
    path = Path(path)
    ckpt = load_checkpoint(path)
    if ckpt["variant"] == "lidar":
        raise CheckpointError(f"--camera-init {path}: a run of variant 'lidar' has no camera branch")
    mine = camera_branch(cfg)
    check_fields(camera_branch(config_of(ckpt, path)), mine, mine,
                 f"--camera-init {path}: trained for another camera branch")
    want = {k: v for k, v in model.state_dict().items() if k.split(".")[0] in CAMERA_MODULES}
    take = {k: v for k, v in ckpt["model"].items() if k.split(".")[0] in CAMERA_MODULES}
    check_tensors(take, want,
                  f"--camera-init {path}: the camera branch of the checkpoint's variant '{ckpt['variant']}'")
    model.load_state_dict(take, strict=False)
    return f"camera branch from {path} (step {ckpt['step']}, variant {ckpt['variant']})"
