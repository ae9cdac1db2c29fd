"""A model config from a preset name or a YAML file of overrides, validated strictly; the same
check reads back the config a checkpoint stores (:meth:`clfbev.config.ModelConfig.to_dict`)."""
from __future__ import annotations

import dataclasses
import math
from pathlib import Path

from clfbev.config import PRESETS, ModelConfig
from clfbev.errors import ConfigError


def load_config(name_or_path: str | Path) -> ModelConfig:
    """A preset by name ('tiny', 'paper'), or a YAML file of overrides.

    The YAML file is a mapping of field names to values; the optional key ``preset`` names the
    preset it overrides (default 'tiny'; no chains of files). ``loss`` takes a mapping of
    :class:`LossWeights` fields. Lists become tuples. A file that is missing or not YAML, an
    unknown key, a wrong type, a non-finite number or a value the config rejects raises one
    :class:`ConfigError` naming the file and the key.
    """
    if str(name_or_path) in PRESETS:
        return PRESETS[str(name_or_path)]()
    path = Path(name_or_path)
    return config_from_dict(_read_yaml(path), path)


def _read_yaml(path: Path):
    """The parsed YAML of ``path``; a one-line :class:`ConfigError` if it cannot be read or parsed."""
    import yaml

    try:
        return yaml.safe_load(path.read_text()) or {}
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such file, and not a preset ({', '.join(PRESETS)})") from None
    except (OSError, UnicodeDecodeError) as e:
        raise ConfigError(f"{path}: cannot read the config file ({e})") from None
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
        problem = getattr(e, "problem", None) or type(e).__name__
        raise ConfigError(f"{path}: not valid YAML{where}: {problem}") from None


def preset_of(name_or_path: str | Path) -> str:
    """The preset a config name or YAML file builds on ('tiny' unless the file says otherwise);
    it also picks the training recipe."""
    if str(name_or_path) in PRESETS:
        return str(name_or_path)
    try:
        data = _read_yaml(Path(name_or_path))
    except ConfigError:
        return "tiny"  # load_config reports the file's problem with its own message
    return data.get("preset", "tiny") if isinstance(data, dict) else "tiny"


def config_from_dict(data, source: str | Path = "<config>") -> ModelConfig:
    """A :class:`ModelConfig` from a mapping (a parsed YAML file, or ``ModelConfig.to_dict()``
    as a checkpoint stores it), validated like a YAML file; errors name ``source``."""
    path = source
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a mapping of config keys, got {type(data).__name__}")
    data = dict(data)
    preset = data.pop("preset", "tiny")
    if preset not in PRESETS:
        raise ConfigError(f"{path}: key 'preset' must be one of {list(PRESETS)}, got {preset!r}")
    base = PRESETS[preset]()
    overrides = {}
    for key, value in data.items():
        if key == "loss":
            if not isinstance(value, dict):
                raise ConfigError(f"{path}: key 'loss' must be a mapping of LossWeights fields")
            checked = {k: _check(path, f"loss.{k}", v, base.loss, k) for k, v in value.items()}
            overrides["loss"] = dataclasses.replace(base.loss, **checked)
        else:
            overrides[key] = _check(path, key, value, base, key)
    try:
        return dataclasses.replace(base, **overrides)
    except (ConfigError, ValueError) as e:      # ValueError: the grid arithmetic of clfbev.settings
        raise ConfigError(f"{path}: {e}") from None


def _check(path: Path, key: str, value, base, name: str):
    """The override ``value`` of field ``name`` of ``base``, type-checked against its default."""
    names = {f.name for f in dataclasses.fields(base)}
    if not isinstance(name, str) or name not in names:
        raise ConfigError(f"{path}: unknown key '{key}' (allowed: {', '.join(sorted(names))})")
    default = getattr(base, name)
    if isinstance(default, tuple):
        if not isinstance(value, (list, tuple)) or not all(_same_kind(v, default[0]) for v in value if default):
            raise ConfigError(f"{path}: key '{key}' must be a list of finite values like {list(default)}, "
                              f"got {value!r}")
        return tuple(float(v) if isinstance(v, int) and default and isinstance(default[0], float) else v
                     for v in value)
    if default is None or name == "attn_query_chunk":
        if value is not None and not (isinstance(value, int) and not isinstance(value, bool)):
            raise ConfigError(f"{path}: key '{key}' must be an integer or null, got {value!r}")
        return value
    if not _same_kind(value, default):
        kind = "finite number" if isinstance(default, float) else type(default).__name__
        raise ConfigError(f"{path}: key '{key}' must be a {kind}, got {value!r}")
    return float(value) if isinstance(default, float) else value


def _same_kind(value, default) -> bool:
    if isinstance(default, bool) or isinstance(value, bool):
        return isinstance(value, bool) and isinstance(default, bool)
    if isinstance(default, float):
        return isinstance(value, (int, float)) and math.isfinite(value)
    return isinstance(value, type(default))
