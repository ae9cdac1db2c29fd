"""Training checkpoints: written atomically (:func:`clfbev.io.save_torch`), read with
``torch.load(weights_only=True)``.

A checkpoint is a plain dict of tensors and Python scalars/strings/lists (nothing pickled that
``weights_only`` would refuse):

- ``format``: :data:`FORMAT`;
- ``model``: the state dict; ``config``: ``ModelConfig.to_dict()``; ``variant``;
- ``optimizer``: the optimizer state dict; ``train``: the resolved training settings (a dict);
- ``step``, ``epoch`` (epochs fully done), ``best_nds``, ``torch_rng`` (CPU generator state);
- ``code_version``.

Loading checks that the file is a checkpoint of this format with fields of the right kind and,
where asked, that its config and variant are the expected ones; every failure is a
:class:`CheckpointError` naming the file. :class:`Checkpoints` writes a run's ``last.pt`` and
``best.pt`` and knows when the next is due.
"""

from __future__ import annotations

import io as io_module
import lzma
import time
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path

import torch
from torch import nn

from clfbev import io
from clfbev.config import VARIANTS, ModelConfig
from clfbev.config_file import config_from_dict
from clfbev.errors import CheckpointError, ConfigError
from clfbev.model import CLFusionBEV
from clfbev.run.train_config import TrainConfig

FORMAT = "clfbev-checkpoint-v1"
REQUIRED = ("format", "model", "config", "variant", "step", "epoch")
XZ_MAGIC = b"\xfd7zXZ\x00"      # the xz container's first bytes
# What a resume reads besides REQUIRED (a checkpoint written for evaluation only may lack them).
RESUME_FIELDS = ("optimizer", "train", "best_nds", "torch_rng")


def save_checkpoint(path: str | Path, state: dict) -> Path:
    """Write ``state`` (a dict as in the module docstring, without ``format``) to ``path``
    atomically: a crash at any moment leaves either the old file or the new one."""
    return io.save_torch(path, {"format": FORMAT, **state})


def read_torch(path: Path) -> object:
    """``torch.load(path, weights_only=True)`` on the CPU, of the file or, when it is
    xz-compressed (:func:`export_weights`), of its contents; any failure a CheckpointError naming the file."""
    if not path.is_file():
        raise CheckpointError(f"checkpoint {path} does not exist")
    try:
        with open(path, "rb") as f:
            compressed = f.read(len(XZ_MAGIC)) == XZ_MAGIC
        if compressed:
            return torch.load(io_module.BytesIO(lzma.decompress(path.read_bytes())), map_location="cpu",
                              weights_only=True)
        return torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:
        # Any bytes may be in a file the user names, and the unpickler fails on them as it may
        # (KeyError for text, EOFError or RuntimeError when truncated, UnpicklingError, ...).
        first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise CheckpointError(f"checkpoint {path} is corrupt or not a checkpoint ({first})") from None


def export_weights(src: str | Path, out: str | Path) -> dict:
    """Write the weights of checkpoint ``src`` to ``out`` xz-compressed, with what evaluation
    reads (config, variant, step, epoch, code version) and without the optimizer's state: the
    form in which a run's final weights are kept. Returns the checkpoint read."""
    ckpt = load_checkpoint(src)
    kept = {k: ckpt[k] for k in (*REQUIRED, "code_version") if k in ckpt}
    buffer = io_module.BytesIO()
    torch.save(kept, buffer)
    io.write_bytes(out, lzma.compress(buffer.getvalue(), preset=9))
    return ckpt


def load_checkpoint(path: str | Path, required: tuple[str, ...] = REQUIRED) -> dict:
    """The checkpoint dict at ``path`` (on the CPU), loaded with ``weights_only=True``, holding at
    least the fields ``required``."""
    path = Path(path)
    return checked(read_torch(path), path, required)


def checked(ckpt: object, where: str | Path, required: tuple[str, ...] = REQUIRED) -> dict:
    """``ckpt`` if it is a checkpoint dict of this format holding the fields ``required``, of the
    right kinds; else a CheckpointError naming ``where`` (the file, or a part of one)."""
    if not isinstance(ckpt, dict) or ckpt.get("format") != FORMAT:
        raise CheckpointError(f"checkpoint {where} is not a {FORMAT} file")
    missing = [k for k in required if k not in ckpt]
    if missing:
        raise CheckpointError(f"checkpoint {where} lacks the fields {missing}")
    _check_fields(ckpt, where)
    return ckpt


def _check_fields(ckpt: dict, path: str | Path) -> None:
    """Refuse fields of the wrong kind: the weights not a mapping of finite tensors, an unknown
    variant, a step or epoch that is not a count."""
    weights = ckpt["model"]
    if not isinstance(weights, dict) or not all(isinstance(v, torch.Tensor) for v in weights.values()):
        raise CheckpointError(f"checkpoint {path}: field 'model' is not a state dict of tensors")
    bad = next((k for k, v in weights.items() if v.is_floating_point() and not torch.isfinite(v).all()), None)
    if bad is not None:
        raise CheckpointError(f"checkpoint {path}: the weights '{bad}' hold non-finite values")
    if ckpt["variant"] not in VARIANTS:
        raise CheckpointError(f"checkpoint {path}: field 'variant' is {ckpt['variant']!r}, not one of {VARIANTS}")
    for key in ("step", "epoch"):
        if isinstance(ckpt[key], bool) or not isinstance(ckpt[key], int) or ckpt[key] < 0:
            raise CheckpointError(f"checkpoint {path}: field '{key}' is {ckpt[key]!r}, not a count")


def check_fields(theirs: dict, mine: dict, keys, what: str) -> None:
    """Refuse a checkpoint whose config ``theirs`` differs from ``mine`` (plain dicts) in one of
    ``keys``: a CheckpointError ``{what} (differs in: key theirs != mine, ...)``."""
    diff = [k for k in keys if theirs[k] != mine[k]]
    if diff:
        differs = ", ".join(f"{k} {theirs[k]} != {mine[k]}" for k in diff)
        raise CheckpointError(f"{what} (differs in: {differs})")


def check_tensors(weights: dict, want: dict, what: str) -> None:
    """Refuse ``weights`` ({name: tensor}) unless it holds exactly the names of the state dict
    ``want`` with their shapes: a CheckpointError that starts with ``what`` (the file, in words)
    and names the first missing, unexpected or misshapen tensors."""
    missing, extra = sorted(set(want) - set(weights)), sorted(set(weights) - set(want))
    if missing or extra:
        raise CheckpointError(f"{what} is of another architecture (missing {missing[:3]}, unexpected {extra[:3]})")
    bad = next((k for k in want if weights[k].shape != want[k].shape), None)
    if bad is not None:
        raise CheckpointError(f"{what}: tensor '{bad}' has shape {tuple(weights[bad].shape)}, "
                              f"the model's is {tuple(want[bad].shape)}")


def load_renamed(module: nn.Module, path: Path, rename: Callable[[str], str], what: str) -> None:
    """Load a foreign state dict (the file ``path``, e.g. a library's ImageNet weights) into
    ``module``: each of the module's tensors ``k`` from the file's ``rename(k)``, shapes checked;
    the file's other tensors (a classifier) are left out. BatchNorm's batch counter, absent from
    some files and changing no output, stays the module's where the file lacks it. ``what``
    names the expected weights in the CheckpointError (e.g. "torchvision's ResNet-18")."""
    theirs = read_torch(path)
    if not isinstance(theirs, dict):
        raise CheckpointError(f"{path} is not a state dict")
    mine = module.state_dict()
    wanted = [k for k in mine if not (k.endswith("num_batches_tracked") and rename(k) not in theirs)]
    missing = next((k for k in wanted if rename(k) not in theirs), None)
    if missing is not None:
        raise CheckpointError(f"{path} is not {what} (no {rename(missing)})")
    bad = next((k for k in wanted if theirs[rename(k)].shape != mine[k].shape), None)
    if bad is not None:
        raise CheckpointError(f"{path}: {rename(bad)} has shape {tuple(theirs[rename(bad)].shape)}, "
                              f"the model's {bad} {tuple(mine[bad].shape)}")
    module.load_state_dict({**mine, **{k: theirs[rename(k)] for k in wanted}}, strict=True)


def config_of(ckpt: dict, path: str | Path) -> ModelConfig:
    """The :class:`ModelConfig` a checkpoint was trained with."""
    try:
        return config_from_dict(ckpt["config"], f"{path} (config)")
    except ConfigError as e:
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
    return model_of(ckpt, path).to(device).eval(), ckpt


def model_of(ckpt: dict, where: str | Path) -> CLFusionBEV:
    """The model a :func:`checked` checkpoint dict holds (``where`` names it in errors)."""
    model = CLFusionBEV(config_of(ckpt, where), ckpt["variant"])
    try:
        model.load_state_dict(ckpt["model"])
    except RuntimeError as e:
        first = str(e).strip().splitlines()[0]
        raise CheckpointError(f"checkpoint {where}: weights do not fit its config ({first})") from None
    return model


class Checkpoints:
    """``RUN/last.pt`` and ``RUN/best.pt`` of one run (rank 0 writes them), and when the next
    ``last.pt`` is due: every ``save_every_steps`` steps and every ``ckpt_minutes``."""

    def __init__(self, run: Path, cfg: ModelConfig, variant: str, tc: TrainConfig, version: str) -> None:
        self.last, self.best = run / "last.pt", run / "best.pt"
        self.cfg, self.variant, self.tc, self.version = cfg, variant, tc, version
        self.saved_at = time.monotonic()

    def save(self, path: Path, state) -> None:
        """Write ``state`` (a :class:`clfbev.run.train.TrainState`: model, optimizer, step, epoch,
        best NDS) with the run's settings, code version and the torch RNG state to ``path``."""
        save_checkpoint(path, {
            "model": state.model.state_dict(), "optimizer": state.opt.state_dict(), "config": self.cfg.to_dict(),
            "variant": self.variant, "train": asdict(self.tc), "step": state.step, "epoch": state.epoch,
            "best_nds": state.best_nds, "torch_rng": torch.get_rng_state(), "code_version": self.version,
        })
        if path == self.last:
            self.saved_at = time.monotonic()

    def due(self, step: int) -> bool:
        """Whether ``last.pt`` is due after step ``step``."""
        timed = time.monotonic() - self.saved_at > self.tc.ckpt_minutes * 60
        return bool(self.tc.save_every_steps and step % self.tc.save_every_steps == 0) or timed
