"""The encoder checkpoint: what ``clfbev pretrain`` writes and ``clfbev train --image-init PATH``
loads into the detector's camera encoder.

A plain dict, written atomically (:func:`clfbev.io.save_torch`) and read with
``torch.load(weights_only=True)``:

- ``format``: :data:`ENCODER_FORMAT`;
- ``encoder``: the state dict of :class:`clfbev.camera_encoder.CameraEncoder` (ResNet, FPN,
  depth net, and the semantic head where the config has one), nothing else;
- ``camera``: the :class:`clfbev.config.ModelConfig` fields the encoder depends on
  (:data:`CAMERA_FIELDS`);
- ``command``: the command line that made it; ``data``: the identity of the pretraining set
  (:func:`clfbev.pretrain_data.data_identity`); ``step``; ``code_version``.

:func:`resolve_image_init` turns ``--image-init`` into a file: a path as given, or for
``shipped`` the checkpoint in ``clfbev/weights/`` whose record (the ``.json`` beside it) names
the config's camera fields.

Loading refuses, with one :class:`clfbev.errors.CheckpointError` naming the file, a file that is
not such a checkpoint, one made for other camera fields, and one whose tensors do not have
exactly the encoder's names and shapes.
"""
from __future__ import annotations

import json
from pathlib import Path

import torch
from torch import nn

from clfbev import io
from clfbev.camera_encoder import CameraEncoder
from clfbev.config import ModelConfig
from clfbev.errors import CheckpointError
from clfbev.run.checkpoint import check_tensors, read_torch
from clfbev.run.efficientnet_init import EFFICIENTNET_LITE0, load_efficientnet_backbone
from clfbev.run.torchvision_init import TORCHVISION, load_torchvision_backbone
from clfbev.run.train_config import SHIPPED

ENCODER_FORMAT = "clfbev-encoder-v1"
WEIGHTS_DIR = Path(__file__).resolve().parents[1] / "weights"
CAMERA_FIELDS = ("image_size", "cam_backbone", "cam_depth", "cam_width", "fpn_ch", "context_ch", "depth_bins",
                 "feature_stride")
# Camera fields added after encoders were recorded: the value every earlier record was made with.
EARLIER_CAMERA_FIELDS = {"cam_backbone": "resnet"}


def recorded_camera(camera: dict) -> dict:
    """An encoder record's camera fields, those it predates filled in (:data:`EARLIER_CAMERA_FIELDS`)."""
    return {**EARLIER_CAMERA_FIELDS, **camera}


def camera_fields(cfg: ModelConfig) -> dict:
    """The fields of ``cfg`` the camera encoder's weights depend on (YAML/JSON-safe)."""
    plain = cfg.to_dict()
    return {k: plain[k] for k in CAMERA_FIELDS}


def shipped_encoder(cfg: ModelConfig) -> Path | None:
    """The encoder shipped in :data:`WEIGHTS_DIR` for ``cfg``'s camera (the ``.pt`` beside the
    first record whose ``camera`` equals :func:`camera_fields`), or None when none ships for it."""
    mine = camera_fields(cfg)
    for record in sorted(WEIGHTS_DIR.glob("*.json")):
        camera = json.loads(record.read_text()).get("camera")
        if isinstance(camera, dict) and recorded_camera(camera) == mine:
            return record.with_suffix(".pt")
    return None


def init_camera_encoder(encoder: CameraEncoder, value: str, cfg: ModelConfig) -> str:
    """Start ``encoder`` (built from ``cfg``) as ``--image-init value`` says: '' keeps its seeded
    weights, ``torchvision`` loads the backbone from the local torch cache
    (:mod:`clfbev.run.torchvision_init`), ``efficientnet-lite0`` from its package
    (:mod:`clfbev.run.efficientnet_init`), ``shipped`` or a path an encoder checkpoint. Returns
    what it was started from, in words, for the log."""
    if value == TORCHVISION:
        return f"backbone from torchvision's {load_torchvision_backbone(encoder.backbone, cfg.cam_width)}"
    if value == EFFICIENTNET_LITE0:
        return f"backbone from EfficientNet-Lite0's ImageNet weights {load_efficientnet_backbone(encoder.backbone)}"
    path = resolve_image_init(value, cfg)
    if path is None:
        return "from scratch" + (f" (no encoder ships for this camera: {camera_fields(cfg)})" if value else "")
    load_image_init(encoder, path, cfg)
    return f"from the encoder checkpoint {path}"


def resolve_image_init(value: str, cfg: ModelConfig) -> Path | None:
    """The encoder checkpoint ``--image-init value`` names for ``cfg``: None for '' (from
    scratch) and for ``shipped`` when no encoder ships for this camera."""
    if not value:
        return None
    return shipped_encoder(cfg) if value == SHIPPED else Path(value)


def save_encoder(path: str | Path, encoder: nn.Module, cfg: ModelConfig, command: list[str], data: dict,
                 step: int, version: str) -> Path:
    """Write the encoder checkpoint of ``encoder`` to ``path``, atomically."""
    return io.save_torch(path, {"format": ENCODER_FORMAT, "encoder": encoder.state_dict(),
                                "camera": camera_fields(cfg), "command": list(command), "data": data,
                                "step": step, "code_version": version})


def load_encoder_checkpoint(path: str | Path) -> dict:
    """The encoder checkpoint at ``path``, checked to be one."""
    path = Path(path)
    ckpt = read_torch(path)
    if not isinstance(ckpt, dict) or ckpt.get("format") != ENCODER_FORMAT:
        raise CheckpointError(f"{path} is not an encoder checkpoint ({ENCODER_FORMAT}; `clfbev pretrain` writes one)")
    weights = ckpt.get("encoder")
    if not isinstance(weights, dict) or not all(isinstance(v, torch.Tensor) for v in weights.values()):
        raise CheckpointError(f"encoder checkpoint {path}: field 'encoder' is not a state dict of tensors")
    bad = next((k for k, v in weights.items() if v.is_floating_point() and not torch.isfinite(v).all()), None)
    if bad is not None:
        raise CheckpointError(f"encoder checkpoint {path}: the weights '{bad}' hold non-finite values")
    if not isinstance(ckpt.get("camera"), dict):
        raise CheckpointError(f"encoder checkpoint {path}: field 'camera' is missing")
    return ckpt


def load_image_init(encoder: nn.Module, path: str | Path, cfg: ModelConfig) -> dict:
    """Load the encoder checkpoint at ``path`` into ``encoder`` (the detector's camera encoder,
    built from ``cfg``): every tensor of the encoder, and only those, after checking the camera
    fields and every name and shape. Returns the checkpoint."""
    ckpt = load_encoder_checkpoint(path)
    mine = camera_fields(cfg)
    theirs = recorded_camera(ckpt["camera"])
    diff = [k for k in CAMERA_FIELDS if theirs.get(k) != mine[k]]
    if diff:
        differs = ", ".join(f"{k} {theirs.get(k)} != {mine[k]}" for k in diff)
        raise CheckpointError(f"encoder checkpoint {path} was pretrained for another camera (differs in: {differs})")
    check_tensors(ckpt["encoder"], encoder.state_dict(), f"encoder checkpoint {path}")
    encoder.load_state_dict(ckpt["encoder"], strict=True)
    return ckpt
