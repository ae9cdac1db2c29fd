"""The training loop, readable top to bottom: data, model, AdamW, warmup + cosine, clipping,
logs, atomic checkpoints, exact resume, validation by the official metric, and DDP.

    clfbev train --data DIR --config tiny --variant full --out RUN [--epochs N | --max-steps N]
    torchrun --nproc_per_node 2 -m clfbev.train --data DIR --config tiny --out RUN ...

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

import argparse
import json
import math
import os
import subprocess
import sys
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
import torch
import torch.distributed as dist
from torch import Tensor, nn

from clfbev import atomic
from clfbev.augment import AugmentConfig, crop_to_range, random_augment
from clfbev.checkpoint import CheckpointError, check_matches, load_checkpoint, save_checkpoint
from clfbev.config import VARIANTS, ModelConfig, load_config, preset_of
from clfbev.data import Batch, DataError, NuScenesDetection, Sample, collate
from clfbev.evaluate import evaluate, predict_split, write_results
from clfbev.gt_paste import GTDatabase, gt_paste
from clfbev.model import CLFusionBEV

VERSION = "v1.0-sim"
LOSS_KEYS = ("loss", "loss_cls", "loss_reg", "loss_vel", "loss_dir", "loss_depth")


class TrainError(RuntimeError):
    """Training cannot go on (e.g. a non-finite loss); the message says what was kept."""


@dataclass(frozen=True)
class TrainConfig:
    """Optimisation and bookkeeping settings of one run (the paper's defaults where it has them).

    lr, weight_decay : AdamW (paper: 2e-4, 1e-2). warmup_frac : linear warmup over this share of
    the steps, then cosine decay to ``lr * min_lr_ratio``. grad_clip : max global grad norm.
    batch_size : samples per step and rank. epochs / max_steps : the length (max_steps wins).
    augment : random global + image augmentation. modality_dropout : probability that a training
    sample loses one modality (camera or lidar, even odds): zero images or no points, the input
    a failed sensor gives at test time. gt_paste : objects pasted per sample from a database cut
    from the training split (lidar only, see clfbev/gt_paste.py; 0 = off); gt_paste_fade : share
    of the last steps trained without pasting, on the real distribution; gt_paste_balanced :
    draw the pasted objects class-balanced instead of uniformly. workers : DataLoader
    processes.
    ckpt_minutes : also write ``last.pt`` this often (besides every epoch). save_every_steps :
    also write it every N steps (0: off). val_split : split validated every epoch ('' : none).
    precise_bn_batches : after the last step, BatchNorm's running statistics are recomputed
    over this many training batches (:func:`precise_batchnorm`; 0: off).

    The defaults are the paper's GPU recipe; :func:`recipe` gives the one of a model preset,
    which is what ``clfbev train --config NAME`` starts from.
    """

    train_split: str = "sim-train"
    val_split: str = "sim-val"
    version: str = VERSION
    seed: int = 0
    lr: float = 2e-4
    weight_decay: float = 1e-2
    warmup_frac: float = 0.05
    min_lr_ratio: float = 1e-2
    grad_clip: float = 10.0
    batch_size: int = 2
    epochs: int = 20
    max_steps: int = 0
    augment: bool = True
    modality_dropout: float = 0.0
    gt_paste: int = 0
    gt_paste_fade: float = 0.0
    gt_paste_balanced: bool = False
    workers: int = 0
    ckpt_minutes: float = 10.0
    save_every_steps: int = 0
    precise_bn_batches: int = 32


def recipe(preset: str, variant: str) -> TrainConfig:
    """The training recipe of a model preset ('tiny' or 'paper') for ``variant``.

    ``tiny`` (a 2-core CPU, a few hundred generated samples, from scratch): 8 epochs at batch 2,
    AdamW at a peak lr of 2e-3 with 5% warmup and cosine decay (docs/benchmarks.md has the
    measured comparison: 1e-3 and 4e-3 score alike; PointPillars on nuScenes learns at 3e-3 and
    not at 1.5e-4), augmentation on, and 10 objects pasted per sample (SECOND's GT sampling, the
    largest gain on small sets), none in the last 20% of the steps. The ``camera`` variant pastes nothing: the pasted objects
    exist only in the lidar, and a camera model would be taught to find objects with no pixels.
    ``paper``: the paper's AdamW at 2e-4, weight decay 1e-2, 20 epochs.
    """
    if preset == "paper":
        return TrainConfig()
    if preset != "tiny":
        raise ValueError(f"no training recipe for preset {preset!r} (have: tiny, paper)")
    return TrainConfig(lr=2e-3, epochs=8, gt_paste=0 if variant == "camera" else 10, gt_paste_fade=0.2)


def lr_at(step: int, total: int, tc: TrainConfig) -> float:
    """Learning rate of optimizer step ``step`` (0-based) of ``total``: linear warmup from
    ``lr / 10`` to ``lr`` over ``warmup_frac`` of the steps, then cosine to ``lr * min_lr_ratio``."""
    warm = max(1, int(round(tc.warmup_frac * total)))
    if step < warm:
        return tc.lr * (0.1 + 0.9 * step / warm)
    t = (step - warm) / max(1, total - warm)
    floor = tc.lr * tc.min_lr_ratio
    return floor + 0.5 * (tc.lr - floor) * (1.0 + math.cos(math.pi * min(1.0, t)))


# ---------------------------------------------------------------- data

class EpochSamples(torch.utils.data.Dataset):
    """The training samples of one epoch: sample i is augmented with rng ``(seed, epoch, i)``
    (independent of the worker that loads it), then cropped to the model's range; with
    ``modality_dropout`` p, it then loses its camera or its lidar input with probability p
    (rng ``(seed, epoch, i, 1)``)."""

    def __init__(self, base: NuScenesDetection, seed: int, epoch: int, augment: AugmentConfig | None,
                 pc_range: tuple[float, ...], modality_dropout: float = 0.0, gt_db=None, gt_paste: int = 0,
                 gt_paste_balanced: bool = False) -> None:
        self.base, self.seed, self.epoch, self.augment, self.pc_range = base, seed, epoch, augment, pc_range
        self.modality_dropout, self.gt_db, self.gt_paste = modality_dropout, gt_db, gt_paste
        self.gt_paste_balanced = gt_paste_balanced

    def __len__(self) -> int:
        return len(self.base)

    def __getitem__(self, i: int) -> Sample:
        sample = self.base[i]
        if self.gt_paste and self.gt_db is not None:     # before the global transform, as SECOND does
            sample = gt_paste(sample, self.gt_db, self.gt_paste, np.random.default_rng((self.seed, self.epoch, i, 2)),
                              self.gt_paste_balanced)
        if self.augment is not None:
            sample = random_augment(sample, np.random.default_rng((self.seed, self.epoch, i)), self.augment)
            sample = crop_to_range(sample, self.pc_range)
        if self.modality_dropout > 0:
            u, which = np.random.default_rng((self.seed, self.epoch, i, 1)).random(2)
            if u < self.modality_dropout:
                sample = (replace(sample, images=torch.zeros_like(sample.images)) if which < 0.5
                          else replace(sample, points=sample.points[:0]))
        return sample


def epoch_batches(n: int, batch_size: int, seed: int, epoch: int, rank: int, world: int) -> list[list[int]]:
    """Rank ``rank``'s batches of sample indices for ``epoch``: a seeded permutation of ``n``,
    padded by wrapping to a multiple of ``world * batch_size``, every ``world``-th index."""
    g = torch.Generator().manual_seed(seed * 1_000_003 + epoch)
    order = torch.randperm(n, generator=g).tolist()
    per_step = world * batch_size
    total = math.ceil(n / per_step) * per_step
    order = (order * math.ceil(total / n))[:total]
    mine = order[rank::world]
    return [mine[i:i + batch_size] for i in range(0, len(mine), batch_size)]


# The epoch index whose samples re-estimate BatchNorm (no training epoch reaches it).
PRECISE_BN_EPOCH = 1_000_000


@torch.no_grad()
def precise_batchnorm(model: CLFusionBEV, train_set: NuScenesDetection, tc: TrainConfig,
                      augment: AugmentConfig | None) -> None:
    """Recompute every BatchNorm's running statistics with the final weights, as the exact
    average over ``tc.precise_bn_batches`` training batches (augmented as in training, nothing
    pasted, as in the fade's last steps).

    With momentum 0.01 (SECOND's) the running statistics average the last few hundred steps,
    computed by weights that kept moving: in a run of a few hundred steps they lag the weights
    the evaluation uses (precise BN, Wu & Johnson 2021). Deterministic: the batches are those of
    a fixed epoch index no training epoch reaches, so a resumed run gets the same statistics.
    """
    norms = [m for m in model.modules() if isinstance(m, nn.modules.batchnorm._BatchNorm)]
    if not norms or tc.precise_bn_batches <= 0:
        return
    device = next(model.parameters()).device
    samples = EpochSamples(train_set, tc.seed, PRECISE_BN_EPOCH, augment, model.cfg.pc_range)
    batches = epoch_batches(len(train_set), tc.batch_size, tc.seed, PRECISE_BN_EPOCH, 0, 1)[: tc.precise_bn_batches]
    momenta = [m.momentum for m in norms]
    for m in norms:
        m.reset_running_stats()
        m.momentum = None            # a cumulative average over the batches below
    was_training = model.training
    model.train()
    for indices in batches:
        batch = collate([samples[i] for i in indices]).to(device)
        with torch.autocast(device.type, dtype=torch.bfloat16, enabled=device.type == "cuda"):
            model(batch)
    for m, momentum in zip(norms, momenta):
        m.momentum = momentum
    model.train(was_training)


class LossModule(nn.Module):
    """``forward(batch) -> loss dict``, so that DDP's forward wraps the whole loss computation."""

    def __init__(self, model: CLFusionBEV) -> None:
        super().__init__()
        self.model = model

    def forward(self, batch: Batch) -> dict[str, Tensor]:
        return self.model.loss(batch)


# ---------------------------------------------------------------- bookkeeping

def code_version(here: Path | None = None) -> str:
    """``git describe`` of the source tree, ``-dirty`` when a tracked file of the package folder
    ``here`` (default: this package) is modified: a changed doc or script elsewhere in the tree
    does not change a run. Else the package version."""
    here = Path(__file__).resolve().parent if here is None else here
    try:
        out = subprocess.run(["git", "describe", "--always"], cwd=here, capture_output=True, text=True, timeout=10)
        changed = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no", "--", "."], cwd=here,
                                 capture_output=True, text=True, timeout=10)
        if out.returncode == 0 and out.stdout.strip() and changed.returncode == 0:
            return out.stdout.strip() + ("-dirty" if changed.stdout.strip() else "")
    except (OSError, subprocess.SubprocessError):
        pass
    from importlib.metadata import PackageNotFoundError, version
    try:
        return version("clfusionbev")
    except PackageNotFoundError:
        return "unknown"


class ScalarLog:
    """Scalars to ``RUN/metrics.jsonl`` (one JSON object per line) and TensorBoard ``RUN/tb``.
    On resume from step k, lines of steps > k (written after the checkpoint) are dropped and
    TensorBoard purges its events after k, so the logs read as one uninterrupted run."""

    def __init__(self, run: Path, resume_step: int) -> None:
        from torch.utils.tensorboard import SummaryWriter
        self.path = run / "metrics.jsonl"
        if self.path.exists():
            keep = [ln for ln in self.path.read_text().splitlines()
                    if ln.strip() and _complete_json(ln) and json.loads(ln)["step"] <= resume_step]
            atomic.write_text(self.path, "".join(ln + "\n" for ln in keep))
        self.file = self.path.open("a")
        self.tb = SummaryWriter(str(run / "tb"), purge_step=resume_step + 1 if resume_step else None)

    def log(self, step: int, epoch: int, scalars: dict[str, float]) -> None:
        self.file.write(json.dumps({"step": step, "epoch": epoch, **scalars}) + "\n")
        self.file.flush()
        for k, v in scalars.items():
            self.tb.add_scalar(k, v, step)

    def close(self) -> None:
        self.file.close()
        self.tb.close()


def _complete_json(line: str) -> bool:
    try:
        return isinstance(json.loads(line), dict)
    except ValueError:
        return False          # a line torn by a kill


# ---------------------------------------------------------------- validation

def validate(model: CLFusionBEV, dataset: NuScenesDetection, out_dir: Path) -> dict:
    """mAP / NDS of ``model`` on ``dataset`` through the official DetectionEval; the devkit's
    summary dict (also written to ``out_dir``)."""
    was_training = model.training
    results = predict_split(model, dataset)
    path = write_results(out_dir / "results.json", results)
    summary = evaluate(dataset.nusc, path, dataset.split, out_dir, model.cfg.class_names)
    model.train(was_training)
    return summary


# ---------------------------------------------------------------- the loop

def train(data: str | Path, out: str | Path, cfg: ModelConfig, variant: str, tc: TrainConfig,
          resume: bool = False, progress: bool = True) -> dict:
    """Train ``variant`` of ``cfg`` on ``data`` into the run folder ``out``; returns a summary
    (steps, final loss, best NDS, last validation). See the module docstring for the contract.
    Call under torchrun for DDP (the process group is set up here)."""
    run = Path(out)
    rank, world, device = _setup_distributed()
    is_main = rank == 0
    last_path, best_path = run / "last.pt", run / "best.pt"

    # ---- resume or start
    ckpt = None
    if last_path.exists():
        if not resume:
            raise CheckpointError(f"{last_path} exists: pass --resume to continue that run, or choose another --out")
        ckpt = load_checkpoint(last_path)
        check_matches(ckpt, last_path, cfg, variant)
        # Settings that change the result must match; how often to save and how many loader
        # processes do not.
        saved = asdict(TrainConfig(**ckpt["train"]))
        diff = [k for k, v in asdict(tc).items() if saved[k] != v and k not in ("ckpt_minutes", "workers")]
        if diff:
            raise CheckpointError(f"{last_path} was trained with other settings (differs in: {', '.join(diff)})")

    # ---- data
    train_set = NuScenesDetection(data, tc.version, tc.train_split, cfg.data_config())
    val_set = NuScenesDetection(data, tc.version, tc.val_split, cfg.data_config()) if (tc.val_split and is_main) else None
    if len(train_set) == 0:
        raise DataError(f"split '{tc.train_split}' of {data} has no samples")
    steps_per_epoch = len(epoch_batches(len(train_set), tc.batch_size, tc.seed, 0, rank, world))
    total = tc.max_steps if tc.max_steps > 0 else tc.epochs * steps_per_epoch
    augment = AugmentConfig() if tc.augment else None
    gt_db = GTDatabase.from_dataset(train_set) if tc.gt_paste else None
    paste_until = int(round(total * (1.0 - tc.gt_paste_fade)))

    # ---- model and optimizer
    torch.manual_seed(tc.seed)
    model = CLFusionBEV(cfg, variant).to(device)
    opt = torch.optim.AdamW(model.parameters(), lr=tc.lr, weight_decay=tc.weight_decay)
    step, epoch, best_nds = 0, 0, -1.0
    if ckpt is not None:
        model.load_state_dict(ckpt["model"])
        opt.load_state_dict(ckpt["optimizer"])
        step, epoch, best_nds = int(ckpt["step"]), int(ckpt["epoch"]), float(ckpt["best_nds"])
        torch.set_rng_state(ckpt["torch_rng"])
    loss_module: nn.Module = LossModule(model)
    if world > 1:
        loss_module = nn.parallel.DistributedDataParallel(loss_module)
    use_amp = device.type == "cuda"

    log = None
    version = code_version()          # a git subprocess: once per run, not at every checkpoint
    if is_main:
        run.mkdir(parents=True, exist_ok=True)
        atomic.write_json(run / "run.json", {"config": cfg.to_dict(), "variant": variant, "train": asdict(tc),
                                             "world_size": world, "code_version": version,
                                             "argv": sys.argv, "resumed_at_step": step})
        log = ScalarLog(run, step)

    def save(path: Path) -> None:
        save_checkpoint(path, {
            "model": model.state_dict(), "optimizer": opt.state_dict(), "config": cfg.to_dict(),
            "variant": variant, "train": asdict(tc), "step": step, "epoch": epoch,
            "best_nds": best_nds, "torch_rng": torch.get_rng_state(), "code_version": version,
        })

    from tqdm import tqdm
    bar = tqdm(total=total, initial=step, disable=not (is_main and progress), unit="step", dynamic_ncols=True)
    last_save, last_val, loss_value = time.monotonic(), None, float("nan")
    model.train()
    try:
        while step < total:
            batches = epoch_batches(len(train_set), tc.batch_size, tc.seed, epoch, rank, world)
            done_in_epoch = step - epoch * steps_per_epoch
            # The fade works per epoch (an epoch that starts past paste_until pastes nothing), so
            # that a run resumed mid-epoch pastes exactly as the uninterrupted one.
            paste = tc.gt_paste if epoch * steps_per_epoch < paste_until else 0
            epoch_set = EpochSamples(train_set, tc.seed, epoch, augment, cfg.pc_range, tc.modality_dropout,
                                     gt_db, paste, tc.gt_paste_balanced)
            loader = torch.utils.data.DataLoader(epoch_set, batch_sampler=batches[done_in_epoch:],
                                                 collate_fn=collate, num_workers=tc.workers)
            for batch in loader:
                t0 = time.perf_counter()
                lr = lr_at(step, total, tc)
                for group in opt.param_groups:
                    group["lr"] = lr
                batch = batch.to(device)
                with torch.autocast(device.type, dtype=torch.bfloat16, enabled=use_amp):
                    losses = loss_module(batch)
                loss = losses["loss"]
                if not _all_finite(loss.detach(), world):
                    raise TrainError(f"non-finite loss ({float(loss.detach()):g}) at step {step + 1}: training stopped; "
                                     f"the last good checkpoint {last_path} is kept")
                opt.zero_grad(set_to_none=True)
                loss.backward()
                grad_norm = nn.utils.clip_grad_norm_(model.parameters(), tc.grad_clip)
                if not _all_finite(grad_norm.detach(), world):
                    raise TrainError(f"non-finite gradient at step {step + 1}: training stopped; "
                                     f"the last good checkpoint {last_path} is kept")
                opt.step()
                step += 1
                loss_value = float(loss.detach())
                if is_main:
                    rate = len(batch.sample_tokens) * world / (time.perf_counter() - t0)
                    log.log(step, epoch, {**{f"train/{k}": float(losses[k].detach()) for k in LOSS_KEYS if k in losses},
                                          "train/lr": lr, "train/grad_norm": float(grad_norm),
                                          "train/samples_per_s": rate})
                    bar.set_postfix(epoch=epoch, loss=f"{loss_value:.3f}", samples_s=f"{rate:.2f}")
                    bar.update(1)
                    timed = time.monotonic() - last_save > tc.ckpt_minutes * 60
                    if (tc.save_every_steps and step % tc.save_every_steps == 0) or timed:
                        save(last_path)
                        last_save = time.monotonic()
                if step >= total:
                    break
            if step == (epoch + 1) * steps_per_epoch:
                epoch += 1
            if is_main:
                if step >= total:
                    precise_batchnorm(model, train_set, tc, augment)
                if val_set is not None:
                    last_val = validate(model, val_set, run / "val")
                    log.log(step, epoch, {"val/mAP": last_val["mean_ap"], "val/NDS": last_val["nd_score"]})
                    bar.write(f"epoch {epoch} step {step}: val mAP {last_val['mean_ap']:.4f} NDS {last_val['nd_score']:.4f}")
                    if last_val["nd_score"] > best_nds:
                        best_nds = last_val["nd_score"]
                        save(best_path)
                save(last_path)
                last_save = time.monotonic()
            if world > 1:
                dist.barrier()
    finally:
        bar.close()
        if log is not None:
            log.close()
        if world > 1 and dist.is_initialized():
            dist.destroy_process_group()
    return {"steps": step, "epochs": epoch, "loss": loss_value, "best_nds": best_nds, "val": last_val}


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


# ---------------------------------------------------------------- command line

def add_arguments(p: argparse.ArgumentParser) -> None:
    """The ``clfbev train`` options (shared with ``python -m clfbev.train`` for torchrun). Every
    optimisation option defaults to the recipe of the ``--config`` preset (:func:`recipe`)."""
    d = TrainConfig()
    p.add_argument("--data", required=True, type=Path, help="nuScenes-format dataroot (e.g. from `simgen make`)")
    p.add_argument("--config", default="tiny",
                   help="model config: 'tiny' (CPU), 'paper', or a YAML file of overrides; also picks the recipe")
    p.add_argument("--variant", default="full", choices=VARIANTS,
                   help="lidar | camera | concat (BEVFusion-style) | mcm (+cross-attention) | full (+BSM)")
    p.add_argument("--out", required=True, type=Path, help="run folder: last.pt, best.pt, run.json, metrics.jsonl, tb/")
    p.add_argument("--split", dest="train_split", default=d.train_split, help="training split (splits.json or official)")
    p.add_argument("--val-split", default=d.val_split, help="split validated every epoch; '' to skip validation")
    p.add_argument("--version", default=d.version, help="table folder under the dataroot")
    p.add_argument("--seed", type=int, default=d.seed)
    rec = "[recipe]"
    length = p.add_mutually_exclusive_group()
    length.add_argument("--epochs", type=int, default=None, help=f"epochs {rec}")
    length.add_argument("--max-steps", type=int, default=0, help="optimizer steps (overrides --epochs)")
    p.add_argument("--batch-size", type=int, default=None, help=f"samples per step and process {rec}")
    p.add_argument("--lr", type=float, default=None, help=f"peak AdamW learning rate {rec}: tiny 2e-3, paper 2e-4")
    p.add_argument("--weight-decay", type=float, default=None, help=rec)
    p.add_argument("--warmup-frac", type=float, default=None, help=f"share of steps of linear warmup {rec}")
    p.add_argument("--grad-clip", type=float, default=None, help=f"max global gradient norm {rec}")
    p.add_argument("--no-augment", dest="augment", action="store_false", default=None, help="no random augmentation")
    p.add_argument("--modality-dropout", type=float, default=None, metavar="P",
                   help=f"drop the camera or the lidar input of a sample with probability P (robust fusion) {rec}")
    p.add_argument("--gt-paste", type=int, default=None, metavar="N",
                   help=f"paste up to N objects per sample from other training samples (lidar only; 0 = off) {rec}")
    p.add_argument("--gt-paste-fade", type=float, default=None, metavar="F",
                   help=f"train the last share F of the steps without pasting {rec}")
    p.add_argument("--gt-paste-balanced", action=argparse.BooleanOptionalAction, default=None,
                   help=f"draw the pasted objects class-balanced (every class as often) instead of uniformly {rec}")
    p.add_argument("--no-depth-loss", action="store_true",
                   help="no lidar supervision of the camera's depth (the ablation; sets loss.depth = 0)")
    p.add_argument("--workers", type=int, default=d.workers, help="DataLoader worker processes")
    p.add_argument("--ckpt-minutes", type=float, default=d.ckpt_minutes, help="also checkpoint this often")
    p.add_argument("--save-every-steps", type=int, default=0, help="also checkpoint every N steps")
    p.add_argument("--threads", type=int, default=0, help="torch CPU threads (0: torch's default)")
    p.add_argument("--resume", action="store_true", help="continue the run in --out from its last.pt")
    p.add_argument("--quiet", action="store_true", help="no progress bar")


# The options whose default is the recipe's value (argparse dest = TrainConfig field).
_RECIPE_OPTIONS = ("epochs", "batch_size", "lr", "weight_decay", "warmup_frac", "grad_clip", "augment",
                   "modality_dropout", "gt_paste", "gt_paste_fade", "gt_paste_balanced")


def train_config_from(args: argparse.Namespace) -> TrainConfig:
    """TrainConfig of parsed arguments: the recipe of ``--config``'s preset for ``--variant``,
    with the options given on the command line; ValueError for out-of-range values."""
    base = recipe(preset_of(args.config), args.variant)
    given = {name: getattr(args, name) for name in _RECIPE_OPTIONS if getattr(args, name) is not None}
    tc = replace(base, train_split=args.train_split, val_split=args.val_split, version=args.version, seed=args.seed,
                 max_steps=args.max_steps, workers=args.workers, ckpt_minutes=args.ckpt_minutes,
                 save_every_steps=args.save_every_steps, **given)
    checks = {"--batch-size": tc.batch_size >= 1, "--epochs": tc.epochs >= 1, "--max-steps": tc.max_steps >= 0,
              "--lr": tc.lr > 0, "--weight-decay": tc.weight_decay >= 0, "--grad-clip": tc.grad_clip > 0,
              "--warmup-frac": 0 <= tc.warmup_frac < 1, "--workers": tc.workers >= 0,
              "--ckpt-minutes": tc.ckpt_minutes > 0, "--modality-dropout": 0 <= tc.modality_dropout <= 1,
              "--gt-paste": tc.gt_paste >= 0, "--gt-paste-fade": 0 <= tc.gt_paste_fade <= 1,
              "--save-every-steps": tc.save_every_steps >= 0}
    bad = [k for k, ok in checks.items() if not ok]
    if bad:
        raise ValueError(f"out-of-range value for {', '.join(bad)}")
    return tc


def run_from_args(args: argparse.Namespace) -> dict:
    if args.threads:
        torch.set_num_threads(args.threads)
    cfg = load_config(args.config)
    if args.no_depth_loss:
        cfg = replace(cfg, loss=replace(cfg.loss, depth=0.0))
    summary = train(args.data, args.out, cfg, args.variant, train_config_from(args), resume=args.resume,
                    progress=not args.quiet)
    if int(os.environ.get("RANK", "0")) == 0:
        best = f", best val NDS {summary['best_nds']:.4f}" if summary["best_nds"] >= 0 else ""
        # A resumed run that was already finished trains no step, so it has no loss of its own.
        loss = f", final loss {summary['loss']:.4f}" if math.isfinite(summary["loss"]) else " (nothing left to train)"
        print(f"trained {summary['steps']} steps{loss}{best}; checkpoints in {args.out}")
    return summary


def main(argv: list[str] | None = None) -> int:
    """``python -m clfbev.train`` (what torchrun runs); same options and errors as ``clfbev train``."""
    from clfbev.cli import run_guarded
    p = argparse.ArgumentParser(prog="clfbev.train", description=__doc__.split("\n\n")[0])
    add_arguments(p)
    args = p.parse_args(argv)
    return run_guarded(lambda: run_from_args(args))


if __name__ == "__main__":
    sys.exit(main())
