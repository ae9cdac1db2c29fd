#!/usr/bin/env python
"""Write demo_out/REPORT.md from what scripts/demo.sh produced: the devkit's metrics, the
per-class table, the loss curve, the overlays and the timings.

    python scripts/demo_report.py OUT_DIR --run RUN_DIR --timing OUT_DIR/timing.json
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("out", type=Path, help="the demo's output folder")
    ap.add_argument("--timing", type=Path, required=True, help="JSON of stage -> seconds")
    ap.add_argument("--run", type=Path, default=None, help="the training run whose model is shown (default OUT/run); "
                    "a staged recipe's fusion stage, with its staged.json beside it")
    args = ap.parse_args()
    from clfbev import io
    from clfbev.run.cli import format_summary
    from clfbev.run.run_log import plot_loss_curve

    out = args.out
    timing = json.loads(args.timing.read_text())
    summary = json.loads((out / "eval" / "metrics_summary.json").read_text())
    run_dir = args.run or out / "run"
    run = json.loads((run_dir / "run.json").read_text())
    plot_loss_curve(run_dir / "metrics.jsonl", out / "loss_curve.png")
    check = (out / "check.txt").read_text().strip() if (out / "check.txt").exists() else ""
    tc = run["train"]
    lines = [
        "# CL-FusionBEV demo report",
        "",
        f"Generated with `bash scripts/demo.sh` in {timing['total_s'] / 60:.1f} min on this machine "
        f"(code {run['code_version']}).",
        "",
        "| stage | seconds |",
        "|---|---:|",
        *[f"| {k.removesuffix('_s')} | {v:.0f} |" for k, v in timing.items() if k.endswith("_s") and k != "total_s"],
        f"| **total** | **{timing['total_s']:.0f}** |",
        "",
        "## Data",
        "",
        f"`simgen make --scenes {timing.get('scenes', '?')}` (preset urban), validated by `simgen check`:",
        "",
        "```", check, "```",
        "",
        "## Training",
        "",
        *training_lines(run, run_dir),
        "",
        "![training losses](loss_curve.png)",
        "",
        "## Evaluation (official nuScenes DetectionEval on sim-val)",
        "",
        "Classes restricted to those with ground truth in the split. The attribute: moving above "
        "simgen's speed thresholds, else the state the head's still logit names (clfbev/attributes.py).",
        "",
        "```", format_summary(summary), "```",
        "",
        "Devkit files: `eval/metrics_summary.json`, `eval/metrics_details.json`, curves in `eval/plots/`.",
        "",
        "## Pictures",
        "",
        "Six cameras and the BEV; ground truth green, predictions (score >= 0.3) orange; below, the MCM "
        "and BSM attention of one BEV query cell (the best-scoring prediction).",
        "",
        "![camera overlays, BEV and attention maps](overlay.png)",
        "",
    ]
    io.write_text(out / "REPORT.md", "\n".join(lines))
    print(f"wrote {out / 'REPORT.md'}: mAP {summary['mean_ap']:.4f}, NDS {summary['nd_score']:.4f}, "
          f"car AP {summary['mean_dist_aps'].get('car', float('nan')):.4f}")
    return 0


def training_lines(run: dict, run_dir: Path) -> list[str]:
    """What trained the model: the tiny recipe's settings, and for a staged recipe's fusion stage
    each stage's steps and CPU time (its staged.json)."""
    tc = run["train"]
    length = f"{tc['max_steps']} steps" if tc["max_steps"] else f"{tc['epochs']} epochs"
    recipe = (f"batch {tc['batch_size']}, AdamW lr {tc['lr']:g} (warmup {tc['warmup_frac']:.0%} then cosine), "
              f"weight decay {tc['weight_decay']:g}, grad clip {tc['grad_clip']:g}, augmentation "
              f"{'on' if tc['augment'] else 'off'}, GT-paste {tc.get('gt_paste', 0)} objects per sample (none in the "
              f"last {tc.get('gt_paste_fade', 0):.0%} of the steps), seed {tc['seed']}")
    staged = run_dir.parent / "staged.json"
    if not (tc.get("lidar_init") and staged.exists()):
        return [f"`clfbev train --config tiny --variant {run['variant']}`: {length}, {recipe}: the tiny recipe. "
                "Checkpoint: the final weights (`last.pt`)."]
    stages = json.loads(staged.read_text())["stages"]
    rows = [f"| {name} | {entry['settings'].split(' --max-steps ')[-1].split()[0] if '--max-steps' in entry['settings'] else '-'} "
            f"| {sum(p['user_s'] + p['sys_s'] for p in entry['parts']):.0f} |" for name, entry in stages.items()]
    return [f"The staged recipe (`scripts/staged.sh`): the camera on its frozen encoder's cached features, the "
            f"lidar apart, then the `{run['variant']}` fusion stage from both ({length}, {recipe}). The evaluated "
            "model is the experts file: the fused model, with the camera and lidar stages for a sample without lidar "
            "or cameras.", "", "| stage | steps | CPU-s |", "|---|---:|---:|", *rows]


if __name__ == "__main__":
    sys.exit(main())
