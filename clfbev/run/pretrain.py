"""Image-view pretraining of the camera encoder on dense labels: ``clfbev pretrain``.

    clfbev pretrain --data DIR --config tiny --out RUN [--max-steps N] [--resume]

The encoder is the detector's own :class:`clfbev.camera_encoder.CameraEncoder` (ResNet, FPN and
the depth net), built from the same config. Three heads read its FPN features and are trained
with the targets of :mod:`clfbev.supervision.dense`: the depth net's logits against the lift's
depth bins, a per-cell lidarseg class head, and a perspective 3D head (CenterNet: per-class
centre heatmap, and offset, depth, size, heading at the centres). Only the encoder is kept:
``RUN/encoder.pt`` (:mod:`clfbev.run.image_init`), which ``clfbev train --image-init`` loads.

The loop is the detector's (:mod:`clfbev.run.train`): the same warmup + cosine learning rate,
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
from clfbev.run.epochs import epoch_batches
from clfbev.run.image_init import save_encoder
from clfbev.run.run_log import ScalarLog, code_version, write_run_json
from clfbev.run.train import Loop, TrainState, lr_at, optimizer_step, restore_state
from clfbev.run.train_config import VERSION, setting
from clfbev.supervision.dense import BOX_CODE, LIDARSEG_CLASSES, WEIGHTS, DenseTargets, dense_losses

PRETRAIN_FORMAT = "clfbev-pretrain-v1"


@dataclass(frozen=True)
class PretrainConfig:
    """Optimisation and bookkeeping settings of one pretraining run: AdamW at ``lr`` with linear
    warmup over ``warmup_frac`` of the steps, then cosine decay to ``lr * min_lr_ratio``."""

    split: str = field(default="sim-train", metadata=setting(
        "split to pretrain on: of a set made for pretraining, with its own simgen seed, never one the "
        "detector is evaluated on"))
    version: str = field(default=VERSION, metadata=setting("table folder under the dataroot"))
    seed: int = field(default=0, metadata=setting("seeds the initial weights and the order of the samples", lo=0))
    lr: float = field(default=2e-3, metadata=setting("peak AdamW learning rate", lo=0, lo_open=True))
    weight_decay: float = field(default=1e-2, metadata=setting("AdamW weight decay", lo=0))
    warmup_frac: float = field(default=0.05, metadata=setting(
        "share of the steps of linear warmup", lo=0, hi=1, hi_open=True))
    min_lr_ratio: float = field(default=1e-2, metadata=setting(
        "the cosine decay ends at the peak learning rate times this", lo=0, hi=1))
    grad_clip: float = field(default=10.0, metadata=setting("max global gradient norm", lo=0, lo_open=True))
    batch_size: int = field(default=2, metadata=setting("samples (of six images each) per step", lo=1))
    epochs: int = field(default=10, metadata=setting("epochs", lo=1, group="length"))
    max_steps: int = field(default=0, metadata=setting(
        "optimizer steps (overrides --epochs; 0: --epochs decides)", lo=0, group="length"))
    workers: int = field(default=0, metadata=setting("DataLoader worker processes", lo=0, bookkeeping=True))
    ckpt_minutes: float = field(default=10.0, metadata=setting(
        "also write last.pt this often (besides every epoch)", lo=0, lo_open=True, bookkeeping=True))
    save_every_steps: int = field(default=0, metadata=setting(
        "also write last.pt every N steps (0: off)", lo=0, bookkeeping=True, metavar="N"))


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

    def save(self, path: Path, state: TrainState) -> None:
        io.save_torch(path, {
            "format": PRETRAIN_FORMAT, "model": state.model.state_dict(), "optimizer": state.opt.state_dict(),
            "config": self.cfg.to_dict(), "train": asdict(self.tc), "step": state.step, "epoch": state.epoch,
            "torch_rng": torch.get_rng_state(), "code_version": self.version,
        })
        self.saved_at = time.monotonic()


# ---------------------------------------------------------------- the loop

def pretrain(data: str | Path, out: str | Path, cfg: ModelConfig, pc: PretrainConfig, resume: bool = False,
             progress: bool = True) -> dict:
    """Pretrain the camera encoder of ``cfg`` on the dense labels of ``data`` into the run folder
    ``out``; returns a summary (steps, final loss, encoder checkpoint path)."""
    from tqdm import tqdm
    run = Path(out)
    ckpt = _resume_checkpoint(run / "last.pt", cfg, pc, resume)
    dataset = DenseLabelled(data, pc.version, pc.split, cfg)
    steps_per_epoch = len(epoch_batches(len(dataset), pc.batch_size, pc.seed, 0, 0, 1))
    total = pc.max_steps if pc.max_steps > 0 else pc.epochs * steps_per_epoch
    device = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    state = _start_state(cfg, pc, ckpt)
    state.model.to(device)
    version = code_version()
    run.mkdir(parents=True, exist_ok=True)
    write_run_json(run, cfg, "pretrain", pc, 1, version, state.step)
    log = ScalarLog(run, state.step)
    bar = tqdm(total=total, initial=state.step, disable=not progress, unit="step", dynamic_ncols=True)
    loop = Loop(run, pc, None, PretrainLoss(state.model), device, 0, 1, log, bar,
                PretrainCheckpoints(run, cfg, "pretrain", pc, version))
    state.model.train()
    try:
        while state.step < total:
            _pretrain_epoch(loop, state, dataset, steps_per_epoch, total)
            if state.step == (state.epoch + 1) * steps_per_epoch:
                state.epoch += 1
            loop.ckpts.save(loop.ckpts.last, state)
    finally:
        bar.close()
        log.close()
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
    saved, now = ckpt.get("train", {}), asdict(pc)
    diff = [f.name for f in fields(PretrainConfig)
            if not f.metadata["bookkeeping"] and saved.get(f.name) != now[f.name]]
    if diff:
        raise CheckpointError(f"{last} was pretrained with other settings (differs in: {', '.join(diff)})")
    return ckpt


def _start_state(cfg: ModelConfig, pc: PretrainConfig, ckpt: dict | None) -> TrainState:
    """The net seeded with ``pc.seed`` and its AdamW, or both as ``ckpt`` left them (with the RNG)."""
    torch.manual_seed(pc.seed)
    model = PretrainNet(cfg)
    state = TrainState(model, torch.optim.AdamW(model.parameters(), lr=pc.lr, weight_decay=pc.weight_decay))
    if ckpt is not None:
        restore_state(state, ckpt, "pretraining checkpoint")
    return state


def _pretrain_epoch(loop: Loop, state: TrainState, dataset: DenseLabelled, steps_per_epoch: int,
                    total: int) -> None:
    """The steps of epoch ``state.epoch`` not trained yet, stopping at step ``total``."""
    pc = loop.tc
    batches = epoch_batches(len(dataset), pc.batch_size, pc.seed, state.epoch, 0, 1)
    done = state.step - state.epoch * steps_per_epoch
    loader = torch.utils.data.DataLoader(dataset, batch_sampler=batches[done:],
                                         collate_fn=DenseCollate(state.model.cfg), num_workers=pc.workers)
    for batch, targets in loader:
        t0 = time.perf_counter()
        lr = lr_at(state.step, total, pc)
        losses, grad_norm = optimizer_step(loop, state, batch.to(loop.device), targets.to(loop.device), lr)
        rate = batch.images.shape[0] * batch.images.shape[1] / (time.perf_counter() - t0)
        scalars = {f"pretrain/{k}": float(losses[k].detach()) for k in ("loss", *WEIGHTS)}
        loop.log.log(state.step, state.epoch, {**scalars, "pretrain/lr": lr, "pretrain/grad_norm": float(grad_norm),
                                               "pretrain/images_per_s": rate})
        loop.bar.set_postfix(epoch=state.epoch, loss=f"{state.loss:.3f}", images_s=f"{rate:.1f}")
        loop.bar.update(1)
        if loop.ckpts.due(state.step):
            loop.ckpts.save(loop.ckpts.last, state)
        if state.step >= total:
            break


def final_loss(summary: dict) -> str:
    """The summary's loss, or a note when a resumed finished run trained nothing."""
    return f"final loss {summary['loss']:.4f}" if math.isfinite(summary["loss"]) else "nothing left to train"
