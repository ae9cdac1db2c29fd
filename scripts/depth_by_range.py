"""How well a trained model's camera lift places its features: per band of the target's depth,
the camera feature cells that a key-frame lidar point reaches (the cells BEVDepth's depth loss
trains), and the share of them whose arg-max depth bin lies within one bin of the nearest
point's bin (1 m in ``tiny``), with the median error in bins.

    python scripts/depth_by_range.py DATAROOT RUN/last.pt [--split sim-val] [--every 4]

``--every K`` takes every K-th sample of the split (no augmentation, the evaluation's loader).
Prints a markdown table. A missing or junk file is one line naming it, exit 2.
"""
from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from clfbev.errors import ConfigError, run_guarded

BANDS = ((0, 10), (10, 20), (20, 35), (35, 52))


def bin_errors(model, dataset, every: int) -> tuple[np.ndarray, np.ndarray]:
    """(n,) the target depth in metres of every lidar-seen camera cell of every ``every``-th
    sample, and (n,) its arg-max bin's distance from the target bin, in bins."""
    from clfbev.data import collate
    from clfbev.geometry import batch_depth_bins, depth_bin_centres
    cfg = model.cfg
    centres = depth_bin_centres(cfg.depth_bins)
    depth, error = [], []
    with torch.no_grad():
        for i in range(0, len(dataset), every):
            batch = collate([dataset[i]])
            target = batch_depth_bins(batch, cfg)                              # (1, N, h, w), -1: none
            # An oracle model lifts with the target itself: one projection for both.
            predicted = model(replace(batch, depth_bins=target)).depth.argmax(dim=2)      # (1, N, h, w)
            seen = target >= 0
            depth.append(centres[target[seen]].numpy())
            error.append((predicted[seen] - target[seen]).abs().numpy())
    return np.concatenate(depth), np.concatenate(error)


def table(depth: np.ndarray, error: np.ndarray) -> str:
    rows = ["| target depth | cells | within 1 bin | median error, bins |", "|---|---:|---:|---:|"]
    for lo, hi in BANDS:
        sel = (depth >= lo) & (depth < hi)
        n = int(sel.sum())
        within = f"{(error[sel] <= 1).mean():.2f}" if n else "-"
        median = f"{np.median(error[sel]):.0f}" if n else "-"
        rows.append(f"| {lo}-{hi} m | {n} | {within} | {median} |")
    return "\n".join(rows)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="depth_by_range", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("dataroot", type=Path)
    p.add_argument("ckpt", type=Path)
    p.add_argument("--split", default="sim-val")
    p.add_argument("--version", default="v1.0-sim")
    p.add_argument("--every", type=int, default=4, help="every K-th sample of the split (default 4)")
    a = p.parse_args(argv)
    if a.every < 1:
        raise ConfigError(f"--every must be >= 1, got {a.every}")
    from clfbev.data import NuScenesDetection
    from clfbev.run.checkpoint import load_model
    model, _ = load_model(a.ckpt)
    if model.camera_encoder is None:
        raise ConfigError(f"{a.ckpt}: a {model.variant!r} model has no camera")
    dataset = NuScenesDetection(a.dataroot, a.version, a.split, model.cfg.data_config())
    print(table(*bin_errors(model, dataset, a.every)))
    return 0


if __name__ == "__main__":
    raise SystemExit(run_guarded(main, prog="depth_by_range"))
