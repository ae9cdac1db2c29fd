"""Training checkpoints: written atomically, read with ``torch.load(weights_only=True)``.

A checkpoint is a plain dict of tensors and Python scalars/strings/lists (nothing pickled that
``weights_only`` would refuse):

- ``format``: :data:`FORMAT`;
- ``model``: the state dict; ``config``: ``ModelConfig.to_dict()``; ``variant``;
- ``optimizer``: the optimizer state dict; ``train``: the resolved training settings (a dict);
- ``step``, ``epoch`` (epochs fully done), ``best_nds``, ``torch_rng`` (CPU generator state);
- ``code_version``.

Loading checks that the file is a checkpoint of this format and, where asked, that its config
and variant are the expected ones; every failure is a :class:`CheckpointError` naming the file.
"""

from __future__ import annotations

import os
import pickle
import tempfile
import zipfile
from pathlib import Path

import torch

from clfbev.config import ModelConfig, config_from_dict
from clfbev.model import CLFusionBEV

FORMAT = "clfbev-checkpoint-v1"
REQUIRED = ("format", "model", "config", "variant", "step", "epoch")


class CheckpointError(ValueError):
    """An unusable checkpoint: missing, corrupt, or of another config/variant."""


def save_checkpoint(path: str | Path, state: dict) -> Path:
    """Write ``state`` (a dict as in the module docstring, without ``format``) to ``path``
    atomically: a temporary file in the same folder, fsync'ed, then renamed over ``path``. A
    crash at any moment leaves either the old file or the new one, never a torn one."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            torch.save({"format": FORMAT, **state}, f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return path


def load_checkpoint(path: str | Path) -> dict:
    """The checkpoint dict at ``path`` (on the CPU), loaded with ``weights_only=True``."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"checkpoint {path} does not exist")
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except (RuntimeError, EOFError, OSError, pickle.UnpicklingError, zipfile.BadZipFile, ValueError) as e:
        first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise CheckpointError(f"checkpoint {path} is corrupt or not a checkpoint ({first})") from None
    if not isinstance(ckpt, dict) or ckpt.get("format") != FORMAT:
        raise CheckpointError(f"checkpoint {path} is not a {FORMAT} file")
    missing = [k for k in REQUIRED if k not in ckpt]
    if missing:
        raise CheckpointError(f"checkpoint {path} lacks the fields {missing}")
    return ckpt


def config_of(ckpt: dict, path: str | Path) -> ModelConfig:
    """The :class:`ModelConfig` a checkpoint was trained with."""
    try:
        return config_from_dict(ckpt["config"], f"{path} (config)")
    except ValueError as e:
        raise CheckpointError(str(e)) from None


def check_matches(ckpt: dict, path: str | Path, cfg: ModelConfig | None, variant: str | None) -> None:
    """Refuse a checkpoint of another config or variant than the one asked for (``None``:
    accept any). The message names the first differing config fields."""
    if variant is not None and ckpt["variant"] != variant:
        raise CheckpointError(f"checkpoint {path} is of variant '{ckpt['variant']}', not '{variant}'")
    if cfg is not None:
        saved = config_of(ckpt, path)
        if saved != cfg:
            diff = [k for k, v in cfg.to_dict().items() if saved.to_dict().get(k) != v]
            raise CheckpointError(f"checkpoint {path} was trained with another config (differs in: {', '.join(diff)})")


def load_model(path: str | Path, cfg: ModelConfig | None = None, variant: str | None = None,
               device: str | torch.device = "cpu") -> tuple[CLFusionBEV, dict]:
    """(model in eval mode on ``device``, checkpoint dict) for the checkpoint at ``path``.

    ``cfg`` / ``variant``: when given, the checkpoint must have been trained with exactly them.
    """
    ckpt = load_checkpoint(path)
    check_matches(ckpt, path, cfg, variant)
    model = CLFusionBEV(config_of(ckpt, path), ckpt["variant"])
    try:
        model.load_state_dict(ckpt["model"])
    except RuntimeError as e:
        first = str(e).strip().splitlines()[0]
        raise CheckpointError(f"checkpoint {path}: weights do not fit its config ({first})") from None
    return model.to(device).eval(), ckpt
