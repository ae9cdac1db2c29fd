"""The cost of a `camera` training step under each denser supervision of its BEV, as rounds of
whole steps of every arm in one process on one thread, the arms' order rotating round by round.

    python scripts/bench_camera_bev.py DATA base=tiny heatmap=H.yaml distill=D.yaml bilinear=B.yaml [--rounds 6]

Each ARM=CONFIG is a model config (a preset name or a YAML file of overrides, as ``clfbev train
--config``). A whole step is what ``clfbev train --variant camera`` does per batch of 2 with
the ``tiny`` recipe: load and augment the samples (the key sweep alone, all sweeps where the
config distils a lidar teacher, as the training loads them), collate them with their targets
(the teacher's features included), forward, loss, backward, clip, AdamW; the camera encoder
starts from the shipped one. Prints each step's thread CPU time per round, then per arm the
median and its ratio to the first arm's, round by round (median and range), and the share of
the camera BEV's cells that hold a feature (any channel non-zero), per band of range from the
ego, over the rounds' batches: where the lift reaches.
"""
from __future__ import annotations

import argparse
import statistics
import time
from dataclasses import replace

import torch
from torch import nn

from clfbev.augment import AugmentConfig
from clfbev.config_file import load_config
from clfbev.data import NuScenesDetection
from clfbev.model import CLFusionBEV
from clfbev.run.epochs import EpochSamples
from clfbev.run.image_init import init_camera_encoder
from clfbev.run.train_config import SHIPPED
from clfbev.supervision.targets import TrainingCollate, training_loss


BANDS = ((0, 20), (20, 35), (35, 51.2))      # metres from the ego


class Arm:
    """One config of the `camera` variant: its samples, model and optimizer."""

    def __init__(self, data: str, config: str, seed: int = 0) -> None:
        cfg = load_config(config)
        torch.manual_seed(seed)
        self.model = CLFusionBEV(cfg, "camera")
        init_camera_encoder(self.model.camera_encoder, SHIPPED, cfg)
        data_cfg = cfg.data_config() if cfg.cam_distill > 0 else replace(cfg.data_config(), n_sweeps=1)
        self.samples = EpochSamples(NuScenesDetection(data, "v1.0-sim", "sim-train", data_cfg), seed, 0,
                                    AugmentConfig(), cfg.pc_range)
        self.collate = TrainingCollate(cfg)
        self.opt = torch.optim.AdamW(self.model.parameters(), lr=2e-3, weight_decay=1e-2)
        self.model.train()

    def filled(self, indices: list[int]) -> torch.Tensor:
        """(len(BANDS),) the share of the camera BEV's cells with a feature per band of range."""
        batch, _ = self.collate([self.samples[i] for i in indices])
        with torch.no_grad():
            bev = self.model.camera_encoder.lift_splat(batch.images, batch.intrinsics, batch.T_lidar_from_cam,
                                                       batch.img_aug)[0]
        cfg = self.model.cfg
        ny, nx = cfg.cam_bev_shape
        dx, dy = cfg.cam_bev_voxel[:2]
        y = cfg.pc_range[1] + (torch.arange(ny) + 0.5) * dy
        x = cfg.pc_range[0] + (torch.arange(nx) + 0.5) * dx
        r = torch.hypot(y[:, None], x[None, :])
        seen = (bev != 0).any(dim=1).float().mean(dim=0)                 # (ny, nx)
        return torch.stack([seen[(r >= lo) & (r < hi)].mean() for lo, hi in BANDS])

    def step(self, indices: list[int]) -> float:
        """One whole training step on the samples ``indices``; returns the loss."""
        batch, targets = self.collate([self.samples[i] for i in indices])
        loss = training_loss(self.model(batch), targets, self.model.cfg)["loss"]
        self.opt.zero_grad(set_to_none=True)
        loss.backward()
        nn.utils.clip_grad_norm_(self.model.parameters(), 10.0)
        self.opt.step()
        return float(loss.detach())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("data")
    ap.add_argument("arms", nargs="+", metavar="ARM=CONFIG")
    ap.add_argument("--rounds", type=int, default=6)
    args = ap.parse_args()
    torch.set_num_threads(1)
    arms = {name: Arm(args.data, config) for name, config in (a.split("=", 1) for a in args.arms)}
    names = list(arms)
    n = len(next(iter(arms.values())).samples)
    for arm in arms.values():
        arm.step([0, 1])                                  # warm-up, not timed
    rows = []
    for k in range(args.rounds):
        indices = [(2 * k + 2) % n, (2 * k + 3) % n]
        cpu = {}
        for name in names[k % len(names):] + names[:k % len(names)]:
            c = time.thread_time()
            arms[name].step(indices)
            cpu[name] = time.thread_time() - c
        rows.append(cpu)
        print(f"round {k}: " + ", ".join(f"{name} {cpu[name]:.3f}" for name in names) + " s CPU", flush=True)
    base = names[0]
    for name in names:
        ratios = [r[name] / r[base] for r in rows]
        print(f"{name}: median {statistics.median(r[name] for r in rows):.3f} s CPU / step; / {base} median "
              f"{statistics.median(ratios):.3f} (range {min(ratios):.3f}-{max(ratios):.3f})")
    for name in names:
        share = torch.stack([arms[name].filled([(2 * k + 2) % n, (2 * k + 3) % n]) for k in range(args.rounds)]).mean(0)
        print(f"{name}: camera BEV cells with a feature, " + ", ".join(
            f"{lo:g}-{hi:g} m {v:.3f}" for (lo, hi), v in zip(BANDS, share.tolist())))


if __name__ == "__main__":
    main()
