"""``--image-init torchvision``: torchvision's ImageNet ResNet weights from the local torch cache
into the camera backbone, by name and shape; a clear refusal when they are absent or do not fit.
The weights file is one the test writes in torchvision's naming (nothing is downloaded)."""
from __future__ import annotations

import dataclasses

import pytest
import torch

from clfbev.config import tiny
from clfbev.errors import CheckpointError
from clfbev.resnet import ResNet
from clfbev.run.image_init import init_camera_encoder
from clfbev.run.pretrain import build_camera_encoder
from clfbev.run.torchvision_init import TORCHVISION, torchvision_names

# torchvision's resnet18 names (torchvision/models/resnet.py): a few, to pin the mapping.
KNOWN = {"stem.0.weight": "conv1.weight", "stem.1.running_var": "bn1.running_var",
         "layer1.0.body.0.weight": "layer1.0.conv1.weight", "layer1.1.body.4.bias": "layer1.1.bn2.bias",
         "layer3.0.shortcut.0.weight": "layer3.0.downsample.0.weight",
         "layer4.0.shortcut.1.running_mean": "layer4.0.downsample.1.running_mean"}


def _write_torchvision_file(hub, depth: int, seed: int, **shape_change) -> dict:
    """A state dict named as torchvision names its ResNet-``depth`` (with its classifier), saved
    where torchvision's cache keeps it; returns it."""
    torch.manual_seed(seed)
    net = ResNet(depth, 3, 64)
    theirs = {torchvision_names(k): v.clone() for k, v in net.state_dict().items()}
    theirs.update({"fc.weight": torch.randn(1000, net.out_channels[-1]), "fc.bias": torch.randn(1000)})
    for k, shape in shape_change.items():
        theirs[k] = torch.zeros(shape)
    (hub / "checkpoints").mkdir(parents=True, exist_ok=True)
    torch.save(theirs, hub / "checkpoints" / f"resnet{depth}-0123abcd.pth")
    return theirs


def test_the_names_are_torchvisions():
    assert {k: torchvision_names(k) for k in KNOWN} == KNOWN
    bottleneck = ResNet(50, 3, 64).state_dict()
    assert torchvision_names("layer2.1.body.7.weight") == "layer2.1.bn3.weight" and "layer2.1.body.7.weight" in bottleneck


def test_the_backbone_gets_every_tensor_and_nothing_else_changes(tmp_path, monkeypatch):
    monkeypatch.setattr(torch.hub, "get_dir", lambda: str(tmp_path))
    theirs = _write_torchvision_file(tmp_path, 18, seed=3)
    cfg = dataclasses.replace(tiny(), cam_width=64, cam_depth=18)
    torch.manual_seed(0)
    encoder = build_camera_encoder(cfg)
    before = {k: v.clone() for k, v in encoder.state_dict().items()}
    said = init_camera_encoder(encoder, TORCHVISION, cfg)
    assert "resnet18-0123abcd.pth" in said
    after = encoder.state_dict()
    for k, v in after.items():
        if k.startswith("backbone."):
            assert torch.equal(v, theirs[torchvision_names(k[len("backbone."):])]), k
        else:
            assert torch.equal(v, before[k]), k      # the FPN and the depth net keep their seeded weights


def test_absent_or_unfit_weights_are_refused_with_one_message(tmp_path, monkeypatch):
    monkeypatch.setattr(torch.hub, "get_dir", lambda: str(tmp_path))
    cfg = dataclasses.replace(tiny(), cam_width=64, cam_depth=18)
    encoder = build_camera_encoder(cfg)
    with pytest.raises(CheckpointError, match=r"no torchvision ResNet-18 weights .*checkpoints"):
        init_camera_encoder(encoder, TORCHVISION, cfg)
    _write_torchvision_file(tmp_path, 18, seed=1, **{"layer2.0.conv1.weight": (3, 3)})
    with pytest.raises(CheckpointError, match=r"layer2.0.conv1.weight has shape \(3, 3\)"):
        init_camera_encoder(encoder, TORCHVISION, cfg)
    narrow = build_camera_encoder(tiny())
    with pytest.raises(CheckpointError, match="cam_width 16"):
        init_camera_encoder(narrow, TORCHVISION, tiny())
