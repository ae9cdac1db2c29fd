"""``clfbev train --lidar-init RUN/last.pt``: a run that starts from a trained run's lidar
detector, BEVFusion's second stage.

BEVFusion trains its fused detector in two stages: the lidar detector alone, then the whole
fused model starting from the lidar detector's weights, with a pretrained image backbone. A
fused model trained from scratch in one stage has to learn its lidar path and its fusion at
once, and on a small budget it ends below the lidar detector (docs/benchmarks.md). Here the
lidar encoder, the BEV backbone and the head load from a training checkpoint; the camera
encoder keeps its own start (``--image-init``) and the fusion modules their seeded
initialisation, under which a fused model is its lidar path (:mod:`clfbev.fusion`). Where the
fused BEV is narrower than the lidar BEV (``tiny``: 64 against 79 channels) the backbone's
first convolution cannot carry over and stays seeded; the log names what did not load.

The same start serves the control a two-stage run is measured against: the lidar model itself
started from its checkpoint and trained the same steps, so that both arms have had the same
lidar training and differ only by the camera.
"""

from __future__ import annotations

from pathlib import Path

from torch import nn

from clfbev.config import ModelConfig
from clfbev.run.checkpoint import check_fields, check_tensors, config_of, load_checkpoint

# The model config fields that decide what the lidar path and the head compute; a checkpoint
# that differs in one of them holds weights for another detector, whatever their shapes.
LIDAR_FIELDS = ("class_names", "pc_range", "n_sweeps", "voxel_size", "vfe_ch", "sparse_channels",
                "lidar_bev_stride", "sparse_blocks", "sweep_bands", "sweep_offsets", "sweep_trail",
                "sweep_trail_min_z", "sweep_trail_in_bev", "bev_channels",
                "bev_blocks", "bev_up_ch", "anchor_rotations", "code_size", "n_dir_bins", "velocity_tower",
                "velocity_detach", "velocity_gate")
# Modules that must load whole, and the one that loads where its tensors fit.
WHOLE = ("lidar_encoder", "head")
FITTING = "backbone"
# The head's still logit (loss.attribute) loads where both the checkpoint and the model have it;
# a model that adds it to a run without one starts it seeded, as a new head's output.
STILL_HEAD = "head.conv_still."


def init_from_lidar_run(model: nn.Module, path: str | Path, cfg: ModelConfig) -> str:
    """Load the lidar encoder, the head and every fitting backbone tensor of the training
    checkpoint at ``path`` into ``model`` (a :class:`clfbev.model.CLFusionBEV` with a lidar
    encoder, built from ``cfg``). Returns what was loaded, in words, for the log."""
    path = Path(path)
    ckpt = load_checkpoint(path)
    check_fields(config_of(ckpt, path).to_dict(), cfg.to_dict(), LIDAR_FIELDS,
                 f"--lidar-init {path}: trained for another lidar detector")
    take, seeded = _lidar_tensors(ckpt, model.state_dict(), path)
    model.load_state_dict(take, strict=False)
    kept = f"; seeded: {', '.join(seeded)}" if seeded else ""
    return f"lidar encoder, backbone and head from {path} (step {ckpt['step']}, variant {ckpt['variant']}){kept}"


def _lidar_tensors(ckpt: dict, want: dict, path: Path) -> tuple[dict, list[str]]:
    """({name: tensor} to load into a model whose state dict is ``want``: every tensor of the
    WHOLE modules, checked by name and shape (the still head's where both have one), and the
    FITTING module's that fit; [the names left seeded])."""
    weights = ckpt["model"]

    def both(k: str) -> bool:
        """Not the still head's, or in the checkpoint and the model alike."""
        return not k.startswith(STILL_HEAD) or (k in weights and k in want)

    take = {k: v for k, v in weights.items() if k.split(".")[0] in WHOLE and both(k)}
    check_tensors(take, {k: v for k, v in want.items() if k.split(".")[0] in WHOLE and both(k)},
                  f"--lidar-init {path}: the lidar detector of the checkpoint's variant '{ckpt['variant']}'")
    seeded = [k for k in want if not both(k)]
    for k, v in want.items():
        if k.split(".")[0] == FITTING:
            if k in weights and weights[k].shape == v.shape:
                take[k] = weights[k]
            else:
                seeded.append(k)
    return take, seeded
