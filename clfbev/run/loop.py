"""The training loop that ``clfbev train`` and ``clfbev pretrain`` share: epochs of seeded
batches, warmup + cosine learning rate, AdamW steps with clipping, scalar logs, progress bar and
``last.pt`` when due. What differs between them is a :class:`Task`: its samples and collate, what
it logs, and what ends its epochs.

Resume contract: everything random is a pure function of ``(seed, epoch, sample index)`` or is
saved in the checkpoint (weights, optimizer, step, epoch, torch RNG state), and the learning
rate is a pure function of the step. A run resumed at step k skips the first k batches of its
epoch's (known) order without loading them and recomputes exactly the steps it lost.

DDP: rank r of W takes every W-th index of the epoch's order (:func:`epoch_batches`); every rank
runs the steps, rank 0 alone logs and ends the epochs, and the others wait for it.
"""
from __future__ import annotations

import math
import time
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import torch
import torch.distributed as dist
from torch import Tensor, nn

from clfbev.config import ModelConfig
from clfbev.errors import CheckpointError, TrainError
from clfbev.run.checkpoint import Checkpoints
from clfbev.run.epochs import epoch_batches
from clfbev.run.run_log import ScalarLog, code_version, write_run_json
from clfbev.run.train_config import OptimConfig


def lr_at(step: int, total: int, oc: OptimConfig) -> float:
    """Learning rate of optimizer step ``step`` (0-based) of ``total``: linear warmup from
    ``lr / 10`` to ``lr`` over ``warmup_frac`` of the steps, then cosine to ``lr * min_lr_ratio``."""
    warm = max(1, int(round(oc.warmup_frac * total)))
    if step < warm:
        return oc.lr * (0.1 + 0.9 * step / warm)
    t = (step - warm) / max(1, total - warm)
    floor = oc.lr * oc.min_lr_ratio
    return floor + 0.5 * (oc.lr - floor) * (1.0 + math.cos(math.pi * min(1.0, t)))


def adamw(model: nn.Module, oc: OptimConfig) -> torch.optim.AdamW:
    """The AdamW of ``model`` (its learning rate is set at every step, :func:`lr_at`)."""
    return torch.optim.AdamW(model.parameters(), lr=oc.lr, weight_decay=oc.weight_decay)


def run_length(n: int, oc: OptimConfig, rank: int, world: int) -> tuple[int, int]:
    """(optimizer steps per epoch, steps of the whole run) for ``n`` samples."""
    steps_per_epoch = len(epoch_batches(n, oc.batch_size, oc.seed, 0, rank, world))
    return steps_per_epoch, oc.max_steps if oc.max_steps > 0 else oc.epochs * steps_per_epoch


# ---------------------------------------------------------------- what a run is made of

@dataclass
class LoopState:
    """Where a run stands (what its checkpoint holds besides the settings), and the last loss
    (reported, not saved)."""

    model: nn.Module
    opt: torch.optim.Optimizer
    step: int = 0
    epoch: int = 0              # epochs fully done
    loss: float = math.nan


class Task(ABC):
    """What one kind of training brings to the loop: its samples, what it logs, how its epochs end."""

    prefix: ClassVar[str]       # of its scalars in the logs: "train" gives "train/loss"
    unit: ClassVar[str]         # what its throughput counts: "samples" gives "train/samples_per_s"

    @abstractmethod
    def epoch_data(self, epoch: int) -> tuple[torch.utils.data.Dataset, Callable]:
        """Epoch ``epoch``'s samples (item i is sample i, anything random in it drawn from
        ``(seed, epoch, i)``) and the ``collate_fn`` making (batch, targets) of a list of them."""

    @abstractmethod
    def count(self, batch) -> int:
        """How many ``unit`` one rank's ``batch`` holds."""

    @abstractmethod
    def logged(self, losses: dict[str, Tensor]) -> dict[str, Tensor]:
        """The terms of a step's ``losses`` written to the logs, in their order."""

    @abstractmethod
    def end_epoch(self, loop: Loop, state: LoopState) -> None:
        """Rank 0 after an epoch or the run's last step; writes ``last.pt``."""


@dataclass
class Loop:
    """The fixed parts of one training process; ``log`` is None on ranks other than 0.
    ``loss_module(batch, targets)`` returns the loss dict, the weighted total as ``loss``."""

    run: Path
    optim: OptimConfig
    task: Task
    loss_module: nn.Module
    device: torch.device
    rank: int
    world: int
    log: ScalarLog | None
    bar: object                 # tqdm
    ckpts: Checkpoints
    steps_per_epoch: int
    total: int                  # optimizer steps of the whole run


def open_records(run: Path, cfg: ModelConfig, variant: str, oc: OptimConfig, rank: int, world: int, step: int,
                 total: int, progress: bool) -> tuple[str, ScalarLog | None, object]:
    """(code version, scalar log, progress bar) of a run (re)starting at ``step``: rank 0 writes
    ``run.json`` and opens the log; the bar shows on rank 0 with ``progress``."""
    from tqdm import tqdm
    version = code_version()          # a git subprocess: once per run, not at every checkpoint
    log = None
    if rank == 0:
        run.mkdir(parents=True, exist_ok=True)
        write_run_json(run, cfg, variant, oc, world, version, step)
        log = ScalarLog(run, step)
    bar = tqdm(total=total, initial=step, disable=not (rank == 0 and progress), unit="step", dynamic_ncols=True)
    return version, log, bar


def restore_state(state: LoopState, ckpt: dict, what: str) -> None:
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


# ---------------------------------------------------------------- the loop

def run_epochs(loop: Loop, state: LoopState) -> None:
    """Train from ``state`` to step ``loop.total``: the epochs' steps on every rank, then the
    task's epoch end on rank 0 while the others wait. Closes the progress bar and the log."""
    state.model.train()
    try:
        while state.step < loop.total:
            train_epoch(loop, state)
            if state.step == (state.epoch + 1) * loop.steps_per_epoch:
                state.epoch += 1
            if loop.rank == 0:
                loop.task.end_epoch(loop, state)
            if loop.world > 1:
                dist.barrier()
    finally:
        loop.bar.close()
        if loop.log is not None:
            loop.log.close()


def epoch_loader(loop: Loop, state: LoopState) -> torch.utils.data.DataLoader:
    """This rank's batches of epoch ``state.epoch`` not trained yet (a resumed run starts inside
    the epoch), loaded by ``workers`` processes."""
    oc = loop.optim
    samples, collate = loop.task.epoch_data(state.epoch)
    batches = epoch_batches(len(samples), oc.batch_size, oc.seed, state.epoch, loop.rank, loop.world)
    done_in_epoch = state.step - state.epoch * loop.steps_per_epoch
    return torch.utils.data.DataLoader(samples, batch_sampler=batches[done_in_epoch:], collate_fn=collate,
                                       num_workers=oc.workers)


def train_epoch(loop: Loop, state: LoopState) -> None:
    """The steps of epoch ``state.epoch`` left, stopping at the run's last step."""
    for batch, targets in epoch_loader(loop, state):
        t0 = time.perf_counter()
        lr = lr_at(state.step, loop.total, loop.optim)
        losses, grad_norm = optimizer_step(loop, state, batch.to(loop.device), targets.to(loop.device), lr)
        if loop.rank == 0:
            rate = loop.task.count(batch) * loop.world / (time.perf_counter() - t0)
            record_step(loop, state, losses, grad_norm, lr, rate)
        if state.step >= loop.total:
            break


def compute_losses(loop: Loop, batch, targets) -> dict[str, Tensor]:
    """The losses of ``batch`` against its ``targets`` (both on the device): the weighted total
    ``loss`` and its parts, through the (DDP-wrapped) loss module; bfloat16 autocast on a GPU."""
    with torch.autocast(loop.device.type, dtype=torch.bfloat16, enabled=loop.device.type == "cuda"):
        return loop.loss_module(batch, targets)


def optimizer_step(loop: Loop, state: LoopState, batch, targets, lr: float) -> tuple[dict[str, Tensor], Tensor]:
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
    grad_norm = nn.utils.clip_grad_norm_(state.model.parameters(), loop.optim.grad_clip)
    if not _all_finite(grad_norm.detach(), loop.world):
        raise TrainError(f"non-finite gradient at step {state.step + 1}: {kept}")
    state.opt.step()
    state.step += 1
    state.loss = float(loss.detach())
    return losses, grad_norm


def record_step(loop: Loop, state: LoopState, losses: dict[str, Tensor], grad_norm: Tensor, lr: float,
                rate: float) -> None:
    """Rank 0 after a step: the task's scalars to the logs and the progress bar; last.pt when due."""
    task = loop.task
    loop.log.log(state.step, state.epoch, {**{f"{task.prefix}/{k}": float(v.detach())
                                              for k, v in task.logged(losses).items()},
                                           f"{task.prefix}/lr": lr, f"{task.prefix}/grad_norm": float(grad_norm),
                                           f"{task.prefix}/{task.unit}_per_s": rate})
    loop.bar.set_postfix({"epoch": state.epoch, "loss": f"{state.loss:.3f}", f"{task.unit}_s": f"{rate:.2f}"})
    loop.bar.update(1)
    # The last step's last.pt is the epoch end's (for the detector, after precise BatchNorm): one
    # written here would let a run killed before that resume as finished, without it.
    if loop.ckpts.due(state.step) and state.step < loop.total:
        loop.ckpts.save(loop.ckpts.last, state)


def _all_finite(x: Tensor, world: int) -> bool:
    """Whether ``x`` is finite on every rank (all ranks must stop together)."""
    ok = torch.tensor([float(torch.isfinite(x).all())], device=x.device)
    if world > 1:
        dist.all_reduce(ok, op=dist.ReduceOp.MIN)
    return bool(ok.item() > 0)
