"""Training the detector, readable top to bottom: data, model, AdamW, warmup + cosine, clipping,
logs, atomic checkpoints, exact resume, validation by the official metric, and DDP. The loop
itself is :mod:`clfbev.run.loop` (shared with ``clfbev pretrain``); this module gives it the
detector's samples, loss and epoch end (precise BatchNorm, validation, ``best.pt``).

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

import os
import sys
from dataclasses import dataclass, replace
from pathlib import Path

import torch
import torch.distributed as dist
from torch import Tensor, nn

from clfbev.augment import AugmentConfig
from clfbev.config import ModelConfig
from clfbev.data import Batch, NuScenesDetection
from clfbev.errors import CheckpointError, ConfigError, DataError
from clfbev.feature_cache import CachedFeatureDataset, FeatureCache, encoder_identity
from clfbev.gt_paste import GTDatabase
from clfbev.model import CLFusionBEV
from clfbev.run.camera_init import init_from_camera_run
from clfbev.run.checkpoint import REQUIRED, RESUME_FIELDS, Checkpoints, check_matches, load_checkpoint
from clfbev.run.efficientnet_init import EFFICIENTNET_LITE0
from clfbev.run.epochs import EpochSamples, precise_batchnorm
from clfbev.run.evaluate import evaluate_model
from clfbev.run.image_init import init_camera_encoder
from clfbev.run.lidar_init import init_from_lidar_run
from clfbev.run.loop import Loop, LoopState, Task, adamw, open_records, restore_state, run_epochs, run_length
from clfbev.run.memory_need import check_memory
from clfbev.run.torchvision_init import TORCHVISION
from clfbev.run.train_config import TrainConfig, check_resumable
from clfbev.supervision.targets import Targets, TrainingCollate, training_loss



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
class TrainState(LoopState):
    """Where a run stands (:class:`clfbev.run.loop.LoopState`) with the best validation NDS (in
    the checkpoint) and the last validation (reported, not saved)."""

    model: CLFusionBEV
    best_nds: float = -1.0
    last_val: dict | None = None


class DetectionTask(Task):
    """The detector's part of the loop: the epoch's augmented samples with their targets, every
    loss term in the logs, and the epoch end of :meth:`end_epoch`."""

    prefix, unit = "train", "samples"

    def __init__(self, data: TrainingData, tc: TrainConfig, cfg: ModelConfig, cameras: bool) -> None:
        self.data, self.tc, self.cfg, self.cameras = data, tc, cfg, cameras

    def epoch_data(self, epoch: int) -> tuple[EpochSamples, TrainingCollate]:
        data, tc = self.data, self.tc
        # The fade works per epoch (an epoch that starts past paste_until pastes nothing), so
        # that a run resumed mid-epoch pastes exactly as the uninterrupted one.
        paste = tc.gt_paste if epoch * data.steps_per_epoch < data.paste_until else 0
        samples = EpochSamples(data.train_set, tc.seed, epoch, data.augment, self.cfg.pc_range, tc.modality_dropout,
                               data.gt_db, paste, tc.gt_paste_balanced, tc.modality_dropout_lidar,
                               tc.modality_dropout_camera)
        return samples, TrainingCollate(self.cfg, cameras=self.cameras)

    def count(self, batch: Batch) -> int:
        return len(batch.sample_tokens)

    def logged(self, losses: dict[str, Tensor]) -> dict[str, Tensor]:
        # Every term the loss returns is logged: what it computes is what the metrics show.
        return losses

    def end_epoch(self, loop: Loop, state: TrainState) -> None:
        """After the last step, BatchNorm's statistics recomputed; validation, with best.pt when
        the NDS improves; last.pt."""
        data = self.data
        if state.step >= loop.total:
            precise_batchnorm(state.model, data.train_set, self.tc, data.augment)
        if data.val_set is not None:
            val = state.last_val = evaluate_model(state.model, data.val_set, loop.run / "val")
            loop.log.log(state.step, state.epoch, {"val/mAP": val["mean_ap"], "val/NDS": val["nd_score"]})
            loop.bar.write(f"epoch {state.epoch} step {state.step}: val mAP {val['mean_ap']:.4f} "
                           f"NDS {val['nd_score']:.4f}")
            if val["nd_score"] > state.best_nds:
                state.best_nds = val["nd_score"]
                loop.ckpts.save(loop.ckpts.best, state)
        loop.ckpts.save(loop.ckpts.last, state)


# ---------------------------------------------------------------- the run

def train(data: str | Path, out: str | Path, cfg: ModelConfig, variant: str, tc: TrainConfig,
          resume: bool = False, progress: bool = True) -> dict:
    """Train ``variant`` of ``cfg`` on ``data`` into the run folder ``out``; returns a summary
    (steps, final loss, best NDS, last validation). See the module docstring for the contract.
    Call under torchrun for DDP (the process group is set up here)."""
    run = Path(out)
    rank, world, device = _setup_distributed()
    check_sensor_settings(tc, variant)
    ckpt = resume_checkpoint(run / "last.pt", cfg, variant, tc, resume)
    check_memory(cfg, variant, tc.batch_size, tc.image_freeze, device)
    training = load_training_data(data, cfg, variant, tc, rank, world)
    state = start_state(cfg, variant, tc, device, ckpt, run / "last.pt")
    if tc.feature_cache:
        training.train_set.cache.check_encoder(encoder_identity(state.model.camera_encoder))
    loss_module: nn.Module = LossModule(state.model)
    if world > 1:
        loss_module = nn.parallel.DistributedDataParallel(loss_module)
    version, log, bar = open_records(run, cfg, variant, tc, rank, world, state.step, training.total, progress)
    task = DetectionTask(training, tc, state.model.cfg, state.model.camera_encoder is not None)
    loop = Loop(run, tc, task, loss_module, device, rank, world, log, bar, Checkpoints(run, cfg, variant, tc, version),
                training.steps_per_epoch, training.total)
    try:
        run_epochs(loop, state)
    finally:
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
    steps_per_epoch, total = run_length(len(train_set), tc, rank, world)
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
    state = TrainState(model, adamw(model, tc))
    if ckpt is not None:
        restore_state(state, ckpt, f"checkpoint {path}")
        state.best_nds = float(ckpt["best_nds"])
    return state


# ---------------------------------------------------------------- processes

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
