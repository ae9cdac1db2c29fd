"""clfbev.run.memory_need: the memory a training step needs at the least, and the refusal.

- autograd's saved tensors of a known network are counted to the byte;
- the probe at about a quarter of the size, scaled by the pixels, gives the full-size count;
- a step that no machine holds is refused in one line, exit 2, before the run folder exists.
"""
from __future__ import annotations

import torch
from torch import nn

from clfbev.config import tiny
from clfbev.run import memory_need
from clfbev.run.memory_need import image_activation_bytes, saved_bytes
from test_bad_input import MICRO, assert_bad_input, clfbev


def test_saved_bytes_of_a_conv_and_a_relu():
    conv = nn.Conv2d(3, 8, 3, bias=False)
    x = torch.randn(1, 3, 32, 32)
    # The conv saves its input and its weight, the ReLU its output.
    expected = 4 * (3 * 32 * 32 + 8 * 3 * 3 * 3 + 8 * 30 * 30)
    assert saved_bytes(lambda: torch.relu(conv(x)).sum()) == expected
    assert saved_bytes(lambda: torch.relu(conv(x)).sum(), conv.parameters()) == expected - 4 * 8 * 3 * 3 * 3
    with torch.no_grad():
        assert saved_bytes(lambda: torch.relu(conv(x)).sum()) == 0


def test_the_probe_scales_to_the_full_size_count(monkeypatch):
    cfg = tiny()
    for frozen in (False, True):
        probed = image_activation_bytes(cfg, frozen)
        monkeypatch.setattr(memory_need, "PROBE_SCALE", 1)
        full = image_activation_bytes(cfg, frozen)
        monkeypatch.undo()
        assert abs(probed - full) <= 1e-3 * full, (frozen, probed, full)
    assert image_activation_bytes(cfg, True) < 0.1 * image_activation_bytes(cfg, False)
    # A config whose probe's coarsest map is one cell still trains BatchNorm on the probe.
    assert image_activation_bytes(MICRO, False) > 0


def test_the_check_leaves_the_random_state_and_counts_frozen_weights_once(monkeypatch):
    cfg = tiny()
    monkeypatch.setattr(memory_need, "available_bytes", lambda device: 1 << 50)
    torch.manual_seed(7)
    memory_need.check_memory(cfg, "camera", 2, True, torch.device("cpu"))
    after = torch.rand(3)
    torch.manual_seed(7)
    assert torch.equal(after, torch.rand(3))
    model = memory_need.CLFusionBEV(cfg, "camera")
    trained = memory_need.state_bytes(model)
    model.camera_encoder.freeze_image_features()
    frozen_params = sum(p.numel() for p in model.parameters() if not p.requires_grad)
    assert frozen_params > 0 and memory_need.state_bytes(model) == trained - 12 * frozen_params


def test_a_step_no_machine_holds_is_refused_before_anything_is_written(tiny_dataset, tmp_path):
    run = tmp_path / "run"
    proc = clfbev("train", "--data", tiny_dataset, "--config", "tiny", "--variant", "camera", "--out", run,
                  "--batch-size", "1000000", "--max-steps", "1")
    assert_bad_input(proc, "--batch-size 1000000", "GiB", "ResNet-18 width 16 on 192x352 images")
    assert not run.exists()
