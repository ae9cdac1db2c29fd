"""The detector's command line (`clfbev train | pretrain | cache-features | experts | export | eval | predict |
show | robustness`), and its only entry point (the ``clfbev`` script, ``python -m clfbev``, and what torchrun starts on each rank).

    clfbev train   --data DIR --config tiny --variant full --out RUN [--epochs N | --max-steps N] [--resume]
    torchrun --nproc_per_node 2 -m clfbev train --data DIR --out RUN ...          (DDP)
    clfbev pretrain --data DIR --config tiny --out RUN [--max-steps N] [--resume]   (camera encoder, dense labels)
    clfbev cache-features --data DIR --config tiny --image-init shipped --out CACHE [--split sim-train]
    clfbev export  --ckpt RUN/last.pt --out weights.pt.xz                          (weights alone, compressed)
    clfbev eval    --data DIR --ckpt RUN/best.pt [--split sim-val] --out DIR
    clfbev predict --data DIR --ckpt CKPT --out results.json [--split all]
    clfbev show    --data DIR --results results.json [--sample I] --out FILE.png [--attention --ckpt CKPT [--cell X,Y]]
    clfbev robustness --ckpt NAME=CKPT ... --set NAME=DATAROOT ... [--corrupt NAME:SEV ...] --out DIR

Bad input (a missing dataroot, an unknown split, a corrupt or mismatched checkpoint, an invalid
config file, an unwritable output) gets one line on stderr naming the file or option, and exit
code 2 (:func:`clfbev.errors.run_guarded`). A non-finite training loss stops training with exit
code 3, keeping the last checkpoint.
"""

from __future__ import annotations

import argparse
import math
import os
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import torch

from clfbev import io
from clfbev.camera_encoder import CameraEncoder
from clfbev.config import VARIANTS
from clfbev.config_file import load_config
from clfbev.corruptions import parse as parse_corruption
from clfbev.data import NuScenesDetection, collate, load_nuscenes
from clfbev.errors import ConfigError, DataError, OutputError, run_guarded
from clfbev.feature_cache import FeatureCache, encoder_identity, fill_cache
from clfbev.run import robustness
from clfbev.run.attention_plot import draw_attention
from clfbev.run.attention_query import attention_modules
from clfbev.run.checkpoint import export_weights, load_model
from clfbev.run.efficientnet_init import EFFICIENTNET_LITE0
from clfbev.run.evaluate import EVAL_SCORE_THR, evaluate_model, predict_split, write_results
from clfbev.run.experts_file import assemble, load_predictor
from clfbev.run.image_init import camera_fields, init_camera_encoder, resolve_image_init
from clfbev.run.memory import keep_freed_memory
from clfbev.run.pretrain import PretrainConfig, final_loss, pretrain
from clfbev.run.sheets import check_records, load_results, sample_sheet
from clfbev.run.torchvision_init import TORCHVISION
from clfbev.run.train import train
from clfbev.run.train_config import (SHIPPED, VERSION, add_setting_options, add_train_arguments, settings_from,
                                     train_config_from, whole_number)


def check_writable(out: Path, is_file: bool = False) -> None:
    """Refuse an output folder (or, with ``is_file``, the folder of an output file) whose nearest
    existing ancestor is not a writable folder."""
    p = Path(out).resolve()
    if is_file:
        if p.is_dir():
            raise OutputError(f"--out {out} is a directory, expected a file path")
        p = p.parent
    while not p.exists():
        p = p.parent
    if not p.is_dir():
        raise OutputError(f"--out {out}: {p} is not a directory")
    if not os.access(p, os.W_OK | os.X_OK):
        raise OutputError(f"--out {out}: {p} is not writable")


def _device():
    """The GPU when there is one."""
    return torch.device("cuda" if torch.cuda.is_available() else "cpu")


def _load(args):
    """(model, record) of --ckpt (a checkpoint or an experts file), refused unless of --config /
    --variant where given."""
    cfg = load_config(args.config) if args.config else None
    return load_predictor(args.ckpt, cfg, args.variant, device=_device())


# ---------------------------------------------------------------- commands

def cmd_train(args) -> None:
    """Train into --out (see clfbev.run.train); rank 0 prints the summary."""
    check_writable(args.out)
    if args.threads:
        torch.set_num_threads(args.threads)
    keep_freed_memory()
    cfg = load_config(args.config)
    if args.no_depth_loss:
        cfg = replace(cfg, loss=replace(cfg.loss, depth=0.0))
    summary = train(args.data, args.out, cfg, args.variant, train_config_from(args), resume=args.resume,
                    progress=not args.quiet)
    if int(os.environ.get("RANK", "0")) == 0:
        best = f", best val NDS {summary['best_nds']:.4f}" if summary["best_nds"] >= 0 else ""
        # A resumed run that was already finished trains no step, so it has no loss of its own.
        loss = f", final loss {summary['loss']:.4f}" if math.isfinite(summary["loss"]) else " (nothing left to train)"
        print(f"trained {summary['steps']} steps{loss}{best}; checkpoints in {args.out}")


def cmd_pretrain(args) -> None:
    """Pretrain the camera encoder into --out (see clfbev.run.pretrain)."""
    check_writable(args.out)
    if args.threads:
        torch.set_num_threads(args.threads)
    summary = pretrain(args.data, args.out, load_config(args.config), settings_from(args, PretrainConfig()),
                       resume=args.resume, progress=not args.quiet)
    print(f"pretrained {summary['steps']} steps, {final_loss(summary)}; encoder checkpoint {summary['encoder']} "
          f"(clfbev train --image-init {summary['encoder']})")


def cmd_cache_features(args) -> None:
    """The frozen encoder's features of every camera image of --split into --out (see
    clfbev.feature_cache); entries already there are kept, so a killed run is rerun as it was."""
    check_writable(args.out)
    cfg = load_config(args.config)
    if args.image_init in (TORCHVISION, EFFICIENTNET_LITE0):
        raise ConfigError(f"--image-init {args.image_init} loads a backbone alone; the cache needs the ResNet and FPN "
                          "of an encoder checkpoint")
    if resolve_image_init(args.image_init, cfg) is None:
        raise ConfigError(f"--image-init {args.image_init!r}: no encoder checkpoint to cache the features of "
                          f"(for this camera: {camera_fields(cfg)})")
    encoder = CameraEncoder.from_config(cfg)
    started = init_camera_encoder(encoder, args.image_init, cfg)
    encoder.freeze_image_features()
    ds = NuScenesDetection(args.data, args.version, args.split, cfg.data_config())
    cache = FeatureCache.create(args.out, encoder_identity(encoder))
    counts = fill_cache(ds, encoder, cache, progress=not args.quiet)
    print(f"cached the features of {counts['images']} images of {len(ds)} samples ({counts['computed']} computed, "
          f"{counts['kept']} already there) of the encoder {started} in {args.out}; "
          f"clfbev train --image-init {args.image_init} --image-freeze --feature-cache {args.out}")


def cmd_experts(args) -> None:
    """Assemble the sensor experts' file --out from the fused, camera and lidar checkpoints."""
    check_writable(args.out, is_file=True)
    paths = {role: path for role, path in (("fused", args.fused), ("camera", args.camera), ("lidar", args.lidar))
             if path is not None}
    experts = assemble(paths, args.out)
    roles = ", ".join(f"{role} {path}" for role, path in paths.items())
    print(f"wrote the {experts.variant} model ({roles}) to {args.out}; clfbev eval --ckpt {args.out}")


def cmd_export(args) -> None:
    """The weights of --ckpt, xz-compressed, for evaluation only."""
    check_writable(args.out, is_file=True)
    ckpt = export_weights(args.ckpt, args.out)
    size = args.out.stat().st_size
    print(f"wrote the {ckpt['variant']} weights of {args.ckpt} (step {ckpt['step']}) to {args.out} "
          f"({size / 1e6:.2f} MB); clfbev eval --ckpt {args.out}")


def cmd_eval(args) -> None:
    """--ckpt on --split through the devkit; the per-class table on stdout."""
    check_writable(args.out)
    model, _ = _load(args)
    ds = NuScenesDetection(args.data, args.version, args.split, model.cfg.data_config(), args.corrupt)
    summary = evaluate_model(model, ds, args.out, batch_size=args.batch_size, score_thr=args.score_thr,
                             plots=not args.no_plots)
    print(format_summary(summary))
    print(f"wrote {Path(args.out) / 'results.json'} and the devkit's metrics_summary.json / metrics_details.json "
          f"to {args.out}")


def format_summary(summary: dict) -> str:
    """The devkit summary as a per-class table plus mAP / NDS (what DetectionEval.main prints)."""
    tp = summary["label_tp_errors"]
    cols = ("trans_err", "scale_err", "orient_err", "vel_err", "attr_err")
    lines = [f"mAP {summary['mean_ap']:.4f}   NDS {summary['nd_score']:.4f}",
             f"{'class':22s} {'AP':>6s} " + " ".join(f"{c.split('_')[0][:6]:>7s}" for c in cols)]
    for name, ap in summary["mean_dist_aps"].items():
        lines.append(f"{name:22s} {ap:6.3f} " + " ".join(f"{tp[name][c]:7.3f}" for c in cols))
    return "\n".join(lines)


def _named_paths(items: list[str], flag: str) -> list[tuple[str, Path]]:
    """['NAME=PATH', ...] of option ``flag`` -> [(name, path), ...]."""
    out = []
    for item in items:
        name, sep, path = item.partition("=")
        if not sep or not name or not path:
            raise ConfigError(f"{flag} {item}: expected NAME=PATH")
        out.append((name, Path(path)))
    return out


def cmd_robustness(args) -> None:
    """Every --ckpt on every --set and --corrupt condition; the report in --out."""
    check_writable(args.out)
    ckpts = _named_paths(args.ckpt, "--ckpt")
    conditions = robustness.conditions_of(_named_paths(args.set, "--set"), args.corrupt, args.version)
    record = robustness.run(ckpts, conditions, Path(args.out), args.split, args.version)
    for name, m in record["models"].items():
        mce = f", mCE {m['mCE']:.3f}" if "mCE" in m else ""
        print(f"{name}: clean NDS {m['metrics'][record['clean']]['NDS']:.4f}, mRR {m['mRR']:.3f}{mce}")
    print(f"wrote robustness.json, robustness.md and robustness.png to {args.out}")


def cmd_predict(args) -> None:
    """The results JSON of --ckpt on --split, with no evaluation (any dataroot)."""
    check_writable(args.out, is_file=True)
    model, _ = _load(args)
    ds = NuScenesDetection(args.data, args.version, args.split, model.cfg.data_config())
    results = predict_split(model, ds, batch_size=args.batch_size, score_thr=args.score_thr)
    write_results(args.out, results)
    n = sum(len(v) for v in results.values())
    print(f"wrote {n} boxes for {len(results)} samples to {args.out}")


def cmd_show(args) -> None:
    """The sheet of one sample (and, with --attention, the attention strip below it) as an image."""

    check_writable(args.out, is_file=True)
    model = _attention_model(args) if args.attention else None   # a bad checkpoint fails before any drawing
    results = load_results(args.results)
    nusc = load_nuscenes(args.data, args.version)
    tokens = [t for t in (s["token"] for s in nusc.sample) if t in results]
    if not tokens:
        raise DataError(f"{args.results} has no sample of {Path(args.data) / args.version}")
    if not 0 <= args.sample < len(tokens):
        raise ConfigError(f"--sample {args.sample}: {args.results} covers {len(tokens)} samples (0..{len(tokens) - 1})")
    token = tokens[args.sample]
    sheet = sample_sheet(nusc, token, check_records(args.results, token, results[token]), args.score_thr)
    if model is not None:
        sheet = np.concatenate([sheet, _attention_strip(args, model, token, sheet.shape[1])], 0)
    io.write_image(args.out, sheet)
    print(f"wrote {args.out}")


def _attention_model(args):
    """The model of --ckpt; ConfigError (exit 2) if there is none or it has no attention module:
    --attention asks for a picture that such a variant cannot give, so it is refused, not skipped."""
    if not args.ckpt:
        raise ConfigError("--attention needs --ckpt (the model whose attention is drawn)")
    # A training checkpoint: an experts file holds three models and draws no single attention.
    model, _ = load_model(args.ckpt, load_config(args.config) if args.config else None, args.variant,
                          device=_device())
    if not attention_modules(model):
        raise ConfigError(f"--attention: {args.ckpt} is of variant '{model.variant}', which has no MCM or BSM "
                          "attention (the 'mcm' and 'full' variants have)")
    return model


def _attention_strip(args, model, token: str, width: int):
    """The MCM / BSM attention strip of sample ``token``, ``width`` pixels wide (BGR)."""
    ds = NuScenesDetection(args.data, args.version, "all", model.cfg.data_config())
    batch = collate([ds[ds.sample_tokens.index(token)]], model.cfg).to(_device())
    return draw_attention(model, batch, width, args.score_thr, args.cell)


# ---------------------------------------------------------------- option types (argparse exits 2 naming them)

def _xy(text: str) -> tuple[float, float]:
    """'X,Y' metres -> (x, y)."""
    try:
        x, y = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected X,Y in metres (e.g. 10,-5), got {text!r}") from None
    if not (math.isfinite(x) and math.isfinite(y)):
        raise argparse.ArgumentTypeError(f"expected finite X,Y in metres, got {text!r}")
    return x, y


def _score(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not 0.0 <= value <= 1.0:
        raise argparse.ArgumentTypeError(f"expected a score in [0, 1], got {text!r}")
    return value


def _image_path(text: str) -> Path:
    """An output image path whose suffix OpenCV can encode."""
    if not cv2.haveImageWriter(text):
        raise argparse.ArgumentTypeError(f"cannot write an image named {text!r}; use .png or .jpg")
    return Path(text)


CORRUPT_HELP = ("beam_missing:1-32 | density:0-1 | fov:DEGREES | lidar_missing | camera_crash:1-6 | "
                "frame_lost:0-1 | extrinsic_noise:DEG | motion_blur:PIXELS (1-100) | misalign:SENSOR:0-10 "
                "(s deg about each ego axis, 0.02 s m along each) | late:SENSOR:FRAMES (1-20); SENSOR is LIDAR_TOP "
                "or a camera channel, e.g. CAM_FRONT (clfbev/corruptions.py; deterministic per sample token)")


def _corruption(text: str):
    try:
        return parse_corruption(text)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


# ---------------------------------------------------------------- parser

def _model_args(p: argparse.ArgumentParser, ckpt_required: bool = True) -> None:
    """The options of the commands that run a checkpoint on a dataroot."""
    p.add_argument("--data", required=True, type=Path, help="nuScenes-format dataroot")
    p.add_argument("--ckpt", required=ckpt_required, type=Path, help="checkpoint (RUN/best.pt or RUN/last.pt)")
    p.add_argument("--version", default=VERSION, help="table folder under the dataroot")
    p.add_argument("--config", default=None, help="refuse a checkpoint not trained with this config")
    p.add_argument("--variant", default=None, choices=VARIANTS, help="refuse a checkpoint of another variant")
    p.add_argument("--batch-size", type=whole_number(1), default=1)


def _eval_score_thr(p: argparse.ArgumentParser) -> None:
    p.add_argument("--score-thr", type=_score, default=EVAL_SCORE_THR,
                   help=f"keep boxes scoring at least this (default {EVAL_SCORE_THR}: AP integrates over all "
                   "scores; at most 500 boxes per sample)")


def _add_train(sub) -> None:
    p = sub.add_parser("train", help="train a variant; checkpoints, logs and validation in --out",
                       description="Train CL-FusionBEV (or an ablation variant) from scratch. Writes RUN/last.pt "
                       "(atomically, every epoch and every --ckpt-minutes), RUN/best.pt (best val NDS), run.json, "
                       "metrics.jsonl and TensorBoard events in RUN/tb. Under torchrun it trains with DDP. Options "
                       "marked [recipe] default to the training recipe of the --config preset.")
    add_train_arguments(p)
    p.set_defaults(fn=cmd_train)


def _add_pretrain(sub) -> None:
    p = sub.add_parser(
        "pretrain", help="pretrain the camera encoder on dense labels (simgen make --dense-labels)",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Train the detector's image encoder (ResNet + FPN + depth net, as --config builds it) on the "
        "exact dense labels of a simulated set, then write RUN/encoder.pt for `clfbev train --image-init`.\n\n"
        "Targets per feature cell: the depth bin of the lift (cross-entropy; the nearest pixel of the cell), "
        "the nuScenes-lidarseg class of that pixel, and a perspective 3D head (CenterNet: a heatmap of the "
        "projected box centres, with offset, depth, size and heading).\n\n"
        "Make the pretraining set apart, with a seed of its own, never a split the detector is evaluated on:\n"
        "  simgen make --out PRE --seed 1001 --dense-labels ...\n"
        "  clfbev pretrain --data PRE --config tiny --out PRETRAIN\n"
        "  clfbev train --data DATA --config tiny --variant camera --image-init PRETRAIN/encoder.pt --out RUN\n"
        "encoder.pt records the command and the pretraining set's identity (its logs and a hash of its sample "
        "tokens). RUN also holds last.pt (kill and --resume: the same weights), run.json, metrics.jsonl, tb/.")
    p.add_argument("--data", required=True, type=Path, help="dataroot with dense/ labels")
    p.add_argument("--config", default="tiny", help="model config: 'tiny', 'paper' or a YAML file (the detector's)")
    p.add_argument("--out", required=True, type=Path,
                   help="run folder: encoder.pt, last.pt, run.json, metrics.jsonl, tb/")
    add_setting_options(p, PretrainConfig)
    p.add_argument("--threads", type=whole_number(0), default=0, help="torch CPU threads (0: torch's default)")
    p.add_argument("--resume", action="store_true", help="continue the run in --out from its last.pt")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(fn=cmd_pretrain)


def _add_cache_features(sub) -> None:
    p = sub.add_parser(
        "cache-features", help="compute the frozen image encoder's features of a split once, for a camera stage",
        description="Compute the FPN features of every camera image of --split with the encoder of --image-init "
        "(ResNet and FPN, frozen, eval mode, one image at a time on one thread, float32) and write one file per "
        "image into --out, named by the sha256 of the image file and checked against the encoder's identity "
        "(encoder.json). `clfbev train --image-init SAME --image-freeze --feature-cache CACHE` then reads them "
        "instead of the images. Rerunning keeps the entries already there: a killed run resumes.")
    p.add_argument("--data", required=True, type=Path, help="nuScenes-format dataroot")
    p.add_argument("--config", default="tiny", help="model config: 'tiny', 'paper' or a YAML file (the detector's)")
    p.add_argument("--image-init", default=SHIPPED, metavar="PATH",
                   help=f"the encoder checkpoint: PATH (of `clfbev pretrain`) or '{SHIPPED}' [default {SHIPPED}]")
    p.add_argument("--split", default="sim-train", help="split whose images to cache ('all': every scene)")
    p.add_argument("--version", default=VERSION, help="table folder under the dataroot")
    p.add_argument("--out", required=True, type=Path, help="cache folder (one per encoder)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(fn=cmd_cache_features)


def _add_experts(sub) -> None:
    p = sub.add_parser(
        "experts", help="one model of a fused checkpoint and its camera-only and lidar-only experts",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Write one file holding a fused model (concat, mcm or full) and a camera-only and a lidar-only "
        "model beside it, as the staged recipe trains them. Evaluated, each sample is answered by the model whose "
        "sensors delivered: no lidar point at all -> the camera expert; every camera missing -> the lidar expert; "
        "else the fused model (MoME's per-sensor experts, the router a rule on the sensors' presence). "
        "`clfbev eval`, `predict` and `robustness` take the file as --ckpt.\n\n"
        "  clfbev experts --fused STAGED/fusion/last.pt --camera STAGED/camera/last.pt "
        "--lidar STAGED/lidar/last.pt --out STAGED/experts.pt")
    p.add_argument("--fused", required=True, type=Path, help="checkpoint of a concat, mcm or full run")
    p.add_argument("--camera", type=Path, default=None, help="checkpoint of a camera run (same classes and loader)")
    p.add_argument("--lidar", type=Path, default=None, help="checkpoint of a lidar run (same classes and loader)")
    p.add_argument("--out", required=True, type=Path, help="the experts file to write")
    p.set_defaults(fn=cmd_experts)


def _add_export(sub) -> None:
    p = sub.add_parser("export", help="a checkpoint's weights alone, xz-compressed, for evaluation",
                       description="Write the model weights of a training checkpoint with its config and variant "
                       "(what `clfbev eval`, `predict` and `robustness` read), without the optimizer's state, "
                       "xz-compressed: a tiny model's final weights in 0.5-4 MB. Every command that takes --ckpt reads "
                       "the file as it is. It cannot be resumed from.")
    p.add_argument("--ckpt", required=True, type=Path, help="a training checkpoint (last.pt or best.pt)")
    p.add_argument("--out", required=True, type=Path, help="the file to write (e.g. weights.pt.xz)")
    p.set_defaults(fn=cmd_export)


def _add_eval(sub) -> None:
    p = sub.add_parser("eval", help="official nuScenes DetectionEval of a checkpoint on a split",
                       description="Predict a split, write results.json (nuScenes submission format) and run the "
                       "devkit's DetectionEval, restricted to the classes with GT in the split. Writes the devkit's "
                       "metrics_summary.json, metrics_details.json and plots/ to --out; prints a per-class table.")
    _model_args(p)
    _eval_score_thr(p)
    p.add_argument("--split", default="sim-val", help="split to evaluate (splits.json key or official)")
    p.add_argument("--out", required=True, type=Path, help="output folder")
    p.add_argument("--no-plots", action="store_true", help="skip the devkit's PR / TP curve plots")
    p.add_argument("--corrupt", action="append", default=[], type=_corruption, metavar="NAME:SEVERITY",
                   help=CORRUPT_HELP)
    p.set_defaults(fn=cmd_eval)


def _add_robustness(sub) -> None:
    p = sub.add_parser("robustness", help="every checkpoint on paired degraded sets and load-time corruptions",
                       description="Evaluate checkpoints on a clean set, paired degraded sets (simgen fog, rain, "
                       "snowfall, night, occluders, lens dirt, ...) and load-time corruptions, all through the "
                       "official DetectionEval, beside each condition's sensor-visibility oracle (the ground truth "
                       "that the condition's sensors still see, as predictions: the most any detector reaches). "
                       "Writes robustness.json, robustness.md (NDS/mAP, RR and mRR, CE and mCE against the concat "
                       "checkpoint, the share of the oracle) and robustness.png (NDS against severity per condition "
                       "family, bars for the rest) to --out. Each cell is kept in OUT/NAME/CONDITION/ with what it "
                       "evaluated: a rerun reuses the cells of unchanged checkpoints and sets.")
    p.add_argument("--ckpt", action="append", required=True, metavar="NAME=CKPT", help="a checkpoint (repeat)")
    p.add_argument("--set", action="append", required=True, metavar="NAME=DATAROOT",
                   help="a dataroot (repeat); the first is the clean reference, the others must be paired with it")
    p.add_argument("--corrupt", action="append", default=[], type=_corruption, metavar="NAME:SEVERITY",
                   help="a load-time corruption of the clean set, one condition each (repeat). " + CORRUPT_HELP)
    p.add_argument("--split", default="sim-val", help="split to evaluate")
    p.add_argument("--version", default=VERSION, help="table folder under each dataroot")
    p.add_argument("--out", required=True, type=Path, help="output folder")
    p.set_defaults(fn=cmd_robustness)


def _add_predict(sub) -> None:
    p = sub.add_parser("predict", help="results JSON for any dataroot (annotated or not)",
                       description="Run a checkpoint on a dataroot and write nuScenes-format results.")
    _model_args(p)
    _eval_score_thr(p)
    p.add_argument("--split", default="all", help="split to predict ('all': every scene)")
    p.add_argument("--out", required=True, type=Path, help="results JSON path")
    p.set_defaults(fn=cmd_predict)


def _add_show(sub) -> None:
    p = sub.add_parser("show", help="cameras + BEV with predictions and GT (and attention maps) as a PNG",
                       description="Draw one sample: the six cameras and a BEV, GT in green and predictions in "
                       "orange. --attention adds, below, the MCM and BSM attention of one BEV query cell "
                       "(needs --ckpt of an 'mcm' or 'full' model; other variants exit 2): the cell under the "
                       "centre of that model's best detection scoring at least --score-thr, else under the GT "
                       "box nearest the ego, or --cell. Each panel zooms on the weights (window mode: the "
                       "query's window) and shows the mean over heads and each head.")
    _model_args(p, ckpt_required=False)
    p.add_argument("--results", required=True, type=Path, help="results JSON (from eval or predict)")
    p.add_argument("--sample", type=int, default=0, help="index among the samples the results cover")
    p.add_argument("--score-thr", type=_score, default=0.3, help="draw predictions scoring at least this")
    p.add_argument("--attention", action="store_true", help="add the MCM / BSM attention of a query cell "
                   "(mcm / full variants)")
    p.add_argument("--cell", default=None, type=_xy, metavar="X,Y",
                   help="query point in metres, lidar frame (default: the best detection's centre)")
    p.add_argument("--out", required=True, type=_image_path, help="PNG path")
    p.set_defaults(fn=cmd_show)


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="clfbev", description="CL-FusionBEV: camera + lidar BEV fusion detector "
                                 "(train, evaluate with the official nuScenes metrics, predict, visualise).")
    sub = ap.add_subparsers(dest="command", required=True)
    for add in (_add_train, _add_pretrain, _add_cache_features, _add_experts, _add_export, _add_eval, _add_robustness,
                _add_predict, _add_show):
        add(sub)
    return ap


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)    # argparse itself exits 2 on malformed options
    return run_guarded(lambda: args.fn(args))
