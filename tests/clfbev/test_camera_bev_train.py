"""`clfbev train --variant camera` with the camera BEV's denser supervision on (the heatmap head,
the distillation from a lidar checkpoint, the bilinear lift): the new losses are logged, and a
run killed with SIGKILL and resumed ends bit-identical to an uninterrupted one (four training
processes: about a minute on a shared core, so marked slow; the in-process checks of the same
parts are in test_distill.py, test_heatmap.py and test_bilinear_lift.py)."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time

import pytest
import torch

from clfbev.config_file import load_config
from clfbev.model import CLFusionBEV
from clfbev.run.checkpoint import load_checkpoint, save_checkpoint

pytestmark = pytest.mark.usefixtures("one_thread")

ENV = {**os.environ, "OMP_NUM_THREADS": "1"}


def _train(data, out, config, *extra):
    return [sys.executable, "-m", "clfbev", "train", "--data", str(data), "--out", str(out), "--config", str(config),
            "--variant", "camera", "--batch-size", "1", "--threads", "1", "--quiet", "--val-split", "",
            "--max-steps", "4", "--save-every-steps", "1", "--seed", "2", *extra]


@pytest.mark.slow
def test_denser_supervision_trains_logs_and_resumes_bit_identically(tiny_dataset, micro, tmp_path):
    cfg = load_config(micro)
    torch.manual_seed(0)
    save_checkpoint(tmp_path / "teacher.pt", {"model": CLFusionBEV(cfg, "lidar").state_dict(),
                                              "config": cfg.to_dict(), "variant": "lidar", "step": 0, "epoch": 0})
    config = tmp_path / "dense.yaml"
    config.write_text(micro.read_text() + f"cam_heatmap: 1.0\ncam_distill: 1.0\ncam_distill_teacher: "
                      f"{tmp_path / 'teacher.pt'}\ncam_lift: bilinear\ncam_lift_heights: [-1.6, -0.4]\n")
    subprocess.run(_train(tiny_dataset, tmp_path / "a", config), env=ENV, check=True, capture_output=True)

    b = tmp_path / "b"
    proc = subprocess.Popen(_train(tiny_dataset, b, config), env=ENV, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 300
    while time.monotonic() < deadline:
        if (b / "last.pt").exists() and load_checkpoint(b / "last.pt")["step"] >= 1:
            break
        time.sleep(0.02)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert 1 <= load_checkpoint(b / "last.pt")["step"] < 4, "the run was not interrupted"
    subprocess.run(_train(tiny_dataset, b, config, "--resume"), env=ENV, check=True, capture_output=True)

    ca, cb = load_checkpoint(tmp_path / "a" / "last.pt"), load_checkpoint(b / "last.pt")
    assert ca["step"] == cb["step"] == 4
    assert ca["config"]["cam_lift"] == "bilinear" and any(k.startswith("camera_aux.adapter") for k in ca["model"])
    assert ca["model"].keys() == cb["model"].keys()
    for k in ca["model"]:
        assert torch.equal(ca["model"][k], cb["model"][k]), k
    rows = [json.loads(ln) for ln in (tmp_path / "a" / "metrics.jsonl").read_text().splitlines()]
    assert all(r["train/loss_heatmap"] > 0 and r["train/loss_distill"] > 0 for r in rows if "train/loss" in r)
    assert [r["step"] for r in (json.loads(ln) for ln in (b / "metrics.jsonl").read_text().splitlines())] == [1, 2, 3, 4]

    # A resume with another teacher (the config records it) is refused in one line, exit 2.
    (tmp_path / "teacher2.pt").write_bytes((tmp_path / "teacher.pt").read_bytes())
    other = tmp_path / "other.yaml"
    other.write_text(config.read_text().replace("teacher.pt", "teacher2.pt"))
    proc = subprocess.run(_train(tiny_dataset, b, other, "--resume"), env=ENV, capture_output=True, text=True)
    assert proc.returncode == 2 and "cam_distill_teacher" in proc.stderr and len(proc.stderr.strip().splitlines()) == 1
