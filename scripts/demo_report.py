#!/usr/bin/env python
"""Write demo_out/REPORT.md from what scripts/demo.sh produced: the devkit's metrics, the
per-class table, the loss curve, the overlays and the timings.

    python scripts/demo_report.py OUT_DIR --timing OUT_DIR/timing.json
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
    args = ap.parse_args()
    from clfbev import io
    from clfbev.run.cli import format_summary
    from clfbev.run.run_log import plot_loss_curve

    out = args.out
    timing = json.loads(args.timing.read_text())
    summary = json.loads((out / "eval" / "metrics_summary.json").read_text())
    run = json.loads((out / "run" / "run.json").read_text())
    plot_loss_curve(out / "run" / "metrics.jsonl", out / "loss_curve.png")
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
        f"`clfbev train --config tiny --variant {run['variant']}`: {tc['epochs'] if not tc['max_steps'] else tc['max_steps']} "
        f"{'epochs' if not tc['max_steps'] else 'steps'}, batch {tc['batch_size']}, AdamW lr {tc['lr']:g} "
        f"(warmup {tc['warmup_frac']:.0%} then cosine), weight decay {tc['weight_decay']:g}, grad clip {tc['grad_clip']:g}, "
        f"augmentation {'on' if tc['augment'] else 'off'}, GT-paste {tc.get('gt_paste', 0)} objects per sample "
        f"(none in the last {tc.get('gt_paste_fade', 0):.0%} of the steps), seed {tc['seed']}: the tiny recipe. "
        "Checkpoint: the final weights (`last.pt`).",
        "",
        "![training losses](loss_curve.png)",
        "",
        "## Evaluation (official nuScenes DetectionEval on sim-val)",
        "",
        "Classes restricted to those with ground truth in the split. The attribute is derived from "
        "the predicted speed, not learned (see clfbev/run/evaluate.py).",
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


if __name__ == "__main__":
    sys.exit(main())
