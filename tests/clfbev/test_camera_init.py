"""clfbev train --camera-init: a fused run whose camera branch starts from a trained run's, with
--lidar-init its lidar detector from another (the staged recipe's fusion stage), and the
refusals."""
from __future__ import annotations

import dataclasses

import pytest
import torch

from clfbev.errors import CheckpointError, ConfigError
from clfbev.model import CLFusionBEV
from clfbev.run.checkpoint import save_checkpoint
from clfbev.run.image_init import save_encoder
from clfbev.run.train import start_state
from clfbev.run.train_config import TrainConfig

from test_bad_input import MICRO, assert_bad_input, clfbev

pytestmark = pytest.mark.usefixtures("one_thread")

CPU = torch.device("cpu")


def trained_state(cfg, variant: str, seed: int) -> dict:
    """What a training checkpoint of ``variant`` holds, its every float tensor (BatchNorm's
    statistics too) moved off its seeded value, as training moves them."""
    torch.manual_seed(seed)
    weights = CLFusionBEV(cfg, variant).state_dict()
    g = torch.Generator().manual_seed(seed + 100)
    moved = {k: v + 0.1 * torch.rand(v.shape, generator=g) if v.is_floating_point() else v for k, v in weights.items()}
    return {"model": moved, "config": cfg.to_dict(), "variant": variant, "step": 30, "epoch": 1}


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> dict:
    """Checkpoints of a 'camera' run (seed 3) and a 'lidar' run (seed 4) of MICRO."""
    folder = tmp_path_factory.mktemp("runs")
    states = {"camera": trained_state(MICRO, "camera", 3), "lidar": trained_state(MICRO, "lidar", 4)}
    return {v: (save_checkpoint(folder / f"{v}.pt", state), state["model"]) for v, state in states.items()}


def _start(variant: str, cfg=MICRO, **init):
    return start_state(cfg, variant, TrainConfig(seed=5, image_init="", **init), CPU, None, None).model


def test_the_fusion_stage_starts_from_the_camera_run_and_the_lidar_run(runs):
    (camera_path, camera), (lidar_path, lidar) = runs["camera"], runs["lidar"]
    model = _start("full", camera_init=str(camera_path), lidar_init=str(lidar_path)).state_dict()
    scratch = _start("full").state_dict()
    parts = {"camera": [], "lidar": [], "seeded": []}
    for k, v in model.items():
        module = k.split(".")[0]
        if module in ("camera_encoder", "camera_aux"):         # the camera branch and its heatmap head
            assert torch.equal(v, camera[k]), k
            parts["camera"].append(k)
        elif module in ("lidar_encoder", "head") or (module == "backbone" and lidar[k].shape == v.shape):
            assert torch.equal(v, lidar[k]), k
            parts["lidar"].append(k)
        else:
            assert torch.equal(v, scratch[k]), k          # the fusion and the unfitting conv: seeded
            parts["seeded"].append(k)
    # Every camera tensor came over, BatchNorm's statistics included, and none is the seeded one.
    assert parts["camera"] == [k for k in camera if k.split(".")[0] in ("camera_encoder", "camera_aux")]
    assert any(k.startswith("camera_aux.") for k in parts["camera"])
    assert any(k.endswith("running_var") for k in parts["camera"])
    assert not any(torch.equal(scratch[k], camera[k]) for k in parts["camera"] if scratch[k].is_floating_point())
    assert {k.split(".")[0] for k in parts["seeded"]} == {"mcm", "fuser", "bsm", "backbone"}
    # The camera run's own backbone and head (a camera detector's) stay behind.
    assert not torch.equal(model["head.conv_cls.weight"], camera["head.conv_cls.weight"])


def test_the_camera_init_replaces_the_image_init_and_carries_the_auxiliary_heads(runs, tmp_path):
    cfg = dataclasses.replace(MICRO, cam_heatmap=1.0)
    state = trained_state(cfg, "camera", 6)
    path = save_checkpoint(tmp_path / "camera.pt", state)
    torch.manual_seed(9)
    encoder = CLFusionBEV(cfg, "camera").camera_encoder
    enc_path = save_encoder(tmp_path / "encoder.pt", encoder, cfg, ["test"], {}, 0, "test")
    model = start_state(cfg, "concat", TrainConfig(seed=5, image_init=str(enc_path), camera_init=str(path)), CPU,
                        None, None).model.state_dict()
    branch = [k for k in model if k.split(".")[0] in ("camera_encoder", "camera_aux")]
    assert any(k.startswith("camera_aux.") for k in branch)
    for k in branch:
        assert torch.equal(model[k], state["model"][k]), k


def test_refusals(runs, tmp_path):
    camera_path, lidar_path = runs["camera"][0], runs["lidar"][0]
    with pytest.raises(ConfigError, match="'lidar' has no camera encoder"):
        _start("lidar", camera_init=str(camera_path))
    with pytest.raises(CheckpointError, match="a run of variant 'lidar' has no camera branch"):
        _start("full", camera_init=str(lidar_path))
    other = dataclasses.replace(MICRO, context_ch=8)
    with pytest.raises(CheckpointError, match=r"another camera branch \(differs in: context_ch 16 != 8"):
        _start("full", other, camera_init=str(camera_path))
    # A coarser lidar grid moves the camera BEV's cells: another branch, though no camera field changed.
    other = dataclasses.replace(MICRO, voxel_size=(0.8, 0.8, 0.4))
    with pytest.raises(CheckpointError, match=r"another camera branch \(differs in: cam_bev_voxel"):
        _start("full", other, camera_init=str(camera_path))
    cut = trained_state(MICRO, "camera", 3)
    name = next(k for k in cut["model"] if k.startswith("camera_encoder.depth_net"))
    del cut["model"][name]
    with pytest.raises(CheckpointError, match=f"another architecture \\(missing \\['{name}'"):
        _start("full", camera_init=str(save_checkpoint(tmp_path / "cut.pt", cut)))


def test_the_cli_refuses_a_camera_run_of_another_camera(tiny_dataset, micro, tmp_path):
    state = trained_state(dataclasses.replace(MICRO, fpn_ch=16), "camera", 3)
    path = save_checkpoint(tmp_path / "camera16.pt", state)
    proc = clfbev("train", "--data", tiny_dataset, "--out", tmp_path / "run", "--config", micro, "--variant", "full",
                  "--camera-init", path, "--image-init", "", "--max-steps", "1", "--val-split", "", "--threads", "1",
                  "--quiet")
    assert_bad_input(proc, "camera16.pt", "another camera branch", "fpn_ch 16 != 32")
    assert not (tmp_path / "run" / "last.pt").exists()
