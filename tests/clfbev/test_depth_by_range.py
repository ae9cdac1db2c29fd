"""scripts/depth_by_range.py: the lift's depth accuracy per range band, on a model whose depth
is the lidar's target itself, or that target moved by a known number of bins."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import torch
import torch.nn.functional as F

from clfbev.config_file import load_config
from clfbev.data import NuScenesDetection
from clfbev.geometry import CameraGeometry, nearest_depth_bins
from conftest import script_module

dr = script_module("depth_by_range")


class TargetDepth:
    """A stand-in for the detector whose depth distribution is one-hot at the key-frame lidar's
    bin moved by ``shift`` bins (clamped to the last), and uniform where no point reaches."""

    def __init__(self, cfg, shift: int):
        self.cfg, self.shift = cfg, shift

    def __call__(self, batch):
        cfg = self.cfg
        cams = CameraGeometry.of_batch(batch, cfg)
        target = nearest_depth_bins(batch.points, cams)                            # (1, N, h, w)
        D = cfg.num_depth_bins
        moved = (target + self.shift).clamp(max=D - 1)
        probs = torch.where((target >= 0)[..., None], F.one_hot(moved.clamp(min=0), D).float(), 1.0 / D)
        return SimpleNamespace(depth=probs.permute(0, 1, 4, 2, 3))             # (1, N, D, h, w)


def test_depth_errors_are_the_bins_a_lift_is_off(tiny_dataset, micro):
    cfg = load_config(str(micro))
    ds = NuScenesDetection(tiny_dataset, "v1.0-sim", "sim-val", cfg.data_config())
    depth, error = dr.bin_errors(TargetDepth(cfg, 0), ds, 1)
    assert len(depth) > 100 and (error == 0).all()
    assert depth.min() > cfg.depth_bins[0] and depth.max() < cfg.depth_bins[1]
    rows = dr.table(depth, error).splitlines()[2:]
    for (lo, hi), row in zip(dr.BANDS, rows):
        n = int(((depth >= lo) & (depth < hi)).sum())
        assert row == (f"| {lo}-{hi} m | {n} | 1.00 | 0 |" if n else f"| {lo}-{hi} m | 0 | - | - |")

    depth3, error3 = dr.bin_errors(TargetDepth(cfg, 3), ds, 1)
    np.testing.assert_array_equal(depth3, depth)
    last = cfg.num_depth_bins - 1
    target_bin = np.floor((depth - cfg.depth_bins[0]) / cfg.depth_bins[2]).astype(int)
    np.testing.assert_array_equal(error3, np.minimum(3, last - target_bin))
