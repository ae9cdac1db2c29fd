"""clfbev.run.memory: with glibc's thresholds set, building a batch's training targets again and
again no longer faults fresh pages in every time (what `clfbev train` sets before it trains)."""
from __future__ import annotations

import ctypes.util
import os
import subprocess
import sys

import pytest

CHILD = """
import resource, sys, torch
if sys.argv[1] == "keep":
    from clfbev.run.memory import keep_freed_memory
    assert keep_freed_memory()
from clfbev.config_file import load_config
from clfbev.data import NuScenesDetection
from clfbev.supervision.targets import TrainingCollate
cfg = load_config(sys.argv[3])
ds = NuScenesDetection(sys.argv[2], "v1.0-sim", "sim-train", cfg.data_config())
samples, collate = [ds[0], ds[1]], TrainingCollate(cfg)
collate(samples)
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(4):
    batch, targets = collate(samples)
    del batch, targets
print((resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before) // 4)
"""


@pytest.mark.skipif(ctypes.util.find_library("c") != "libc.so.6", reason="glibc's mallopt only")
def test_the_targets_of_a_batch_reuse_freed_memory(tiny_dataset, micro):
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    faults = {}
    for mode in ("default", "keep"):
        out = subprocess.run([sys.executable, "-c", CHILD, mode, str(tiny_dataset), str(micro)], env=env,
                             capture_output=True, text=True, check=True).stdout
        faults[mode] = int(out.strip().splitlines()[-1])
    # A batch's dense anchor targets are tens of MB: by default most of their pages are new each
    # time (28,769 faults per batch of two samples here), with the thresholds set almost none are
    # (803).
    assert faults["default"] > 5000 and faults["keep"] < faults["default"] / 5, faults
