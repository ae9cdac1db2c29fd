"""The record beside a shipped encoder: how it was made, from what, at what cost.

    python scripts/encoder_record.py WEIGHTS.pt --run RUN --make-command "simgen make ..." \
        --make-seconds S --pretrain-seconds S --threads N

Writes WEIGHTS.json (atomically): the encoder checkpoint's own command, pretraining-set identity,
step and code version (clfbev/run/image_init.py writes them into the checkpoint), the command
that made the pretraining set, the images seen (steps x batch x 6 cameras), the wall time of each
stage with the thread count, and the mean of each pretraining loss over the last 50 steps of
RUN/metrics.jsonl. A checkpoint or run that is missing or junk is one line naming it, exit 2.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

from clfbev import io
from clfbev.data import CAMERAS
from clfbev.errors import DataError, run_guarded
from clfbev.run.image_init import load_encoder_checkpoint

LAST_STEPS = 50


def final_losses(metrics: Path) -> dict:
    """{loss name: mean over the last LAST_STEPS logged steps} of a pretraining metrics.jsonl."""
    try:
        rows = [json.loads(line) for line in metrics.read_text().splitlines() if line.strip()]
    except (OSError, json.JSONDecodeError) as e:
        raise DataError(f"{metrics}: not a metrics log ({e})") from None
    rows = [r for r in rows if "pretrain/loss" in r][-LAST_STEPS:]
    if not rows:
        raise DataError(f"{metrics}: no pretraining step logged")
    keys = [k for k in rows[-1] if k.startswith("pretrain/loss")]
    return {k.split("/", 1)[1]: round(sum(r[k] for r in rows) / len(rows), 4) for k in keys}


def record(weights: Path, run: Path, make_command: str, make_s: int, pretrain_s: int, threads: int) -> dict:
    ckpt = load_encoder_checkpoint(weights)
    run_info = json.loads((run / "run.json").read_text())
    batch = run_info["train"]["batch_size"]
    return {
        "weights": weights.name,
        "made_by": "bash scripts/pretrain_encoder.sh",
        "data_command": make_command,
        "pretrain_command": ckpt["command"],
        "pretraining_set": ckpt["data"],
        "camera": ckpt["camera"],
        "steps": ckpt["step"],
        "images_seen": ckpt["step"] * batch * len(CAMERAS),
        "code_version": ckpt["code_version"],
        "wall_seconds": {"make": make_s, "pretrain": pretrain_s},
        "threads": threads,
        f"losses_last_{LAST_STEPS}_steps": final_losses(run / "metrics.jsonl"),
    }


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("weights", type=Path)
    p.add_argument("--run", type=Path, required=True)
    p.add_argument("--make-command", required=True)
    p.add_argument("--make-seconds", type=int, required=True)
    p.add_argument("--pretrain-seconds", type=int, required=True)
    p.add_argument("--threads", type=int, required=True)
    a = p.parse_args(argv)
    if not (a.run / "run.json").is_file():
        raise DataError(f"{a.run / 'run.json'} does not exist: not a pretraining run folder")
    rec = record(a.weights, a.run, a.make_command, a.make_seconds, a.pretrain_seconds, a.threads)
    io.write_text(a.weights.with_suffix(".json"), json.dumps(rec, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(run_guarded(main))
