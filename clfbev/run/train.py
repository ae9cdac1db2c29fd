"""The training loop, readable top to bottom: data, model, AdamW, warmup + cosine, clipping,
logs, atomic checkpoints, exact resume, validation by the official metric, and DDP.

    clfbev train --data DIR --config tiny --variant full --out RUN [--epochs N | --max-steps N]
    torchrun --nproc_per_node 2 -m clfbev train --data DIR --config tiny --out RUN ...

Determinism (what makes ``--resume`` give the same weights as an uninterrupted run): everything
random is a pure function of ``(seed, epoch, sample index)`` or is saved in the checkpoint.

- the model is initialised from ``torch.manual_seed(seed)``;
- epoch e visits the samples in ``randperm`` order from a generator seeded with ``(seed, e)``;
- sample i of epoch e is augmented with ``np.random.default_rng((seed, e, i))``;
- the learning rate is a pure function of the step (no scheduler state);
- a checkpoint holds the weights (with BatchNorm statistics), the optimizer state, the step,
  the epoch and the torch RNG state. Resuming at step k skips the first k batches of the
  epoch's (known) order without loading them.

So a run killed at any moment and resumed from its last checkpoint recomputes exactly the
steps it lost. On the CPU the result is bit-identical (``tests/clfbev/test_train.py``); on a
GPU, kernels such as scatter-add are not deterministic, so it is identical up to float noise.

DDP: rank r of W takes every W-th index of the epoch's order (padded by wrapping so that all
ranks take the same number of steps); gradients are averaged by DistributedDataParallel
(gloo on the CPU, nccl on GPUs). Rank 0 alone logs, validates and writes checkpoints.
"""

from __future__ import annotations

import math
import os
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path

import torch
import torch.distributed as dist
from torch import Tensor, nn

from clfbev.augment import AugmentConfig
from clfbev.config import ModelConfig
from clfbev.data import Batch, NuScenesDetection
from clfbev.errors import CheckpointError, ConfigError, DataError, TrainError
from clfbev.feature_cache import CachedFeatureDataset, FeatureCache, encoder_identity
from clfbev.gt_paste import GTDatabase
from clfbev.model import CLFusionBEV
from clfbev.run.camera_init import init_from_camera_run
from clfbev.run.checkpoint import REQUIRED, RESUME_FIELDS, Checkpoints, check_matches, load_checkpoint
from clfbev.run.efficientnet_init import EFFICIENTNET_LITE0
from clfbev.run.epochs import EpochSamples, epoch_batches, precise_batchnorm
from clfbev.run.evaluate import evaluate_model
from clfbev.run.image_init import init_camera_encoder
from clfbev.run.lidar_init import init_from_lidar_run
from clfbev.run.run_log import ScalarLog, code_version, write_run_json
from clfbev.run.torchvision_init import TORCHVISION
from clfbev.run.train_config import TrainConfig, check_resumable
from clfbev.supervision.targets import Targets, TrainingCollate, training_loss

def lr_at(step: int, total: int, tc: TrainConfig) -> float:
    """Learning rate of optimizer step ``step`` (0-based) of ``total``: linear warmup from
    ``lr / 10`` to ``lr`` over ``warmup_frac`` of the steps, then cosine to ``lr * min_lr_ratio``."""
    warm = max(1, int(round(tc.warmup_frac * total)))
    if step < warm:
        return tc.lr * (0.1 + 0.9 * step / warm)
    t = (step - warm) / max(1, total - warm)
    floor = tc.lr * tc.min_lr_ratio
    return floor + 0.5 * (tc.lr - floor) * (1.0 + math.cos(math.pi * min(1.0, t)))


class LossModule(nn.Module):
    """``forward(batch, targets) -> loss dict``, so that DDP's forward wraps the whole loss
    computation."""

    def __init__(self, model: CLFusionBEV) -> None:
        super().__init__()
        self.model = model

    def forward(self, batch: Batch, targets: Targets) -> dict[str, Tensor]:
        return training_loss(self.model(batch), targets, self.model.cfg)


# ---------------------------------------------------------------- what a run is made of

@dataclass(frozen=True)
class TrainingData:
    """The training split (and, on rank 0, the validation split) and the run's length in steps."""

    train_set: NuScenesDetection
    val_set: NuScenesDetection | None
    augment: AugmentConfig | None
    gt_db: GTDatabase | None
    steps_per_epoch: int
    total: int                  # optimizer steps of the whole run
    paste_until: int            # epochs starting at or after this step paste nothing (the fade)


@dataclass
class TrainState:
    """Where a run stands: what its checkpoint holds besides the settings, and the last loss and
    validation (reported, not saved)."""

    model: CLFusionBEV
    opt: torch.optim.Optimizer
    step: int = 0
    epoch: int = 0              # epochs fully done
    best_nds: float = -1.0
    loss: float = math.nan
    last_val: dict | None = None


@dataclass
class Loop:
    """The fixed parts of one training process; ``log`` is None on ranks other than 0."""

    run: Path
    tc: TrainConfig
    data: TrainingData
    loss_module: nn.Module
    device: torch.device
    rank: int
    world: int
    log: ScalarLog | None
    bar: object                 # tqdm
    ckpts: Checkpoints


# ---------------------------------------------------------------- the loop

def train(data: str | Path, out: str | Path, cfg: ModelConfig, variant: str, tc: TrainConfig,
          resume: bool = False, progress: bool = True) -> dict:
    """Train ``variant`` of ``cfg`` on ``data`` into the run folder ``out``; returns a summary
    (steps, final loss, best NDS, last validation). See the module docstring for the contract.
    Call under torchrun for DDP (the process group is set up here)."""
    from tqdm import tqdm
    run = Path(out)
    rank, world, device = _setup_distributed()
    check_sensor_settings(tc, variant)
    ckpt = resume_checkpoint(run / "last.pt", cfg, variant, tc, resume)
    training = load_training_data(data, cfg, variant, tc, rank, world)
    state = start_state(cfg, variant, tc, device, ckpt, run / "last.pt")
    if tc.feature_cache:
        training.train_set.cache.check_encoder(encoder_identity(state.model.camera_encoder))
    loss_module: nn.Module = LossModule(state.model)
    if world > 1:
        loss_module = nn.parallel.DistributedDataParallel(loss_module)
    version = code_version()          # a git subprocess: once per run, not at every checkpoint
    log = None
    if rank == 0:
        run.mkdir(parents=True, exist_ok=True)
        write_run_json(run, cfg, variant, tc, world, version, state.step)
        log = ScalarLog(run, state.step)
    bar = tqdm(total=training.total, initial=state.step, disable=not (rank == 0 and progress), unit="step",
               dynamic_ncols=True)
    loop = Loop(run, tc, training, loss_module, device, rank, world, log, bar,
                Checkpoints(run, cfg, variant, tc, version))
    state.model.train()
    try:
        while state.step < training.total:
            train_epoch(loop, state)
            if state.step == (state.epoch + 1) * training.steps_per_epoch:
                state.epoch += 1
            if rank == 0:
                end_epoch(loop, state)
            if world > 1:
                dist.barrier()
    finally:
        bar.close()
        if log is not None:
            log.close()
        if world > 1 and dist.is_initialized():
            dist.destroy_process_group()
    return {"steps": state.step, "epochs": state.epoch, "loss": state.loss, "best_nds": state.best_nds,
            "val": state.last_val}


def resume_checkpoint(last: Path, cfg: ModelConfig, variant: str, tc: TrainConfig, resume: bool) -> dict | None:
    """The checkpoint the run continues from, or None for a new run. A run folder that has one
    needs ``resume``, and the checkpoint must be of the same config, variant and settings (all
    but the bookkeeping ones)."""
    if not last.exists():
        return None
    if not resume:
        raise CheckpointError(f"{last} exists: pass --resume to continue that run, or choose another --out")
    ckpt = load_checkpoint(last, REQUIRED + RESUME_FIELDS)
    check_matches(ckpt, last, cfg, variant)
    check_resumable(ckpt["train"], tc, last)
    return ckpt


def check_sensor_settings(tc: TrainConfig, variant: str) -> None:
    """Refuse settings that ask a variant for a sensor it lacks, or a feature cache that the
    training would leave stale (an encoder that trains) or that cannot hold the input asked for
    (the older ``modality_dropout`` zeroes images)."""
    fused = variant not in ("lidar", "camera")
    if (tc.modality_dropout_lidar or tc.modality_dropout_camera) and not fused:
        raise ConfigError(f"--modality-dropout-lidar and --modality-dropout-camera need a variant with both sensors, "
                          f"not '{variant}'")
    if not tc.feature_cache:
        return
    if variant == "lidar":
        raise ConfigError(f"--feature-cache {tc.feature_cache}: the variant 'lidar' has no camera")
    if not tc.image_freeze:
        raise ConfigError(f"--feature-cache {tc.feature_cache} needs --image-freeze (the cached features are those "
                          "of the frozen encoder)")
    if tc.modality_dropout:
        raise ConfigError("--modality-dropout zeroes the images, which --feature-cache does not read; use "
                          "--modality-dropout-lidar and --modality-dropout-camera")


def load_training_data(data: str | Path, cfg: ModelConfig, variant: str, tc: TrainConfig, rank: int,
                       world: int) -> TrainingData:
    """The splits, the augmentation, the GT-paste database and the run's length in steps; with
    ``tc.feature_cache`` the training split reads the cached image features, and only the BEV is
    augmented. The ``camera`` variant's training samples hold the key sweep alone: its lidar
    points are only its depth targets, which read the key sweep (:mod:`clfbev.supervision.depth`),
    and the other sweeps would only be loaded, moved and shuffled (with ``cam_distill`` it keeps
    them all: the lidar teacher reads them)."""
    train_cfg = cfg.data_config()
    if variant == "camera" and not cfg.cam_distill > 0:
        train_cfg = replace(train_cfg, n_sweeps=1)
    if tc.feature_cache:
        train_set = CachedFeatureDataset(data, tc.version, tc.train_split, train_cfg,
                                         FeatureCache.open(tc.feature_cache))
    else:
        train_set = NuScenesDetection(data, tc.version, tc.train_split, train_cfg)
    val_set = NuScenesDetection(data, tc.version, tc.val_split, cfg.data_config()) if (tc.val_split and rank == 0) else None
    if len(train_set) == 0:
        raise DataError(f"split '{tc.train_split}' of {data} has no samples")
    steps_per_epoch = len(epoch_batches(len(train_set), tc.batch_size, tc.seed, 0, rank, world))
    total = tc.max_steps if tc.max_steps > 0 else tc.epochs * steps_per_epoch
    return TrainingData(train_set, val_set, AugmentConfig(image=not tc.feature_cache) if tc.augment else None,
                        GTDatabase.from_dataset(train_set) if tc.gt_paste else None,
                        steps_per_epoch, total, int(round(total * (1.0 - tc.gt_paste_fade))))


def start_state(cfg: ModelConfig, variant: str, tc: TrainConfig, device: torch.device, ckpt: dict | None,
                path: Path) -> TrainState:
    """The model seeded with ``tc.seed`` (its camera encoder then loaded from ``tc.image_init``
    where given, its lidar detector from ``tc.lidar_init``, its camera branch from
    ``tc.camera_init``, and its image features frozen with ``tc.image_freeze``) and its AdamW, or
    both as checkpoint ``ckpt`` (read from ``path``) left them, with the torch RNG state."""
    torch.manual_seed(tc.seed)
    if tc.image_freeze and tc.image_init in (TORCHVISION, EFFICIENTNET_LITE0):
        raise ConfigError(f"--image-freeze keeps the ResNet and FPN of an encoder checkpoint; --image-init "
                          f"{tc.image_init} loads a backbone alone and would freeze a seeded FPN")
    model = CLFusionBEV(cfg, variant)
    if tc.lidar_init and ckpt is None:     # a resumed run's checkpoint already holds the weights
        if model.lidar_encoder is None:
            raise ConfigError(f"--lidar-init {tc.lidar_init}: the variant '{variant}' has no lidar encoder")
        print(f"clfbev train: {init_from_lidar_run(model, tc.lidar_init, cfg)}", file=sys.stderr)
    if tc.image_init and ckpt is None:
        if model.camera_encoder is None:
            raise ConfigError(f"--image-init {tc.image_init}: the variant '{variant}' has no camera encoder")
        started = init_camera_encoder(model.camera_encoder, tc.image_init, cfg)
        print(f"clfbev train: camera encoder {started}", file=sys.stderr)
    if tc.camera_init and ckpt is None:    # after --image-init, whose encoder it replaces
        if model.camera_encoder is None:
            raise ConfigError(f"--camera-init {tc.camera_init}: the variant '{variant}' has no camera encoder")
        print(f"clfbev train: {init_from_camera_run(model, tc.camera_init, cfg)}", file=sys.stderr)
    if tc.image_freeze:
        if model.camera_encoder is None:
            raise ConfigError(f"--image-freeze: the variant '{variant}' has no camera encoder")
        model.camera_encoder.freeze_image_features()
    model = model.to(device)
    state = TrainState(model, torch.optim.AdamW(model.parameters(), lr=tc.lr, weight_decay=tc.weight_decay))
    if ckpt is not None:
        restore_state(state, ckpt, f"checkpoint {path}")
        state.best_nds = float(ckpt["best_nds"])
    return state


def restore_state(state: TrainState, ckpt: dict, what: str) -> None:
    """Put the weights, the optimizer, the torch RNG, the step and the epoch of ``ckpt`` into
    ``state``; CheckpointError naming ``what`` when they do not fit."""
    try:
        state.model.load_state_dict(ckpt["model"])
        state.opt.load_state_dict(ckpt["optimizer"])
        torch.set_rng_state(ckpt["torch_rng"])
        state.step, state.epoch = int(ckpt["step"]), int(ckpt["epoch"])
    except (RuntimeError, ValueError, TypeError, KeyError) as e:
        first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise CheckpointError(f"{what} cannot be resumed ({first})") from None


def epoch_loader(loop: Loop, state: TrainState) -> torch.utils.data.DataLoader:
    """This rank's batches of epoch ``state.epoch`` not trained yet (a resumed run starts inside
    the epoch), loaded by ``tc.workers`` processes."""
    tc, data = loop.tc, loop.data
    batches = epoch_batches(len(data.train_set), tc.batch_size, tc.seed, state.epoch, loop.rank, loop.world)
    done_in_epoch = state.step - state.epoch * data.steps_per_epoch
    # The fade works per epoch (an epoch that starts past paste_until pastes nothing), so
    # that a run resumed mid-epoch pastes exactly as the uninterrupted one.
    paste = tc.gt_paste if state.epoch * data.steps_per_epoch < data.paste_until else 0
    samples = EpochSamples(data.train_set, tc.seed, state.epoch, data.augment, state.model.cfg.pc_range,
                           tc.modality_dropout, data.gt_db, paste, tc.gt_paste_balanced, tc.modality_dropout_lidar,
                           tc.modality_dropout_camera)
    collate = TrainingCollate(state.model.cfg, cameras=state.model.camera_encoder is not None)
    return torch.utils.data.DataLoader(samples, batch_sampler=batches[done_in_epoch:], collate_fn=collate,
                                       num_workers=tc.workers)


def train_epoch(loop: Loop, state: TrainState) -> None:
    """The steps of epoch ``state.epoch`` left, stopping at the run's last step."""
    for batch, targets in epoch_loader(loop, state):
        t0 = time.perf_counter()
        lr = lr_at(state.step, loop.data.total, loop.tc)
        losses, grad_norm = optimizer_step(loop, state, batch.to(loop.device), targets.to(loop.device), lr)
        if loop.rank == 0:
            rate = len(batch.sample_tokens) * loop.world / (time.perf_counter() - t0)
            record_step(loop, state, losses, grad_norm, lr, rate)
        if state.step >= loop.data.total:
            break


def compute_losses(loop: Loop, batch: Batch, targets: Targets) -> dict[str, Tensor]:
    """The losses of ``batch`` against its ``targets`` (both on the device): the weighted total
    ``loss`` and its parts, through the DDP-wrapped module; bfloat16 autocast on a GPU."""
    with torch.autocast(loop.device.type, dtype=torch.bfloat16, enabled=loop.device.type == "cuda"):
        return loop.loss_module(batch, targets)


def optimizer_step(loop: Loop, state: TrainState, batch: Batch, targets: Targets,
                   lr: float) -> tuple[dict[str, Tensor], Tensor]:
    """One AdamW step at ``lr`` with the gradient clipped to ``grad_clip``; (losses, gradient
    norm). A non-finite loss or gradient stops every rank together (TrainError)."""
    for group in state.opt.param_groups:
        group["lr"] = lr
    losses = compute_losses(loop, batch, targets)
    loss = losses["loss"]
    kept = f"training stopped; the last good checkpoint {loop.ckpts.last} is kept"
    if not _all_finite(loss.detach(), loop.world):
        raise TrainError(f"non-finite loss ({float(loss.detach()):g}) at step {state.step + 1}: {kept}")
    state.opt.zero_grad(set_to_none=True)
    loss.backward()
    grad_norm = nn.utils.clip_grad_norm_(state.model.parameters(), loop.tc.grad_clip)
    if not _all_finite(grad_norm.detach(), loop.world):
        raise TrainError(f"non-finite gradient at step {state.step + 1}: {kept}")
    state.opt.step()
    state.step += 1
    state.loss = float(loss.detach())
    return losses, grad_norm


def record_step(loop: Loop, state: TrainState, losses: dict[str, Tensor], grad_norm: Tensor, lr: float,
                rate: float) -> None:
    """Rank 0 after a step: its scalars to the logs and the progress bar; last.pt when due."""
    # Every term the loss returns is logged: what it computes is what the metrics show.
    loop.log.log(state.step, state.epoch, {**{f"train/{k}": float(v.detach()) for k, v in losses.items()},
                                           "train/lr": lr, "train/grad_norm": float(grad_norm),
                                           "train/samples_per_s": rate})
    loop.bar.set_postfix(epoch=state.epoch, loss=f"{state.loss:.3f}", samples_s=f"{rate:.2f}")
    loop.bar.update(1)
    # The last step's last.pt is end_epoch's, after precise BatchNorm: one written here would let a
    # run killed before that resume as finished, without it.
    if loop.ckpts.due(state.step) and state.step < loop.data.total:
        loop.ckpts.save(loop.ckpts.last, state)


def end_epoch(loop: Loop, state: TrainState) -> None:
    """Rank 0 after an epoch (or the run's last step): after the last, BatchNorm's statistics
    recomputed; validation, with best.pt when the NDS improves; last.pt."""
    data = loop.data
    if state.step >= data.total:
        precise_batchnorm(state.model, data.train_set, loop.tc, data.augment)
    if data.val_set is not None:
        val = state.last_val = evaluate_model(state.model, data.val_set, loop.run / "val")
        loop.log.log(state.step, state.epoch, {"val/mAP": val["mean_ap"], "val/NDS": val["nd_score"]})
        loop.bar.write(f"epoch {state.epoch} step {state.step}: val mAP {val['mean_ap']:.4f} NDS {val['nd_score']:.4f}")
        if val["nd_score"] > state.best_nds:
            state.best_nds = val["nd_score"]
            loop.ckpts.save(loop.ckpts.best, state)
    loop.ckpts.save(loop.ckpts.last, state)


# ---------------------------------------------------------------- processes

def _all_finite(x: Tensor, world: int) -> bool:
    """Whether ``x`` is finite on every rank (all ranks must stop together)."""
    ok = torch.tensor([float(torch.isfinite(x).all())], device=x.device)
    if world > 1:
        dist.all_reduce(ok, op=dist.ReduceOp.MIN)
    return bool(ok.item() > 0)


def _setup_distributed() -> tuple[int, int, torch.device]:
    """(rank, world size, device). Under torchrun (WORLD_SIZE > 1) joins the process group:
    nccl with one GPU per local rank when CUDA is present, gloo on the CPU."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world > 1:
        if torch.cuda.is_available():
            local = int(os.environ.get("LOCAL_RANK", "0"))
            torch.cuda.set_device(local)
            dist.init_process_group("nccl")
            return dist.get_rank(), world, torch.device("cuda", local)
        dist.init_process_group("gloo")
        return dist.get_rank(), world, torch.device("cpu")
    return 0, 1, torch.device("cuda" if torch.cuda.is_available() else "cpu")
