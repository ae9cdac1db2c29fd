"""The records of a run folder besides its checkpoints: ``run.json`` (what was run, by which code),
``metrics.jsonl`` and TensorBoard events (the scalars of every step), and the loss curve drawn
from them."""
from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import asdict
from pathlib import Path

import numpy as np

from clfbev import io
from clfbev.config import ModelConfig
from clfbev.run.train_config import TrainConfig

PACKAGE = Path(__file__).resolve().parents[1]       # the clfbev folder


def code_version(here: Path | None = None) -> str:
    """``git describe`` of the source tree, ``-dirty`` when a tracked file of the package folder
    ``here`` (default: clfbev) is modified: a changed doc or script elsewhere in the tree does
    not change a run. Else the package version."""
    here = PACKAGE if here is None else here
    try:
        out = subprocess.run(["git", "describe", "--always"], cwd=here, capture_output=True, text=True, timeout=10)
        changed = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no", "--", "."], cwd=here,
                                 capture_output=True, text=True, timeout=10)
        if out.returncode == 0 and out.stdout.strip() and changed.returncode == 0:
            return out.stdout.strip() + ("-dirty" if changed.stdout.strip() else "")
    except (OSError, subprocess.SubprocessError):
        pass
    from importlib.metadata import PackageNotFoundError, version
    try:
        return version("clfusionbev")
    except PackageNotFoundError:
        return "unknown"


def write_run_json(run: Path, cfg: ModelConfig, variant: str, tc: TrainConfig, world: int, version: str,
                   step: int) -> None:
    """``RUN/run.json``: the config, variant, training settings, code version and command line of
    the run, and the step it (re)started at."""
    io.write_json(run / "run.json", {"config": cfg.to_dict(), "variant": variant, "train": asdict(tc),
                                     "world_size": world, "code_version": version,
                                     "argv": sys.argv, "resumed_at_step": step})


class ScalarLog:
    """Scalars to ``RUN/metrics.jsonl`` (one JSON object per line) and TensorBoard ``RUN/tb``.
    On resume from step k, lines of steps > k (written after the checkpoint) are dropped and
    TensorBoard purges its events after k, so the logs read as one uninterrupted run."""

    def __init__(self, run: Path, resume_step: int) -> None:
        from torch.utils.tensorboard import SummaryWriter
        self.path = run / "metrics.jsonl"
        if self.path.exists():
            keep = [ln for ln in self.path.read_text().splitlines()
                    if ln.strip() and _complete_json(ln) and json.loads(ln)["step"] <= resume_step]
            io.write_text(self.path, "".join(ln + "\n" for ln in keep))
        self.file = self.path.open("a")
        self.tb = SummaryWriter(str(run / "tb"), purge_step=resume_step + 1 if resume_step else None)

    def log(self, step: int, epoch: int, scalars: dict[str, float]) -> None:
        self.file.write(json.dumps({"step": step, "epoch": epoch, **scalars}) + "\n")
        self.file.flush()
        for k, v in scalars.items():
            self.tb.add_scalar(k, v, step)

    def close(self) -> None:
        self.file.close()
        self.tb.close()


def _complete_json(line: str) -> bool:
    """Whether ``line`` is a whole JSON object with a step (a kill can tear the last line)."""
    try:
        row = json.loads(line)
    except ValueError:
        return False
    return isinstance(row, dict) and "step" in row


def plot_loss_curve(metrics_jsonl: str | Path, out_png: str | Path) -> Path:
    """``out_png``: the training loss (and its parts) of ``metrics_jsonl`` against the step, val
    NDS / mAP on a second axis."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = [json.loads(ln) for ln in Path(metrics_jsonl).read_text().splitlines() if ln.strip()]
    train = [r for r in rows if "train/loss" in r]
    val = [r for r in rows if "val/NDS" in r]
    fig, ax = plt.subplots(figsize=(8, 4.5), dpi=110)
    steps = np.array([r["step"] for r in train])
    parts = (("train/loss", "-"), ("train/loss_cls", ":"), ("train/loss_reg", "--"), ("train/loss_dir", "-."),
             ("train/loss_depth", (0, (1, 3))))
    for key, style in (p for p in parts if any(p[0] in r for r in train)):
        y, x = np.array([r.get(key, np.nan) for r in train]), steps
        k = max(1, len(y) // 50)
        if k > 1:    # a trailing running mean makes the trend readable; raw values are in the JSONL
            y, x = np.convolve(y, np.ones(k) / k, mode="valid"), steps[k - 1:]
        ax.plot(x, y, linestyle=style, label=key.split("/")[1])
    ax.set_yscale("log")
    ax.set_xlabel("step")
    ax.set_ylabel("loss")
    ax.grid(alpha=0.3)
    ax.legend(loc="upper left")
    if val:
        ax2 = ax.twinx()
        ax2.plot([r["step"] for r in val], [r["val/NDS"] for r in val], "o-", color="tab:green", label="val NDS")
        ax2.plot([r["step"] for r in val], [r["val/mAP"] for r in val], "s-", color="tab:red", label="val mAP")
        ax2.set_ylabel("val metric")
        ax2.set_ylim(0, 1)
        ax2.legend(loc="upper right")
    fig.tight_layout()
    path = io.save_figure(out_png, fig)
    plt.close(fig)
    return path
