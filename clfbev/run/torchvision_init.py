"""``--image-init torchvision``: the camera backbone from torchvision's ImageNet ResNet weights,
where a user already has them in the local torch cache.

clfbev downloads nothing. torchvision keeps the weights it downloads in
``torch.hub.get_dir()/checkpoints/resnet{depth}-{hash}.pth``; a machine that has run, say,
``torchvision.models.resnet18(weights="IMAGENET1K_V1")`` has that file. Only the backbone is
loaded (the FPN, depth net and the rest keep their seeded initialisation), and only into a
backbone of torchvision's shape: ``cam_width`` 64 (torchvision's nets) and ``cam_depth`` 18, 34,
50 or 101. The images are already normalised with ImageNet's mean and standard deviation
(:mod:`clfbev.sensor_files`), as those weights expect.

:class:`clfbev.resnet.ResNet` has torchvision's layout with its own module names; the mapping is
by name, block by block (:func:`torchvision_names`), and every tensor's shape is checked.
"""
from __future__ import annotations

from pathlib import Path

import torch

from clfbev.errors import CheckpointError
from clfbev.resnet import ResNet
from clfbev.run.checkpoint import load_renamed

TORCHVISION = "torchvision"
TORCHVISION_WIDTH = 64
# Our Sequential index -> torchvision's module, for a block's body and shortcut and for the stem.
_BODY = {"0": "conv1", "1": "bn1", "3": "conv2", "4": "bn2", "6": "conv3", "7": "bn3"}
_STEM = {"0": "conv1", "1": "bn1"}


def torchvision_names(ours: str) -> str:
    """The torchvision name of one of our backbone's tensor names:
    ``stem.1.weight`` -> ``bn1.weight``, ``layer2.0.body.3.weight`` -> ``layer2.0.conv2.weight``,
    ``layer2.0.shortcut.1.running_mean`` -> ``layer2.0.downsample.1.running_mean``."""
    parts = ours.split(".")
    if parts[0] == "stem":
        return ".".join([_STEM[parts[1]], *parts[2:]])
    layer, block, part, index, *rest = parts
    module = _BODY[index] if part == "body" else f"downsample.{index}"
    return ".".join([layer, block, module, *rest])


def cached_weights(depth: int) -> Path:
    """torchvision's ResNet-``depth`` weights file in the local torch cache; CheckpointError when
    there is none (naming the folder looked in)."""
    folder = Path(torch.hub.get_dir()) / "checkpoints"
    found = sorted(folder.glob(f"resnet{depth}-*.pth"))
    if not found:
        raise CheckpointError(
            f"--image-init {TORCHVISION}: no torchvision ResNet-{depth} weights (resnet{depth}-*.pth) in {folder}; "
            f"clfbev downloads nothing: put the file there (torchvision.models.resnet{depth}(weights=...) "
            "does, on a machine with a network), or pass --image-init '' to start from scratch")
    return found[-1]


def load_torchvision_backbone(backbone: ResNet, width: int) -> Path:
    """Load torchvision's ImageNet weights into ``backbone`` (every one of its tensors, shapes
    checked; torchvision's classifier is not used). Returns the file loaded."""
    if width != TORCHVISION_WIDTH:
        raise CheckpointError(f"--image-init {TORCHVISION}: torchvision's ResNets have width {TORCHVISION_WIDTH}, "
                              f"this config's camera has cam_width {width}")
    path = cached_weights(backbone.depth)
    load_renamed(backbone, path, torchvision_names, f"torchvision's ResNet-{backbone.depth}")
    return path
