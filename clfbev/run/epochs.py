"""What an epoch feeds the loop: its samples (augmented by a seed of their own), its batches (a
seeded permutation, sharded over the DDP ranks), and the batches that re-estimate BatchNorm.

Everything random is a pure function of ``(seed, epoch, sample index)``: the worker that loads a
sample, the rank that trains it and a resume half-way through the epoch change nothing.
"""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import torch
from torch import nn

from clfbev.augment import AugmentConfig, crop_to_range, random_augment
from clfbev.data import NuScenesDetection, Sample, collate
from clfbev.gt_paste import gt_paste
from clfbev.model import CLFusionBEV
from clfbev.run.train_config import TrainConfig


class EpochSamples(torch.utils.data.Dataset):
    """The training samples of one epoch: sample i is augmented with rng ``(seed, epoch, i)``
    (independent of the worker that loads it), then cropped to the model's range; with
    ``modality_dropout`` p, it then loses its camera or its lidar input with probability p
    (rng ``(seed, epoch, i, 1)``); with ``dropout_lidar`` / ``dropout_camera``, its lidar is
    absent with the one probability, else its cameras with the other (:func:`drop_sensors`, rng
    ``(seed, epoch, i, 3)``). Objects are pasted first, with rng ``(seed, epoch, i, 2)``."""

    def __init__(self, base: NuScenesDetection, seed: int, epoch: int, augment: AugmentConfig | None,
                 pc_range: tuple[float, ...], modality_dropout: float = 0.0, gt_db=None, gt_paste: int = 0,
                 gt_paste_balanced: bool = False, dropout_lidar: float = 0.0, dropout_camera: float = 0.0) -> None:
        self.base, self.seed, self.epoch, self.augment, self.pc_range = base, seed, epoch, augment, pc_range
        self.modality_dropout, self.gt_db, self.gt_paste = modality_dropout, gt_db, gt_paste
        self.gt_paste_balanced = gt_paste_balanced
        self.dropout_lidar, self.dropout_camera = dropout_lidar, dropout_camera

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
                sample = (replace(sample, images=np.zeros_like(sample.images)) if which < 0.5
                          else replace(sample, points=sample.points[:0]))
        if self.dropout_lidar > 0 or self.dropout_camera > 0:
            sample = drop_sensors(sample, np.random.default_rng((self.seed, self.epoch, i, 3)), self.dropout_lidar,
                                  self.dropout_camera)
        return sample


def drop_sensors(sample: Sample, rng: np.random.Generator, p_lidar: float, p_camera: float) -> Sample:
    """Modality dropout: ``sample`` without its lidar (no points, nor pasted flags) with
    probability ``p_lidar``, else without its cameras (every one in ``camera_missing``: the
    model's camera BEV of it is all zeros) with probability ``p_camera``; a sample always keeps
    one sensor. Two draws from ``rng`` whatever the probabilities, so they never shift another
    stream."""
    u_lidar, u_camera = rng.random(2)
    if u_lidar < p_lidar:
        pasted = None if sample.pasted is None else sample.pasted[:0]
        return replace(sample, points=sample.points[:0], pasted=pasted)
    if u_camera < p_camera:
        return replace(sample, camera_missing=np.ones(len(sample.intrinsics), bool))
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
    computed by weights that kept moving: in a short run they lag the weights the evaluation
    uses (precise BN, Wu & Johnson 2021). Deterministic: the batches are those of a fixed epoch
    index no training epoch reaches, so a resumed run gets the same statistics.
    """
    was_training = model.training
    model.train()
    # Those in training mode: a frozen image encoder keeps its statistics.
    norms = [m for m in model.modules() if isinstance(m, nn.modules.batchnorm._BatchNorm) and m.training]
    if not norms or tc.precise_bn_batches <= 0:
        model.train(was_training)
        return
    device = next(model.parameters()).device
    samples = EpochSamples(train_set, tc.seed, PRECISE_BN_EPOCH, augment, model.cfg.pc_range)
    batches = epoch_batches(len(train_set), tc.batch_size, tc.seed, PRECISE_BN_EPOCH, 0, 1)[: tc.precise_bn_batches]
    momenta = [m.momentum for m in norms]
    for m in norms:
        m.reset_running_stats()
        m.momentum = None            # a cumulative average over the batches below
    for indices in batches:
        batch = collate([samples[i] for i in indices], model.cfg).to(device)
        with torch.autocast(device.type, dtype=torch.bfloat16, enabled=device.type == "cuda"):
            model(batch)
    for m, momentum in zip(norms, momenta):
        m.momentum = momentum
    model.train(was_training)
