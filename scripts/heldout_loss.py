"""A trained model's detection and depth losses on a held-out split: what tells short runs
apart while their AP is still 0.

    python scripts/heldout_loss.py DATAROOT RUN/last.pt [RUN2/last.pt ...] [--split sim-val]

Each sample of the split alone (no augmentation, the evaluation's loader), the model in eval
mode (BatchNorm's running statistics), the training's targets and loss
(:func:`clfbev.supervision.targets.training_loss`; the camera BEV's auxiliary heads run in
training only, so their terms are left out): prints per checkpoint the mean over the samples of
``loss_cls``, ``loss_reg`` (with the angle's term), ``loss_dir`` and, with a camera,
``loss_depth``, as a markdown table. A missing or junk file is one line naming it, exit 2.
"""
from __future__ import annotations

import argparse

import torch

from clfbev.errors import run_guarded

KEYS = ("loss_cls", "loss_reg", "loss_dir", "loss_depth")


def heldout(ckpt: str, data: str, split: str) -> dict[str, float]:
    """{loss name: mean over the samples of ``split``} of the checkpoint at ``ckpt``."""
    from dataclasses import replace

    from clfbev.data import NuScenesDetection, collate
    from clfbev.run.checkpoint import load_model
    from clfbev.supervision.targets import training_loss, with_targets
    model, _ = load_model(ckpt)
    # The detection's and the depth's targets and terms only: the aux heads do not run here.
    cfg = replace(model.cfg, cam_heatmap=0.0, cam_distill=0.0, cam_distill_teacher="")
    dataset = NuScenesDetection(data, "v1.0-sim", split, cfg.data_config())
    sums: dict[str, float] = {}
    with torch.no_grad():
        for i in range(len(dataset)):
            batch, targets = with_targets(collate([dataset[i]]), cfg, model.anchors,
                                          cameras=model.camera_encoder is not None)
            losses = training_loss(model(batch), targets, cfg)
            losses["loss_reg"] = losses["loss_reg"] + losses["loss_reg_theta"]
            for k in KEYS:
                if k in losses:
                    sums[k] = sums.get(k, 0.0) + float(losses[k])
    return {k: v / len(dataset) for k, v in sums.items()}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("data")
    ap.add_argument("ckpts", nargs="+")
    ap.add_argument("--split", default="sim-val")
    args = ap.parse_args()
    torch.set_num_threads(1)

    def run() -> None:
        print("| checkpoint | " + " | ".join(KEYS) + " |")
        print("|---|" + "---:|" * len(KEYS))
        for ckpt in args.ckpts:
            got = heldout(ckpt, args.data, args.split)
            print(f"| {ckpt} | " + " | ".join(f"{got[k]:.4f}" if k in got else "-" for k in KEYS) + " |", flush=True)
    return run_guarded(run, "heldout_loss")


if __name__ == "__main__":
    raise SystemExit(main())
