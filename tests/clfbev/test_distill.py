"""Distillation of a lidar teacher's BEV into the camera's (clfbev/supervision/distill.py): the
loss and its foreground weights against their definition, a frozen teacher loaded from a
training checkpoint that receives no gradient, and the refusals of a wrong teacher."""
from __future__ import annotations

import dataclasses

import pytest
import torch

from clfbev.camera_aux import CameraBEVHeads, teacher_channels
from clfbev.config import tiny
from clfbev.config_file import load_config
from clfbev.data import NuScenesDetection
from clfbev.errors import CheckpointError, ConfigError
from clfbev.model import CLFusionBEV
from clfbev.run.checkpoint import save_checkpoint
from clfbev.supervision.distill import BACKGROUND_WEIGHT, distill_loss, foreground_weights, load_teacher
from clfbev.supervision.heatmap import bev_heatmap
from clfbev.supervision.targets import TrainingCollate, training_loss

pytestmark = pytest.mark.usefixtures("one_thread")


def test_identical_features_cost_exactly_nothing_and_one_cell_costs_its_weight():
    gen = torch.Generator().manual_seed(0)
    teacher = torch.randn(2, 5, 16, 16, generator=gen)
    pc_range = (-6.4, -6.4, -5.0, 6.4, 6.4, 3.0)
    heat = bev_heatmap([torch.tensor([[0.2, 0.2, 0.0, 4.5, 1.9, 1.6, 0.0]]), torch.zeros(0, 9)],
                       [torch.tensor([1]), torch.zeros(0, dtype=torch.long)], 3, pc_range, (0.8, 0.8))
    w = foreground_weights(heat)
    assert distill_loss(teacher.clone(), teacher, w).item() == 0.0
    # The weights: 1 at the box's centre cell (8, 8), its Gaussian (r 2, sigma 5/6) around it,
    # BACKGROUND_WEIGHT beyond the window and in the sample without boxes.
    assert w.shape == (2, 1, 16, 16) and w[0, 0, 8, 8] == 1.0
    assert w[0, 0, 8, 9].item() == pytest.approx(torch.exp(torch.tensor(-1 / (2 * (5 / 6) ** 2))).item())
    assert w[0, 0, 10, 10].item() == pytest.approx(max(BACKGROUND_WEIGHT, torch.exp(torch.tensor(-8 / (2 * (5 / 6) ** 2))).item()))
    assert w[0, 0, 8, 11] == BACKGROUND_WEIGHT and torch.all(w[1] == BACKGROUND_WEIGHT)
    # A student off by d in one channel of one cell pays w_cell d^2 / (C sum w).
    total = w.sum().item()
    for cell, weight in (((0, 8, 8), 1.0), ((0, 2, 3), BACKGROUND_WEIGHT), ((1, 8, 8), BACKGROUND_WEIGHT)):
        student = teacher.clone()
        student[cell[0], 3, cell[1], cell[2]] += 0.5
        assert distill_loss(student, teacher, w).item() == pytest.approx(weight * 0.25 / (5 * total), rel=1e-5)


@pytest.fixture(scope="module")
def micro_cfg(micro):
    return load_config(micro)


def _save_lidar(path, cfg, variant="lidar", seed=0):
    torch.manual_seed(seed)
    model = CLFusionBEV(cfg, variant)
    save_checkpoint(path, {"model": model.state_dict(), "config": cfg.to_dict(), "variant": variant,
                           "step": 0, "epoch": 0})
    return model


def test_the_teacher_is_frozen_and_gets_no_gradient(tiny_dataset, micro_cfg, tmp_path):
    lidar = _save_lidar(tmp_path / "teacher.pt", micro_cfg)
    cfg = dataclasses.replace(micro_cfg, cam_distill=1.0, cam_distill_teacher=str(tmp_path / "teacher.pt"))
    teacher = load_teacher(cfg.cam_distill_teacher, cfg)
    assert teacher.out_channels == teacher_channels(cfg) == cfg.sparse_channels[-1] * 2   # 64: no sweep bands
    assert all(not p.requires_grad for p in teacher.parameters())
    for k, v in teacher.lidar_encoder.state_dict().items():
        assert torch.equal(v, lidar.lidar_encoder.state_dict()[k]), k
    teacher.train()
    assert not teacher.training and not teacher.lidar_encoder.training        # stays in eval mode

    data = NuScenesDetection(tiny_dataset, "v1.0-sim", "sim-train", cfg.data_config())
    batch, targets = TrainingCollate(cfg)([data[0], data[1]])
    assert targets.teacher.shape == (2, teacher_channels(cfg), *cfg.cam_bev_shape)
    assert not targets.teacher.requires_grad
    # The teacher's features are its lidar encoder's BEV without the sweep bands.
    with torch.no_grad():
        lidar.eval()
        whole = lidar.lidar_encoder.encode(batch.points).bev
    assert torch.equal(targets.teacher, whole[:, :teacher_channels(cfg)])

    torch.manual_seed(0)
    model = CLFusionBEV(cfg, "camera").train()
    losses = training_loss(model(batch), targets, cfg)
    losses["loss"].backward()
    assert losses["loss_distill"].item() > 0
    assert all(p.grad is None for p in teacher.parameters())
    assert model.camera_aux.adapter.weight.grad.abs().sum() > 0
    assert model.camera_encoder.depth_net.weight.grad.abs().sum() > 0


def test_a_wrong_teacher_is_refused_with_one_line(micro_cfg, tmp_path):
    other = dataclasses.replace(micro_cfg, vfe_ch=8)
    _save_lidar(tmp_path / "other.pt", other)
    _save_lidar(tmp_path / "camera.pt", micro_cfg, variant="camera")
    for path, words in ((tmp_path / "other.pt", "vfe_ch 8 != 16"), (tmp_path / "camera.pt", "no lidar encoder"),
                        (tmp_path / "missing.pt", "does not exist")):
        cfg = dataclasses.replace(micro_cfg, cam_distill=1.0, cam_distill_teacher=str(path))
        with pytest.raises(CheckpointError, match=words) as e:
            TrainingCollate(cfg)                     # refused before any batch is loaded
        assert "\n" not in str(e.value)
    with pytest.raises(ConfigError, match="cam_distill_teacher"):
        dataclasses.replace(tiny(), cam_distill=1.0)
    with pytest.raises(ConfigError, match="cam_distill"):
        dataclasses.replace(tiny(), cam_distill_teacher="x.pt")
    with pytest.raises(ConfigError, match="cam_heatmap"):
        dataclasses.replace(tiny(), cam_heatmap=-1.0)


def test_the_aux_heads_leave_every_other_start_as_it_was(micro_cfg, tmp_path):
    """Off, nothing is built; on, the heads are built last, so every other tensor of a seeded
    model is the one it has without them (the comparison at one seed is of the heads alone)."""
    _save_lidar(tmp_path / "teacher.pt", micro_cfg)
    off = dataclasses.replace(micro_cfg, cam_heatmap=0.0)
    assert CameraBEVHeads.from_config(off) is None
    on = dataclasses.replace(micro_cfg, cam_heatmap=1.0, cam_distill=1.0, cam_distill_teacher=str(tmp_path / "t.pt"))
    for variant in ("camera", "full"):
        torch.manual_seed(3)
        base = CLFusionBEV(off, variant).state_dict()
        torch.manual_seed(3)
        aux = CLFusionBEV(on, variant).state_dict()
        assert set(aux) - set(base) == {k for k in aux if k.startswith("camera_aux.")} != set()
        for k, v in base.items():
            assert torch.equal(v, aux[k]), k
