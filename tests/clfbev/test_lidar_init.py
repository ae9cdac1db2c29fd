"""clfbev train --lidar-init: a run started from a trained run's lidar detector (BEVFusion's
second stage), and its refusals."""
from __future__ import annotations

import dataclasses

import pytest
import torch

from clfbev.config import tiny
from clfbev.errors import CheckpointError, ConfigError
from clfbev.model import CLFusionBEV
from clfbev.run.checkpoint import save_checkpoint
from clfbev.run.train import start_state
from clfbev.run.train_config import TrainConfig

from test_bad_input import MICRO, assert_bad_input, clfbev

pytestmark = pytest.mark.usefixtures("one_thread")

CPU = torch.device("cpu")


@pytest.fixture(scope="module")
def lidar_state() -> dict:
    """A MICRO 'lidar' model seeded 3 (not the runs' seed 5), as a training checkpoint holds it."""
    torch.manual_seed(3)
    model = CLFusionBEV(MICRO, "lidar")
    return {"model": model.state_dict(), "config": MICRO.to_dict(), "variant": "lidar", "step": 40, "epoch": 1}


def _start(variant: str, path, cfg=MICRO):
    return start_state(cfg, variant, TrainConfig(seed=5, lidar_init=str(path)), CPU, None, path.parent / "x.pt").model


def test_a_fused_model_starts_from_the_lidar_detector(lidar_state, tmp_path):
    path = save_checkpoint(tmp_path / "lidar.pt", lidar_state)
    saved = lidar_state["model"]
    model = _start("full", path).state_dict()
    scratch = start_state(MICRO, "full", TrainConfig(seed=5), CPU, None, tmp_path / "x.pt").model.state_dict()
    assert MICRO.lidar_bev_channels != MICRO.fusion_dim       # the backbone's first conv cannot carry over

    loaded, seeded = [], []
    for k, v in model.items():
        if k.split(".")[0] in ("lidar_encoder", "head") or (k.startswith("backbone.") and saved[k].shape == v.shape):
            assert torch.equal(v, saved[k]), k
            loaded.append(k)
        else:
            assert torch.equal(v, scratch[k]), k              # fusion, camera, the unfitting conv: seeded
            seeded.append(k)
    assert any(k.startswith("lidar_encoder.") for k in loaded) and any(k.startswith("head.") for k in loaded)
    assert [k for k in seeded if k.startswith("backbone.")] == ["backbone.stages.0.0.weight"]
    assert any(k.startswith("mcm.") for k in seeded) and any(k.startswith("camera_encoder.") for k in seeded)
    # The lidar path really differs from the seeded one (the test could fail).
    assert not torch.equal(saved["head.conv_cls.weight"], scratch["head.conv_cls.weight"])

    # A tensor changed in the file is changed in the model.
    edited = {**lidar_state, "model": dict(saved)}
    name = "lidar_encoder.vfe.point_mlp.0.weight"
    edited["model"][name] = saved[name] + 0.25
    again = _start("full", save_checkpoint(tmp_path / "edited.pt", edited)).state_dict()
    assert torch.equal(again[name], edited["model"][name])


def test_a_lidar_model_starts_as_the_checkpoint(lidar_state, tmp_path):
    """The control arm of a two-stage comparison: the same detector, every tensor carried over."""
    path = save_checkpoint(tmp_path / "lidar.pt", lidar_state)
    model = _start("lidar", path).state_dict()
    assert model.keys() == lidar_state["model"].keys()
    assert all(torch.equal(v, lidar_state["model"][k]) for k, v in model.items())


def test_the_still_head_loads_where_both_have_it_and_starts_seeded_where_the_run_lacks_it(tmp_path):
    with_still = dataclasses.replace(MICRO, loss=dataclasses.replace(MICRO.loss, attribute=1.0))
    without = dataclasses.replace(MICRO, loss=dataclasses.replace(MICRO.loss, attribute=0.0))
    torch.manual_seed(3)
    plain_state = {"model": CLFusionBEV(without, "lidar").state_dict(), "config": without.to_dict(),
                   "variant": "lidar", "step": 40, "epoch": 1}
    assert "head.conv_still.weight" not in plain_state["model"]
    path = save_checkpoint(tmp_path / "lidar.pt", plain_state)
    model = _start("lidar", path, with_still).state_dict()
    scratch = start_state(with_still, "lidar", TrainConfig(seed=5), CPU, None, tmp_path / "x.pt").model.state_dict()
    for k, v in model.items():
        assert torch.equal(v, scratch[k] if k.startswith("head.conv_still.") else plain_state["model"][k]), k
    assert "head.conv_still.weight" in model

    # A run with the still head: it loads; into a model without one it is left out.
    torch.manual_seed(4)
    still_state = {**plain_state, "config": with_still.to_dict(), "model": CLFusionBEV(with_still, "lidar").state_dict()}
    still_path = save_checkpoint(tmp_path / "still.pt", still_state)
    again = _start("lidar", still_path, with_still).state_dict()
    assert all(torch.equal(v, still_state["model"][k]) for k, v in again.items())
    plain = _start("lidar", still_path, without).state_dict()
    assert "head.conv_still.weight" not in plain and torch.equal(plain["head.conv_cls.weight"],
                                                                 still_state["model"]["head.conv_cls.weight"])


def test_refusals(lidar_state, tmp_path):
    path = save_checkpoint(tmp_path / "lidar.pt", lidar_state)
    with pytest.raises(ConfigError, match="'camera' has no lidar encoder"):
        _start("camera", path)
    other = dataclasses.replace(MICRO, voxel_size=(0.5, 0.5, 0.5))
    with pytest.raises(CheckpointError, match=r"another lidar detector \(differs in: voxel_size"):
        _start("full", path, other)
    other = dataclasses.replace(MICRO, sweep_trail_min_z=-1.0)     # where the trails' points start
    with pytest.raises(CheckpointError, match=r"another lidar detector \(differs in: sweep_trail_min_z"):
        _start("full", path, other)
    camera_only = {**lidar_state, "variant": "camera", "model": CLFusionBEV(MICRO, "camera").state_dict()}
    with pytest.raises(CheckpointError, match="variant 'camera' is of another architecture"):
        _start("full", save_checkpoint(tmp_path / "camera.pt", camera_only))


def test_the_cli_refuses_a_checkpoint_of_another_detector(tiny_dataset, micro, lidar_state, tmp_path):
    tiny_ckpt = {**lidar_state, "config": tiny().to_dict()}
    path = save_checkpoint(tmp_path / "tiny.pt", tiny_ckpt)
    proc = clfbev("train", "--data", tiny_dataset, "--out", tmp_path / "run", "--config", micro, "--variant", "full",
                  "--lidar-init", path, "--max-steps", "1", "--val-split", "", "--threads", "1", "--quiet")
    assert_bad_input(proc, "tiny.pt", "another lidar detector", "vfe_ch")
    assert not (tmp_path / "run" / "last.pt").exists()
