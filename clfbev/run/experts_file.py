"""The sensor experts (:mod:`clfbev.experts`) in one file: ``clfbev experts`` assembles it from
the staged recipe's checkpoints, and ``clfbev eval``, ``predict`` and ``robustness`` read it
wherever they read a checkpoint (:func:`load_predictor`).

Layout, a plain dict that ``torch.load(weights_only=True)`` reads, written atomically:

- ``format``: :data:`EXPERTS_FORMAT`;
- ``experts``: {role: checkpoint} for ``fused`` and the experts given (``camera``, ``lidar``),
  each a ``clfbev-checkpoint-v1`` dict (:mod:`clfbev.run.checkpoint`) of the fields evaluation
  reads (weights, config, variant, step, epoch, code version; no optimizer state) and
  ``source``, the checkpoint it was taken from.
"""

from __future__ import annotations

from pathlib import Path

import torch

from clfbev import io
from clfbev.config import ModelConfig
from clfbev.errors import CheckpointError, ConfigError
from clfbev.experts import FUSED, ROLES, SensorExperts
from clfbev.model import CLFusionBEV
from clfbev.run.checkpoint import REQUIRED, check_matches, checked, load_checkpoint, model_of, read_torch

EXPERTS_FORMAT = "clfbev-experts-v1"
KEPT = REQUIRED + ("code_version",)


def assemble(paths: dict[str, Path], out: Path) -> SensorExperts:
    """Write the experts file ``out`` of the checkpoints ``paths`` ({role: checkpoint}, ``fused``
    required); returns the experts. Every checkpoint is checked and the experts refused together
    (:func:`clfbev.experts.check_experts`) before anything is written."""
    if FUSED not in paths:
        raise CheckpointError("the experts need the fused model's checkpoint (--fused)")
    ckpts = {role: load_checkpoint(p) for role, p in paths.items()}
    try:
        experts = SensorExperts(**{role: model_of(c, paths[role]) for role, c in ckpts.items()})
    except ConfigError as e:
        raise ConfigError(f"{e} ({', '.join(f'{role} {p}' for role, p in paths.items())})") from None
    io.save_torch(out, {"format": EXPERTS_FORMAT, "experts": {
        role: {**{k: c[k] for k in KEPT if k in c}, "source": str(paths[role])} for role, c in ckpts.items()}})
    return experts


def load_predictor(path: str | Path, cfg: ModelConfig | None = None, variant: str | None = None,
                   device: str | torch.device = "cpu") -> tuple[CLFusionBEV | SensorExperts, dict]:
    """(model in eval mode on ``device``, its record) for a training checkpoint or an experts
    file at ``path``. The record is the checkpoint dict, or for experts ``{"variant": "<fused
    variant>+experts", "experts": {role: source checkpoint}}``. ``cfg`` / ``variant``: when given,
    the model (the fused one of experts) must have been trained with exactly them."""
    path = Path(path)
    raw = read_torch(path)
    if not (isinstance(raw, dict) and raw.get("format") == EXPERTS_FORMAT):
        ckpt = checked(raw, path)
        check_matches(ckpt, path, cfg, variant)
        return model_of(ckpt, path).to(device).eval(), ckpt
    parts = raw.get("experts")
    if not isinstance(parts, dict) or FUSED not in parts or not set(parts) <= set(ROLES):
        raise CheckpointError(f"experts file {path}: field 'experts' is not a mapping of {list(ROLES)} "
                              f"with '{FUSED}' among them")
    ckpts = {role: checked(c, f"{path} ({role})") for role, c in parts.items()}
    check_matches(ckpts[FUSED], f"{path} ({FUSED})", cfg, variant)
    experts = SensorExperts(**{role: model_of(c, f"{path} ({role})") for role, c in ckpts.items()})
    record = {"variant": experts.variant, "experts": {role: c.get("source", "") for role, c in ckpts.items()}}
    return experts.to(device).eval(), record
