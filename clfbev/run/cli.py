"""`clfbev train | eval | predict | show | robustness`: the detector's command line.

    clfbev train   --data DIR --config tiny --variant full --out RUN [--epochs N | --max-steps N] [--resume]
    clfbev eval    --data DIR --ckpt RUN/best.pt [--split sim-val] --out DIR
    clfbev predict --data DIR --ckpt CKPT --out results.json [--split all]
    clfbev show    --data DIR --results results.json [--sample I] --out FILE.png [--attention --ckpt CKPT [--cell X,Y]]
    clfbev robustness --ckpt NAME=CKPT ... --set NAME=DATAROOT ... [--corrupt NAME:SEV ...] --out DIR

Bad input (a missing dataroot, an unknown split, a corrupt or mismatched checkpoint, an invalid
config file, an unwritable output) gets one line on stderr naming the file or option, and exit
code 2. A non-finite training loss stops training with exit code 3, keeping the last checkpoint.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

EXIT_BAD_INPUT = 2
EXIT_TRAIN_FAILED = 3


def run_guarded(fn) -> int:
    """Run ``fn()``; map the project's input errors to one stderr line and exit code 2."""
    from clfbev.checkpoint import CheckpointError
    from clfbev.data import DataError
    from clfbev.train import TrainError
    try:
        fn()
        return 0
    except (DataError, CheckpointError, ValueError, PermissionError, NotADirectoryError, IsADirectoryError, FileExistsError) as e:
        print(f"clfbev: error: {e}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except TrainError as e:
        print(f"clfbev: error: {e}", file=sys.stderr)
        return EXIT_TRAIN_FAILED
    except KeyboardInterrupt:
        print("clfbev: interrupted; `clfbev train ... --resume` continues from the last checkpoint", file=sys.stderr)
        return 130


def check_writable(out: Path, is_file: bool = False) -> None:
    """Refuse an output folder (or, with ``is_file``, the folder of an output file) whose nearest
    existing ancestor is not a writable folder."""
    p = Path(out).resolve()
    if is_file:
        if p.is_dir():
            raise IsADirectoryError(f"--out {out} is a directory, expected a file path")
        p = p.parent
    while not p.exists():
        p = p.parent
    if not p.is_dir():
        raise NotADirectoryError(f"--out {out}: {p} is not a directory")
    if not os.access(p, os.W_OK | os.X_OK):
        raise PermissionError(f"--out {out}: {p} is not writable")


def _device():
    import torch
    return torch.device("cuda" if torch.cuda.is_available() else "cpu")


def _load(args):
    from clfbev.checkpoint import load_model
    from clfbev.config import load_config
    cfg = load_config(args.config) if args.config else None
    return load_model(args.ckpt, cfg, args.variant, device=_device())


# ---------------------------------------------------------------- commands

def cmd_train(args) -> None:
    from clfbev.train import run_from_args
    check_writable(args.out)
    run_from_args(args)


def cmd_eval(args) -> None:
    from clfbev.data import NuScenesDetection
    from clfbev.evaluate import evaluate, predict_split, write_results
    check_writable(args.out)
    model, _ = _load(args)
    ds = NuScenesDetection(args.data, args.version, args.split, model.cfg.data_config(), args.corrupt)
    results = predict_split(model, ds, batch_size=args.batch_size, score_thr=args.score_thr)
    path = write_results(Path(args.out) / "results.json", results)
    summary = evaluate(ds.nusc, path, args.split, args.out, model.cfg.class_names, plots=not args.no_plots)
    print(format_summary(summary))
    print(f"wrote {path} and the devkit's metrics_summary.json / metrics_details.json to {args.out}")


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
    out = []
    for item in items:
        name, sep, path = item.partition("=")
        if not sep or not name or not path:
            raise ValueError(f"{flag} {item}: expected NAME=PATH")
        out.append((name, Path(path)))
    return out


def cmd_robustness(args) -> None:
    from clfbev import robustness
    check_writable(args.out)
    ckpts = _named_paths(args.ckpt, "--ckpt")
    conditions = robustness.conditions_of(_named_paths(args.set, "--set"), args.corrupt, args.version)
    record = robustness.run(ckpts, conditions, Path(args.out), args.split, args.version)
    for name, m in record["models"].items():
        mce = f", mCE {m['mCE']:.3f}" if "mCE" in m else ""
        print(f"{name}: clean NDS {m['metrics'][record['clean']]['NDS']:.4f}, mRR {m['mRR']:.3f}{mce}")
    print(f"wrote robustness.json, robustness.md and robustness.png to {args.out}")


def cmd_predict(args) -> None:
    from clfbev.data import NuScenesDetection
    from clfbev.evaluate import predict_split, write_results
    check_writable(args.out, is_file=True)
    model, _ = _load(args)
    ds = NuScenesDetection(args.data, args.version, args.split, model.cfg.data_config())
    results = predict_split(model, ds, batch_size=args.batch_size, score_thr=args.score_thr)
    write_results(args.out, results)
    n = sum(len(v) for v in results.values())
    print(f"wrote {n} boxes for {len(results)} samples to {args.out}")


def cmd_show(args) -> None:
    import cv2
    import numpy as np
    from clfbev.data import DataError, load_nuscenes
    from clfbev.visualize import load_results, sample_sheet

    check_writable(args.out, is_file=True)
    model = _attention_model(args) if args.attention else None   # a bad checkpoint fails before any drawing
    results = load_results(args.results)
    nusc = load_nuscenes(args.data, args.version)
    tokens = [t for t in (s["token"] for s in nusc.sample) if t in results]
    if not tokens:
        raise DataError(f"{args.results} has no sample of {Path(args.data) / args.version}")
    if not 0 <= args.sample < len(tokens):
        raise ValueError(f"--sample {args.sample}: {args.results} covers {len(tokens)} samples (0..{len(tokens) - 1})")
    token = tokens[args.sample]
    sheet = sample_sheet(nusc, token, results[token], args.score_thr)
    if model is not None:
        sheet = np.concatenate([sheet, _attention_strip(args, model, token, sheet.shape[1])], 0)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(f".{out.stem}.tmp{out.suffix}")
    if not cv2.imwrite(str(tmp), sheet):
        raise ValueError(f"--out {out}: cannot write an image with that extension")
    tmp.replace(out)
    print(f"wrote {out}")


def _attention_model(args):
    """The model of --ckpt; ValueError (exit 2) if there is none or it has no attention module:
    --attention asks for a picture that such a variant cannot give, so it is refused, not skipped."""
    from clfbev.visualize import attention_modules
    if not args.ckpt:
        raise ValueError("--attention needs --ckpt (the model whose attention is drawn)")
    model, _ = _load(args)
    if not attention_modules(model):
        raise ValueError(f"--attention: {args.ckpt} is of variant '{model.variant}', which has no MCM or BSM "
                         "attention (the 'mcm' and 'full' variants have)")
    return model


def _attention_strip(args, model, token: str, width: int):
    """The MCM / BSM attention strip of sample ``token``, ``width`` pixels wide (BGR)."""
    from clfbev.data import NuScenesDetection, collate
    from clfbev.visualize import draw_attention
    ds = NuScenesDetection(args.data, args.version, "all", model.cfg.data_config())
    batch = collate([ds[ds.sample_tokens.index(token)]]).to(_device())
    return draw_attention(model, batch, width, args.score_thr, args.cell)


def _xy(text: str) -> tuple[float, float]:
    """'X,Y' metres -> (x, y); an argparse type, so a malformed value exits 2 naming it."""
    try:
        x, y = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected X,Y in metres (e.g. 10,-5), got {text!r}") from None
    return x, y


# ---------------------------------------------------------------- parser

CORRUPT_HELP = ("beam_missing:1-32 | density:0-1 | fov:DEGREES | lidar_missing | camera_crash:1-6 | "
                "frame_lost:0-1 | extrinsic_noise:DEG (deterministic per sample token)")


def _corruption(text: str):
    from clfbev.corruptions import parse
    try:
        return parse(text)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


def build_parser() -> argparse.ArgumentParser:
    from clfbev.config import VARIANTS
    from clfbev.evaluate import EVAL_SCORE_THR
    from clfbev.train import VERSION, add_arguments

    ap = argparse.ArgumentParser(prog="clfbev", description="CL-FusionBEV: camera + lidar BEV fusion detector "
                                 "(train, evaluate with the official nuScenes metrics, predict, visualise).")
    sub = ap.add_subparsers(dest="command", required=True)

    p = sub.add_parser("train", help="train a variant; checkpoints, logs and validation in --out",
                       description="Train CL-FusionBEV (or an ablation variant) from scratch. Writes RUN/last.pt "
                       "(atomically, every epoch and every --ckpt-minutes), RUN/best.pt (best val NDS), run.json, "
                       "metrics.jsonl and TensorBoard events in RUN/tb. Under torchrun it trains with DDP.")
    add_arguments(p)
    p.set_defaults(fn=cmd_train)

    def model_args(p, ckpt_required=True):
        p.add_argument("--data", required=True, type=Path, help="nuScenes-format dataroot")
        p.add_argument("--ckpt", required=ckpt_required, type=Path, help="checkpoint (RUN/best.pt or RUN/last.pt)")
        p.add_argument("--version", default=VERSION, help="table folder under the dataroot")
        p.add_argument("--config", default=None, help="refuse a checkpoint not trained with this config")
        p.add_argument("--variant", default=None, choices=VARIANTS, help="refuse a checkpoint of another variant")
        p.add_argument("--batch-size", type=int, default=1)
        if ckpt_required:
            p.add_argument("--score-thr", type=float, default=EVAL_SCORE_THR,
                           help=f"keep boxes scoring at least this (default {EVAL_SCORE_THR}: AP integrates "
                                "over all scores; at most 500 boxes per sample)")

    p = sub.add_parser("eval", help="official nuScenes DetectionEval of a checkpoint on a split",
                       description="Predict a split, write results.json (nuScenes submission format) and run the "
                       "devkit's DetectionEval, restricted to the classes with GT in the split. Writes the devkit's "
                       "metrics_summary.json, metrics_details.json and plots/ to --out; prints a per-class table.")
    model_args(p)
    p.add_argument("--split", default="sim-val", help="split to evaluate (splits.json key or official)")
    p.add_argument("--out", required=True, type=Path, help="output folder")
    p.add_argument("--no-plots", action="store_true", help="skip the devkit's PR / TP curve plots")
    p.add_argument("--corrupt", action="append", default=[], type=_corruption, metavar="NAME:SEVERITY",
                   help=CORRUPT_HELP)
    p.set_defaults(fn=cmd_eval)

    p = sub.add_parser("robustness", help="every checkpoint on paired degraded sets and load-time corruptions",
                       description="Evaluate checkpoints on a clean set, paired degraded sets (simgen fog, lens "
                       "dirt, ...) and load-time corruptions, all through the official DetectionEval. Writes "
                       "robustness.json, robustness.md (NDS/mAP, RR and mRR, CE and mCE against the concat "
                       "checkpoint) and robustness.png to --out.")
    p.add_argument("--ckpt", action="append", required=True, metavar="NAME=CKPT", help="a checkpoint (repeat)")
    p.add_argument("--set", action="append", required=True, metavar="NAME=DATAROOT",
                   help="a dataroot (repeat); the first is the clean reference, the others must be paired with it")
    p.add_argument("--corrupt", action="append", default=[], type=_corruption, metavar="NAME:SEVERITY",
                   help="a load-time corruption of the clean set, one condition each (repeat). " + CORRUPT_HELP)
    p.add_argument("--split", default="sim-val", help="split to evaluate")
    p.add_argument("--version", default=VERSION, help="table folder under each dataroot")
    p.add_argument("--out", required=True, type=Path, help="output folder")
    p.set_defaults(fn=cmd_robustness)

    p = sub.add_parser("predict", help="results JSON for any dataroot (annotated or not)",
                       description="Run a checkpoint on a dataroot and write nuScenes-format results.")
    model_args(p)
    p.add_argument("--split", default="all", help="split to predict ('all': every scene)")
    p.add_argument("--out", required=True, type=Path, help="results JSON path")
    p.set_defaults(fn=cmd_predict)

    p = sub.add_parser("show", help="cameras + BEV with predictions and GT (and attention maps) as a PNG",
                       description="Draw one sample: the six cameras and a BEV, GT in green and predictions in "
                       "orange. --attention adds, below, the MCM and BSM attention of one BEV query cell "
                       "(needs --ckpt of an 'mcm' or 'full' model; other variants exit 2): the cell under the "
                       "centre of that model's best detection scoring at least --score-thr, else under the GT "
                       "box nearest the ego, or --cell. Each panel zooms on the weights (window mode: the "
                       "query's window) and shows the mean over heads and each head.")
    model_args(p, ckpt_required=False)
    p.add_argument("--results", required=True, type=Path, help="results JSON (from eval or predict)")
    p.add_argument("--sample", type=int, default=0, help="index among the samples the results cover")
    p.add_argument("--score-thr", type=float, default=0.3, help="draw predictions scoring at least this")
    p.add_argument("--attention", action="store_true", help="add the MCM / BSM attention of a query cell "
                   "(mcm / full variants)")
    p.add_argument("--cell", default=None, type=_xy, metavar="X,Y",
                   help="query point in metres, lidar frame (default: the best detection's centre)")
    p.add_argument("--out", required=True, type=Path, help="PNG path")
    p.set_defaults(fn=cmd_show)
    return ap


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)    # argparse itself exits 2 on malformed options
    return run_guarded(lambda: args.fn(args))


if __name__ == "__main__":
    sys.exit(main())
