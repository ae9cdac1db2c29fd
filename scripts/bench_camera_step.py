"""The cost of a `camera` training step: today's recipe (images decoded and augmented, the
shipped encoder fine-tuned, every lidar sweep loaded) against the camera stage's (the frozen
encoder's cached features, the BEV augmented, the key sweep alone, as `clfbev train
--feature-cache` loads it), as alternating pairs of whole steps in one process on one thread.
A third arm, the recipe with the key sweep alone (what `clfbev train --variant camera` now
loads), tells the loading's share from the cache's; it takes its turn in each round.

    python scripts/bench_camera_step.py DATA CACHE [--pairs 8] [--profile]
    python scripts/bench_camera_step.py DATA CACHE --base-tree DIR [--pairs 8]

``--base-tree DIR`` (a copy of the package as it was, e.g. ``git archive REV clfbev | tar -x -C
DIR``) measures today's step with today's code instead: each round runs the ``today`` arm in a
process importing the package from DIR and the ``cached`` arm in one importing this checkout,
``--steps`` steps each after a warm-up step, the order alternating round by round.

A whole step is what the training loop does per batch of 2: load and augment the samples
(:class:`clfbev.run.epochs.EpochSamples`), collate them with their targets
(:class:`clfbev.supervision.targets.TrainingCollate`), forward, loss, backward, clip, AdamW.
CACHE is ``clfbev cache-features --data DATA --out CACHE`` (the shipped encoder). Each step's
thread CPU time and wall time are printed per pair, then the medians and the ratio.
``--profile`` adds torch.profiler's table of the cached step's operators (and the loading and
targets, as named ranges) over 4 steps.
"""
from __future__ import annotations

import argparse
import statistics
import time
from dataclasses import replace

import torch
from torch import nn

import json
import os
import subprocess
import sys

from clfbev.augment import AugmentConfig
from clfbev.config import tiny
from clfbev.data import NuScenesDetection
from clfbev.model import CLFusionBEV
from clfbev.run.epochs import EpochSamples
from clfbev.run.image_init import init_camera_encoder
from clfbev.run.train_config import SHIPPED
from clfbev.supervision.targets import TrainingCollate, training_loss


class Arm:
    """One way of training the `camera` variant: its samples, model and optimizer."""

    def __init__(self, data: str, cache: str | None, sweeps: int, seed: int = 0) -> None:
        cfg = tiny()
        torch.manual_seed(seed)
        self.model = CLFusionBEV(cfg, "camera")
        init_camera_encoder(self.model.camera_encoder, SHIPPED, cfg)
        data_cfg = replace(cfg.data_config(), n_sweeps=sweeps)
        if cache is None:
            base = NuScenesDetection(data, "v1.0-sim", "sim-train", data_cfg)
            augment = AugmentConfig()
        else:
            from clfbev.feature_cache import CachedFeatureDataset, FeatureCache     # not in a base tree
            self.model.camera_encoder.freeze_image_features()
            base = CachedFeatureDataset(data, "v1.0-sim", "sim-train", data_cfg, FeatureCache.open(cache))
            augment = AugmentConfig(image=False)
        self.samples = EpochSamples(base, seed, 0, augment, cfg.pc_range)
        self.collate = TrainingCollate(cfg)
        self.opt = torch.optim.AdamW(self.model.parameters(), lr=2e-3, weight_decay=1e-2)
        self.model.train()

    def step(self, indices: list[int]) -> float:
        """One whole training step on the samples ``indices``; returns the loss."""
        with torch.profiler.record_function("load_augment"):
            samples = [self.samples[i] for i in indices]
        with torch.profiler.record_function("collate_targets"):
            batch, targets = self.collate(samples)
        with torch.profiler.record_function("forward_loss"):
            loss = training_loss(self.model(batch), targets, self.model.cfg)["loss"]
        self.opt.zero_grad(set_to_none=True)
        with torch.profiler.record_function("backward"):
            loss.backward()
        with torch.profiler.record_function("clip_adamw"):
            nn.utils.clip_grad_norm_(self.model.parameters(), 10.0)
            self.opt.step()
        return float(loss.detach())


def timed(arm: Arm, indices: list[int]) -> tuple[float, float]:
    """(thread CPU s, wall s) of one step."""
    c, w = time.thread_time(), time.perf_counter()
    arm.step(indices)
    return time.thread_time() - c, time.perf_counter() - w


ARMS = {"today": (False, tiny().n_sweeps), "cached": (True, 1), "key_sweep": (False, 1)}


def one_arm(args) -> None:
    """(Child) ``--steps`` timed steps of one arm after a warm-up: one JSON line of CPU seconds."""
    cached, sweeps = ARMS[args.arm]
    arm = Arm(args.data, args.cache if cached else None, sweeps)
    n = len(arm.samples)
    arm.step([0, 1])
    cpu = [timed(arm, [(2 * k + 2) % n, (2 * k + 3) % n])[0] for k in range(args.steps)]
    print(json.dumps({"arm": args.arm, "cpu_s": cpu}))


def against_base(args) -> None:
    """Rounds of a `today` process on the base tree and a `cached` process on this checkout."""
    script = os.path.abspath(__file__)
    here = os.path.dirname(os.path.dirname(script))
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    medians = {"today": [], "cached": []}
    for k in range(args.pairs):
        order = ("today", "cached") if k % 2 == 0 else ("cached", "today")
        for name in order:
            tree = args.base_tree if name == "today" else here
            out = subprocess.run([sys.executable, script, args.data, args.cache, "--arm", name, "--steps",
                                  str(args.steps)], env={**env, "PYTHONPATH": tree}, cwd=tree, check=True,
                                 capture_output=True, text=True).stdout
            medians[name].append(statistics.median(json.loads(out.strip().splitlines()[-1])["cpu_s"]))
        print(f"round {k}: today (base tree) {medians['today'][-1]:.3f} s CPU, cached {medians['cached'][-1]:.3f}; "
              f"ratio {medians['cached'][-1] / medians['today'][-1]:.3f}", flush=True)
    ratios = [c / t for t, c in zip(medians["today"], medians["cached"])]
    print(f"cached / today (base tree): median {statistics.median(ratios):.3f} (range {min(ratios):.3f}-"
          f"{max(ratios):.3f}); median CPU s/step today {statistics.median(medians['today']):.3f}, cached "
          f"{statistics.median(medians['cached']):.3f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("data")
    ap.add_argument("cache")
    ap.add_argument("--pairs", type=int, default=8)
    ap.add_argument("--profile", action="store_true")
    ap.add_argument("--base-tree", default=None)
    ap.add_argument("--arm", choices=sorted(ARMS), default=None)
    ap.add_argument("--steps", type=int, default=3)
    args = ap.parse_args()
    torch.set_num_threads(1)
    try:                                   # as `clfbev train` does; a base tree may predate it
        from clfbev.run.memory import keep_freed_memory
        keep_freed_memory()
    except ImportError:
        pass
    if args.arm:
        return one_arm(args)
    if args.base_tree:
        return against_base(args)
    arms = {"today": Arm(args.data, None, tiny().n_sweeps), "cached": Arm(args.data, args.cache, 1),
            "key_sweep": Arm(args.data, None, 1)}
    n = len(arms["today"].samples)
    for arm in arms.values():
        arm.step([0, 1])                     # warm-up, not timed
    rows = []
    names = list(arms)
    for k in range(args.pairs):
        indices = [(2 * k) % n, (2 * k + 1) % n]
        order = names[k % 3:] + names[:k % 3]          # each arm takes each place in turn
        t = {name: timed(arms[name], indices) for name in order}
        rows.append(t)
        print(f"round {k}: " + ", ".join(f"{name} {t[name][0]:.3f} s CPU ({t[name][1]:.3f} wall)" for name in names)
              + f"; cached / today {t['cached'][0] / t['today'][0]:.3f}", flush=True)
    for name in ("cached", "key_sweep"):
        ratios = [r[name][0] / r["today"][0] for r in rows]
        print(f"{name} / today: median {statistics.median(ratios):.3f} (range {min(ratios):.3f}-{max(ratios):.3f})")
    print("median CPU s/step: " + ", ".join(f"{name} {statistics.median(r[name][0] for r in rows):.3f}"
                                            for name in names))
    cached = arms["cached"]
    if args.profile:
        with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU]) as prof:
            for k in range(4):
                cached.step([(2 * k) % n, (2 * k + 1) % n])
        print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=25))
        print(prof.key_averages().table(sort_by="cpu_time_total", row_limit=12))


if __name__ == "__main__":
    main()
