"""clfbev pretrain (image-view pretraining on dense labels) and clfbev train --image-init.

A dense-labelled set of 2 scenes x 2 samples is made once for the module; the training runs use
a micro config (the tiny preset with small images and channels), as tests/clfbev/test_train.py.
"""
from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from clfbev.config_file import load_config
from clfbev.errors import CheckpointError
from clfbev.geometry import CameraGeometry
from clfbev.model import CLFusionBEV
from clfbev.run.image_init import load_image_init
from clfbev.run.train import start_state
from clfbev.run.train_config import TrainConfig
from clfbev.supervision.dense import cell_depth_and_class, centre_targets

pytestmark = pytest.mark.usefixtures("one_thread")

ENV = {**os.environ, "OMP_NUM_THREADS": "1", "PYOPENGL_PLATFORM": os.environ.get("PYOPENGL_PLATFORM", "egl")}


@pytest.fixture(scope="module")
def dense_data(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("dense") / "data"
    proc = subprocess.run([sys.executable, "-m", "simgen.cli", "make", "--out", str(out), "--preset", "tiny",
                           "--scenes", "2", "--samples-per-scene", "2", "--dense-labels", "--resolution", "352x198",
                           "--seed", "11", "--workers", "1", "--quiet"], capture_output=True, text=True, env=ENV)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return out


def clfbev(*args, check=True) -> subprocess.CompletedProcess:
    proc = subprocess.run([sys.executable, "-m", "clfbev", *map(str, args)], capture_output=True, text=True, env=ENV)
    if check and proc.returncode != 0:
        raise AssertionError(f"clfbev {' '.join(map(str, args))} failed ({proc.returncode}):\n{proc.stderr[-3000:]}")
    return proc


def pretrain_args(data, out, micro, *extra):
    return ["pretrain", "--data", data, "--out", out, "--config", micro, "--batch-size", "1", "--threads", "1",
            "--quiet", *extra]


def _assert_bad_input(proc, *needles):
    assert proc.returncode == 2, (proc.returncode, proc.stderr)
    line = proc.stderr.strip()
    assert "Traceback" not in line and line.startswith("clfbev: error:") and len(line.splitlines()) == 1, line
    for n in needles:
        assert n in line, line


@pytest.fixture(scope="module")
def encoder_ckpt(dense_data, micro, tmp_path_factory) -> Path:
    run = tmp_path_factory.mktemp("pre") / "run"
    clfbev(*pretrain_args(dense_data, run, micro, "--max-steps", "2"))
    return run / "encoder.pt"


# ---------------------------------------------------------------- targets

def test_cell_targets_are_the_nearest_pixel_of_the_cell():
    depth = torch.zeros(1, 1, 16, 8)                  # stride 8: two cells, one above the other
    seg = torch.zeros(1, 1, 16, 8, dtype=torch.uint8)
    depth[0, 0, 2, 3], seg[0, 0, 2, 3] = 12.7, 17      # nearest surface of cell 0
    depth[0, 0, 5, 5], seg[0, 0, 5, 5] = 30.0, 24      # behind it
    bins, classes = cell_depth_and_class(depth, seg, 8, (1.0, 52.0, 1.0))
    assert bins[0, 0, :, 0].tolist() == [11, -1]       # floor((12.7 - 1) / 1); the all-sky cell has none
    assert classes[0, 0, :, 0].tolist() == [17, 0]


def test_a_box_centre_projects_to_its_cell():
    # Camera looking along lidar x (camera z = lidar x, camera x = -lidar y, camera y = -lidar z).
    T_lidar_from_cam = torch.tensor([[0.0, 0, 1, 0], [-1, 0, 0, 0], [0, -1, 0, 0], [0, 0, 0, 1]])
    K = torch.tensor([[100.0, 0, 88], [0, 100, 32], [0, 0, 1]])
    cams = CameraGeometry(K[None, None], T_lidar_from_cam[None, None], torch.eye(3)[None, None], (64, 176), 8,
                          (1.0, 52.0, 1.0))
    box = torch.tensor([[20.0, -4.0, 0.8, 4.0, 2.0, 1.5, 0.0]])     # u = 88 + 100 * 4 / 20 = 108, v = 32 - 4 = 28
    heatmap, centres, codes = centre_targets([box], [torch.tensor([3])], cams, 10)
    assert centres.tolist() == [[0, 0, 3, 13]]                       # v 28 -> row 3, u 108 -> column 13
    assert heatmap[0, 0, 3, 3, 13] == 1.0 and heatmap[0, 0, 3].sum() > 1.0 and heatmap[0, 0, :3].sum() == 0
    assert codes[0, :2].tolist() == pytest.approx([108 / 8 - 13, 28 / 8 - 3])
    assert codes[0, 2].item() == pytest.approx(np.log(20.0))
    assert codes[0, 6:].tolist() == pytest.approx([0.0, 1.0], abs=1e-6)   # heading along lidar x = camera z


# ---------------------------------------------------------------- the settings

# The settings record of a pretraining checkpoint written before the loop's settings were shared.
EARLIER_TRAIN_RECORD = {"split": "sim-train", "version": "v1.0-sim", "seed": 0, "lr": 0.002, "weight_decay": 0.01,
                        "warmup_frac": 0.05, "min_lr_ratio": 0.01, "grad_clip": 10.0, "batch_size": 2, "epochs": 10,
                        "max_steps": 0, "workers": 0, "ckpt_minutes": 10.0, "save_every_steps": 0}


def test_the_settings_are_the_loops_with_pretrainings_defaults_and_earlier_checkpoints_resume(micro, tmp_path):
    """PretrainConfig is the loop's OptimConfig (each shared option the detector's, with its own
    defaults and no recipe) plus its split; its flat record is the one earlier checkpoints hold,
    which resume, and one that differs in a setting (not in bookkeeping) is refused, naming it."""
    import argparse
    from dataclasses import asdict, fields, replace

    from clfbev.run.pretrain import PRETRAIN_FORMAT, PretrainConfig, _resume_checkpoint
    from clfbev.run.train_config import OptimConfig, add_setting_options

    assert issubclass(PretrainConfig, OptimConfig) and issubclass(TrainConfig, OptimConfig)
    shared = {f.name: f for f in fields(TrainConfig)}
    for f in fields(OptimConfig):
        mine = next(g for g in fields(PretrainConfig) if g.name == f.name)
        same = ("flag", "lo", "hi", "lo_open", "hi_open", "bookkeeping", "group", "metavar")
        assert [mine.metadata[k] for k in same] == [shared[f.name].metadata[k] for k in same], f.name
    # The earlier record, and the option added since at its default (the start those runs had).
    assert asdict(PretrainConfig()) == {**EARLIER_TRAIN_RECORD, "image_init": ""}
    p = argparse.ArgumentParser()
    add_setting_options(p, PretrainConfig)            # as `clfbev pretrain` makes its options
    options = {a.dest: a for a in p._actions}
    assert "[default 0.002, > 0]" in options["lr"].help and "[default 10," in options["epochs"].help
    assert not any("recipe" in options[f.name].help for f in fields(PretrainConfig))

    cfg = load_config(str(micro))
    last = tmp_path / "last.pt"
    torch.save({"format": PRETRAIN_FORMAT, "config": cfg.to_dict(), "train": EARLIER_TRAIN_RECORD}, last)
    assert _resume_checkpoint(last, cfg, replace(PretrainConfig(), workers=2, ckpt_minutes=1.0), True)["train"] \
        == EARLIER_TRAIN_RECORD
    for name, value in (("lr", 1e-3), ("split", "sim-val"), ("batch_size", 1), ("image_init", "torchvision")):
        with pytest.raises(CheckpointError, match=rf"differs in: {name}\)"):
            _resume_checkpoint(last, cfg, replace(PretrainConfig(), **{name: value}), True)


# ---------------------------------------------------------------- the run

def test_pretraining_loss_falls(dense_data, micro, tmp_path):
    run = tmp_path / "run"
    clfbev(*pretrain_args(dense_data, run, micro, "--max-steps", "30"))
    losses = [json.loads(ln)["pretrain/loss"] for ln in (run / "metrics.jsonl").read_text().splitlines()]
    assert len(losses) == 30
    assert np.mean(losses[-3:]) < 0.7 * np.mean(losses[:3]), losses
    ckpt = torch.load(run / "encoder.pt", weights_only=True)
    assert ckpt["data"]["split"] == "sim-train" and ckpt["data"]["logs"] == ["simgen-11-0000"]
    assert ckpt["command"][1:3] == ["pretrain", "--data"]


def test_sigkill_then_resume_gives_identical_weights(dense_data, micro, tmp_path):
    common = ["--max-steps", "6", "--save-every-steps", "1", "--seed", "1"]
    clfbev(*pretrain_args(dense_data, tmp_path / "a", micro, *common))
    b = tmp_path / "b"
    proc = subprocess.Popen([sys.executable, "-m", "clfbev", *map(str, pretrain_args(dense_data, b, micro, *common))],
                            env=ENV, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 300
    while time.monotonic() < deadline:
        if (b / "last.pt").exists() and torch.load(b / "last.pt", weights_only=True)["step"] >= 2:
            break
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    killed_at = torch.load(b / "last.pt", weights_only=True)["step"]
    assert 2 <= killed_at < 6, f"the run was not interrupted (checkpoint at step {killed_at})"
    assert not (b / "encoder.pt").exists()
    clfbev(*pretrain_args(dense_data, b, micro, *common, "--resume"))
    ca, cb = (torch.load(r / "last.pt", weights_only=True) for r in (tmp_path / "a", b))
    assert ca["step"] == cb["step"] == 6
    for k in ca["model"]:
        assert torch.equal(ca["model"][k], cb["model"][k]), k
    for sa, sb in zip(ca["optimizer"]["state"].values(), cb["optimizer"]["state"].values()):
        assert all(torch.equal(sa[k], sb[k]) for k in sa)
    ea, eb = (torch.load(r / "encoder.pt", weights_only=True)["encoder"] for r in (tmp_path / "a", b))
    assert all(torch.equal(ea[k], eb[k]) for k in ea)
    steps = [json.loads(ln)["step"] for ln in (b / "metrics.jsonl").read_text().splitlines()]
    assert steps == [1, 2, 3, 4, 5, 6]


# ---------------------------------------------------------------- --image-init

def test_image_init_loads_exactly_the_encoder_tensors(encoder_ckpt, micro, tmp_path):
    cfg = load_config(str(micro))
    saved = torch.load(encoder_ckpt, weights_only=True)["encoder"]
    tc = TrainConfig(seed=5, image_init=str(encoder_ckpt))
    model = start_state(cfg, "full", tc, torch.device("cpu"), None, tmp_path / "last.pt").model
    scratch = start_state(cfg, "full", TrainConfig(seed=5), torch.device("cpu"), None, tmp_path / "last.pt").model
    enc = model.camera_encoder.state_dict()
    assert enc.keys() == saved.keys()
    assert all(torch.equal(enc[k], saved[k]) for k in saved)
    # Everything else is the seeded initialisation, untouched.
    rest, rest0 = model.state_dict(), scratch.state_dict()
    others = [k for k in rest if not k.startswith("camera_encoder.")]
    assert others and all(torch.equal(rest[k], rest0[k]) for k in others)
    assert not all(torch.equal(enc[k], scratch.camera_encoder.state_dict()[k]) for k in saved)

    # A tensor changed in the file is changed in the model.
    ckpt = torch.load(encoder_ckpt, weights_only=True)
    name = "depth_net.weight"
    ckpt["encoder"][name] = ckpt["encoder"][name] + 0.5
    edited = tmp_path / "edited.pt"
    torch.save(ckpt, edited)
    again = CLFusionBEV(cfg, "camera")
    load_image_init(again.camera_encoder, edited, cfg)
    assert torch.equal(again.camera_encoder.state_dict()[name], ckpt["encoder"][name])
    assert not torch.equal(again.camera_encoder.state_dict()[name], saved[name])


def test_image_freeze_keeps_the_encoders_image_features(dense_data, encoder_ckpt, micro, tmp_path):
    """``image_freeze``: training steps and precise BatchNorm leave every tensor of the ResNet and
    the FPN (weights and BatchNorm statistics) as the encoder checkpoint gave them, while the
    depth net and the rest of the model train."""
    from clfbev.data import NuScenesDetection, collate
    from clfbev.run.epochs import precise_batchnorm
    from clfbev.supervision.targets import batch_loss

    cfg = load_config(str(micro))
    tc = TrainConfig(seed=5, image_init=str(encoder_ckpt), image_freeze=True, batch_size=1, precise_bn_batches=2)
    model = start_state(cfg, "camera", tc, torch.device("cpu"), None, tmp_path / "last.pt").model.train()
    enc = model.camera_encoder
    assert not enc.backbone.training and not enc.neck.training and enc.depth_net.training
    before = {k: v.clone() for k, v in model.state_dict().items()}
    ds = NuScenesDetection(dense_data, "v1.0-sim", "sim-train", cfg.data_config())
    opt = torch.optim.AdamW(model.parameters(), lr=1e-2)
    for i in range(2):
        loss = batch_loss(model, collate([ds[i]]))["loss"]
        opt.zero_grad()
        loss.backward()
        opt.step()
    precise_batchnorm(model, ds, tc, None)
    after = model.state_dict()
    image = [k for k in before if k.startswith(("camera_encoder.backbone.", "camera_encoder.neck."))]
    assert image and all(torch.equal(after[k], before[k]) for k in image)
    assert any("running_mean" in k for k in image)
    assert not torch.equal(after["camera_encoder.depth_net.weight"], before["camera_encoder.depth_net.weight"])
    trained = [k for k in before if k.startswith("head.") and before[k].is_floating_point()]
    assert any(not torch.equal(after[k], before[k]) for k in trained)


def test_image_init_refuses_another_architecture(encoder_ckpt, micro, tmp_path):
    cfg = load_config(str(micro))
    ckpt = torch.load(encoder_ckpt, weights_only=True)
    ckpt["encoder"]["depth_net.weight"] = ckpt["encoder"]["depth_net.weight"][:-1]
    reshaped = tmp_path / "reshaped.pt"
    torch.save(ckpt, reshaped)
    with pytest.raises(CheckpointError, match="depth_net.weight"):
        load_image_init(CLFusionBEV(cfg, "camera").camera_encoder, reshaped, cfg)
    del ckpt["encoder"]["depth_net.bias"]
    torch.save(ckpt, reshaped)
    with pytest.raises(CheckpointError, match="another architecture"):
        load_image_init(CLFusionBEV(cfg, "camera").camera_encoder, reshaped, cfg)
    # The pretraining run's own last.pt (encoder and heads) is not an encoder checkpoint.
    with pytest.raises(CheckpointError, match="not an encoder checkpoint"):
        load_image_init(CLFusionBEV(cfg, "camera").camera_encoder, encoder_ckpt.parent / "last.pt", cfg)


def test_bad_input_exits_2(dense_data, encoder_ckpt, micro, tmp_path):
    train = ["train", "--data", dense_data, "--config", micro, "--max-steps", "1", "--val-split", "", "--threads", "1",
             "--quiet", "--variant", "camera"]
    junk = tmp_path / "junk.pt"
    junk.write_bytes(b"not a checkpoint at all")
    _assert_bad_input(clfbev(*train, "--out", tmp_path / "r1", "--image-init", junk, check=False), "junk.pt")
    wider = tmp_path / "wider.yaml"
    wider.write_text(micro.read_text().replace("cam_width: 8", "cam_width: 16"))
    _assert_bad_input(clfbev(*train[:4], wider, *train[5:], "--out", tmp_path / "r2", "--image-init", encoder_ckpt,
                             check=False), "encoder.pt", "cam_width")
    _assert_bad_input(clfbev(*train[:-2], "--variant", "lidar", "--out", tmp_path / "r3", "--image-init",
                             encoder_ckpt, check=False), "lidar")
    _assert_bad_input(clfbev(*train[:-2], "--variant", "lidar", "--out", tmp_path / "r3b", "--image-freeze",
                             check=False), "--image-freeze", "lidar")
    _assert_bad_input(clfbev(*train, "--out", tmp_path / "r3c", "--image-freeze", "--image-init", "torchvision",
                             check=False), "--image-freeze", "torchvision", "seeded FPN")
    # A dataroot without dense labels: the missing file is named.
    bare = tmp_path / "bare"
    shutil.copytree(dense_data, bare, ignore=shutil.ignore_patterns("*_seg.png"))
    _assert_bad_input(clfbev(*pretrain_args(bare, tmp_path / "p1", micro, "--max-steps", "1"), check=False),
                      "_seg.png", "--dense-labels")
