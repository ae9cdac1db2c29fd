"""The memory a training step needs at the least, checked before a run starts: a config the
machine clearly cannot hold is refused in one line instead of being killed for memory, without a
word, minutes into its first step.

The bound is what no training step of the config can do without, counted exactly:

- the image encoder's activations that autograd keeps for the backward pass (every tensor but
  the weights saved by a ResNet/FPN/depth-net forward, counted once per storage through
  ``torch.autograd.graph.saved_tensors_hooks``), measured on one image of about a quarter of
  the config's height and width and scaled by the pixels (convolution activations grow with them),
  times the images of a step (batch x cameras). With the image features frozen only the depth
  net's count. On a GPU, where training runs under bfloat16 autocast, half of it.
- the model's weights, their gradients and AdamW's two moments: 16 bytes per trainable
  parameter, 4 per frozen one.

The lidar branch, the lift's frustum, the BEV and the head come on top, so the true peak is
higher: a refusal is certain, a pass promises nothing.
"""
from __future__ import annotations

import os
from pathlib import Path

import torch

from clfbev.camera_encoder import CameraEncoder
from clfbev.config import ModelConfig
from clfbev.errors import ConfigError
from clfbev.model import CLFusionBEV, count_parameters

N_CAMERAS = 6
PROBE_SCALE = 4             # the probe image is about the config's H / 4 x W / 4 ...
COARSEST_STRIDE = 32        # ... in multiples of the backbone's C5 stride
PROBE_IMAGES = 2
MEMINFO = Path("/proc/meminfo")


def saved_storages(fn, parameters=()) -> list[tuple[int, int]]:
    """(bytes, dimensions of the tensor saved) of each distinct storage that autograd saves for
    the backward pass while ``fn()`` runs, those of ``parameters`` (weights, counted apart) left out."""
    weights = {p.untyped_storage().data_ptr() for p in parameters}
    seen: dict[int, tuple[int, int]] = {}

    def pack(t: torch.Tensor):
        storage = t.untyped_storage()
        if storage.data_ptr() not in weights:
            seen[storage.data_ptr()] = (storage.nbytes(), t.dim())
        return t

    with torch.autograd.graph.saved_tensors_hooks(pack, lambda t: t):
        fn()
    return list(seen.values())


def saved_bytes(fn, parameters=()) -> int:
    """Bytes that autograd saves for the backward pass while ``fn()`` runs (:func:`saved_storages`)."""
    return sum(n for n, _ in saved_storages(fn, parameters))


def image_activation_bytes(cfg: ModelConfig, frozen: bool) -> int:
    """Saved activation bytes of the image encoder per image at the config's size: the probe's
    feature maps scaled by the pixels, its per-channel statistics (BatchNorm's) as they are."""
    encoder = CameraEncoder.from_config(cfg)
    if frozen:
        encoder.freeze_image_features()
    H, W = cfg.image_size
    # Multiples of the coarsest stride, so that every feature map shrinks by exactly the ratio of
    # the pixels where the config's size is a multiple of it too (else the full maps round up:
    # more, never less, than the count). Two images: BatchNorm trains on no fewer values.
    h, w = (max(n // PROBE_SCALE // COARSEST_STRIDE, 1) * COARSEST_STRIDE for n in (H, W))
    image = torch.randn(PROBE_IMAGES, 3, h, w).contiguous(memory_format=torch.channels_last)

    def forward():
        levels = encoder.backbone(image)[encoder._levels]
        encoder.depth_net(encoder.neck(levels)).sum()

    saved = saved_storages(forward, list(encoder.parameters()) + list(encoder.buffers()))
    maps = sum(n for n, dims in saved if dims == 4) // PROBE_IMAGES
    return maps * (H * W) // (h * w) + sum(n for n, dims in saved if dims != 4)


def state_bytes(model: torch.nn.Module) -> int:
    """Weights, gradients and AdamW's two moments of the trainable parameters; weights of the rest."""
    trainable = count_parameters(model)
    frozen = sum(p.numel() for p in model.parameters() if not p.requires_grad)
    return 16 * trainable + 4 * frozen


def step_lower_bound(cfg: ModelConfig, model: torch.nn.Module, batch_size: int, frozen: bool,
                     half: bool = False) -> int:
    """Bytes a training step of ``model`` (built from ``cfg``) needs at the least, batch
    ``batch_size``. ``half``: under 16-bit autocast (a GPU's bfloat16), where an activation may
    take 2 bytes an element instead of the probe's 4."""
    need = state_bytes(model)
    if model.camera_encoder is not None:
        need += batch_size * N_CAMERAS * image_activation_bytes(cfg, frozen) // (2 if half else 1)
    return need


def available_bytes(device: torch.device) -> int | None:
    """Free memory where the step runs: the GPU's, or the host's MemAvailable; None where unknown."""
    if device.type == "cuda":
        return torch.cuda.mem_get_info(device)[0]
    try:
        for line in MEMINFO.read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        return None
    return None


def describe_camera(cfg: ModelConfig) -> str:
    """The image encoder and its input size in words, for the refusal."""
    H, W = cfg.image_size
    encoder = ("EfficientNet-Lite0" if cfg.cam_backbone == "efficientnet_lite0"
               else f"ResNet-{cfg.cam_depth} width {cfg.cam_width}")
    return f"{encoder} on {H}x{W} images"


def check_memory(cfg: ModelConfig, variant: str, batch_size: int, frozen: bool, device: torch.device) -> None:
    """ConfigError when a training step of ``variant`` clearly cannot fit (:func:`step_lower_bound`
    above what is available). Leaves torch's random state as it found it."""
    free = available_bytes(device)
    if free is None:
        return
    with torch.random.fork_rng(devices=[]):
        model = CLFusionBEV(cfg, variant)
        if frozen and model.camera_encoder is not None:
            model.camera_encoder.freeze_image_features()
        need = step_lower_bound(cfg, model, batch_size, frozen, half=device.type == "cuda")
    if need > free:
        where = f"the GPU {device}" if device.type == "cuda" else f"this machine ({os.cpu_count()} CPUs)"
        raise ConfigError(
            f"the {variant} model ({describe_camera(cfg)}) at --batch-size {batch_size} needs at least "
            f"{need / 2**30:.1f} GiB per process (its image encoder's activations for {batch_size * N_CAMERAS} "
            f"images and its weights with their gradients and AdamW state), and {where} has {free / 2**30:.1f} GiB "
            "available: use a smaller --batch-size, --image-freeze, or a machine with more memory")
