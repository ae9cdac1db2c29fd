"""Modality dropout (--modality-dropout-lidar / --modality-dropout-camera): a dropped sensor's input
is exactly absent (no points; an all-zero camera BEV), in training only, drawn from the run's
seeded streams, so a killed run (with the feature cache and the BEV augmentation too) resumes
bit for bit.
"""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from dataclasses import replace

import numpy as np
import pytest
import torch

from clfbev.augment import AugmentConfig
from clfbev.camera_encoder import CameraEncoder
from clfbev.config_file import load_config
from clfbev.data import NuScenesDetection, collate
from clfbev.errors import ConfigError
from clfbev.model import CLFusionBEV
from clfbev.run.checkpoint import load_checkpoint
from clfbev.run.epochs import EpochSamples, drop_sensors
from clfbev.run.image_init import save_encoder
from clfbev.run.train import check_sensor_settings, load_training_data
from clfbev.run.train_config import TrainConfig

pytestmark = pytest.mark.usefixtures("one_thread")

VERSION = "v1.0-sim"
ENV = {**os.environ, "OMP_NUM_THREADS": "1"}


@pytest.fixture(scope="module")
def samples(tiny_dataset, micro):
    cfg = load_config(micro)
    ds = NuScenesDetection(tiny_dataset, VERSION, "sim-train", cfg.data_config())
    return cfg, ds, [ds[0], ds[1]]


def test_drop_sensors_removes_exactly_one_sensor_with_its_probability(samples):
    _, _, (s, _) = samples
    no_lidar = drop_sensors(s, np.random.default_rng(0), 1.0, 1.0)
    assert no_lidar.points.shape == (0, 5) and no_lidar.camera_missing is None      # never both
    no_camera = drop_sensors(s, np.random.default_rng(0), 0.0, 1.0)
    assert no_camera.camera_missing.tolist() == [True] * 6 and no_camera.points is s.points
    kept = drop_sensors(s, np.random.default_rng(0), 0.0, 0.0)
    assert kept is s
    for name in ("images", "intrinsics", "T_lidar_from_cam", "img_aug", "gt_boxes", "gt_labels"):
        assert getattr(no_lidar, name) is getattr(s, name) and getattr(no_camera, name) is getattr(s, name)
    # Frequencies over 4000 draws: lidar 0.3, else cameras 0.5 (0.35 of all), within 4 sigma.
    n, lidar, camera = 4000, 0, 0
    for seed in range(n):
        u = np.random.default_rng(seed).random(2)
        out = drop_sensors(s, np.random.default_rng(seed), 0.3, 0.5)
        lidar += len(out.points) == 0
        camera += out.camera_missing is not None
        assert (len(out.points) == 0) == (u[0] < 0.3) and (out.camera_missing is not None) == (u[0] >= 0.3 and u[1] < 0.5)
    for count, p in ((lidar, 0.3), (camera, 0.35)):
        assert abs(count / n - p) < 4 * (p * (1 - p) / n) ** 0.5


def test_the_draws_are_the_samples_own_and_shift_no_other_stream(samples):
    cfg, ds, _ = samples
    plain = EpochSamples(ds, 3, 1, AugmentConfig(), cfg.pc_range)
    dropping = EpochSamples(ds, 3, 1, AugmentConfig(), cfg.pc_range, dropout_lidar=0.5, dropout_camera=0.5)
    again = EpochSamples(ds, 3, 1, AugmentConfig(), cfg.pc_range, dropout_lidar=0.5, dropout_camera=0.5)
    for i in range(len(ds)):
        a, b, c = plain[i], dropping[i], again[i]
        assert np.array_equal(b.points, c.points) and np.array_equal(b.camera_missing, c.camera_missing)   # (seed, epoch, i)
        assert np.array_equal(a.images, b.images) and np.array_equal(a.gt_boxes, b.gt_boxes)
        assert np.array_equal(a.T_lidar_from_cam, b.T_lidar_from_cam)
        assert len(b.points) == 0 or np.array_equal(a.points, b.points)


def fuser_inputs(model: CLFusionBEV, batch):
    """(lidar BEV, camera BEV) as the fuser gets them, the camera encoder's own BEV output and
    the model's outputs."""
    seen = {}
    lift_splat = model.camera_encoder.lift_splat

    def spy(*args, **kwargs):
        out = lift_splat(*args, **kwargs)
        seen["raw"] = out[0]
        return out

    hook = model.fuser.register_forward_pre_hook(lambda m, args: seen.update(fused=args))
    model.camera_encoder.lift_splat = spy
    try:
        out = model(batch)
    finally:
        hook.remove()
        del model.camera_encoder.lift_splat
    return seen["fused"][0], seen["fused"][1], seen["raw"], out


def test_a_dropped_sensor_gives_an_exactly_zero_bev(samples):
    cfg, _, (s0, s1) = samples
    torch.manual_seed(0)
    model = CLFusionBEV(cfg, "concat").train()
    with torch.no_grad():       # the fuser starts as the lidar path exactly; give the camera a say
        for p in model.fuser.parameters():
            p.normal_(0.0, 0.1)
    lidar, camera, _, _ = fuser_inputs(model, collate([s0, s1]))
    assert camera[0].abs().sum() > 0 and lidar[0].abs().sum() > 0

    # Cameras dropped: exactly zero for that sample, the other's as it was, and no gradient of
    # the detector reaches the camera encoder through the dropped one.
    lidar_c, camera_c, raw, out = fuser_inputs(model, collate([replace(s0, camera_missing=np.ones(6, bool)), s1]))
    raw.retain_grad()
    assert torch.count_nonzero(camera_c[0]) == 0 and torch.equal(camera_c[1], camera[1])
    assert torch.equal(lidar_c, lidar)
    out.head.cls_logits.sum().backward()
    assert torch.count_nonzero(raw.grad[0]) == 0 and torch.count_nonzero(raw.grad[1]) > 0

    # Lidar dropped (no points): its lidar BEV is exactly zero; in eval mode (BatchNorm's running
    # statistics) the other sample's is unchanged.
    lidar_l, camera_l, _, _ = fuser_inputs(model, collate([replace(s0, points=s0.points[:0]), s1]))
    assert torch.count_nonzero(lidar_l[0]) == 0 and torch.equal(camera_l, camera)
    model.eval()
    with torch.no_grad():
        ref, _, _, _ = fuser_inputs(model, collate([s0, s1]))
        lidar_e, _, _, _ = fuser_inputs(model, collate([replace(s0, points=s0.points[:0]), s1]))
    assert torch.count_nonzero(lidar_e[0]) == 0 and torch.equal(lidar_e[1], ref[1])


def test_a_missing_camera_gives_nothing_and_all_missing_is_the_dropped_bev(samples):
    """A camera marked missing (``camera_crash`` at evaluation) adds nothing to the camera BEV:
    whatever its images hold, the BEV is that of the other five; with all six missing the BEV is
    exactly the dropped one (zero), so a crash at evaluation is what modality dropout trained."""
    cfg, _, (s0, _) = samples
    torch.manual_seed(0)
    model = CLFusionBEV(cfg, "concat").eval()
    one = np.zeros(6, bool)
    one[2] = True
    noise = s0.images.copy()
    noise[2] = np.random.default_rng(0).normal(0.0, 1.0, noise[2].shape)
    with torch.no_grad():
        _, full, raw_full, _ = fuser_inputs(model, collate([s0]))
        _, a, raw_a, _ = fuser_inputs(model, collate([replace(s0, camera_missing=one)]))
        _, b, raw_b, _ = fuser_inputs(model, collate([replace(s0, images=noise, camera_missing=one)]))
        _, none, _, _ = fuser_inputs(model, collate([replace(s0, camera_missing=np.ones(6, bool))]))
    assert torch.equal(raw_a, raw_b) and not torch.allclose(raw_a, raw_full)
    assert torch.equal(a, b) and torch.count_nonzero(none) == 0


def test_evaluation_is_untouched(tiny_dataset, micro):
    cfg = load_config(micro)
    tc = TrainConfig(modality_dropout_lidar=1.0, modality_dropout_camera=1.0, augment=False, gt_paste=0,
                     max_steps=1)
    data = load_training_data(tiny_dataset, cfg, "concat", tc, 0, 1)
    train = EpochSamples(data.train_set, tc.seed, 0, None, cfg.pc_range, dropout_lidar=1.0, dropout_camera=1.0)
    assert all(len(train[i].points) == 0 for i in range(len(train)))
    plain = NuScenesDetection(tiny_dataset, VERSION, "sim-val", cfg.data_config())
    for i in range(len(data.val_set)):
        v = data.val_set[i]
        assert v.camera_missing is None and np.array_equal(v.points, plain[i].points) and len(v.points) > 0
    assert collate([data.val_set[0]]).camera_missing is None
    # The lidar-only and camera-only variants have no other sensor to stand on.
    for variant in ("lidar", "camera"):
        with pytest.raises(ConfigError, match="need a variant with both sensors"):
            check_sensor_settings(replace(tc, modality_dropout_lidar=0.0), variant)


@pytest.mark.slow      # as test_train's kill test, with the cache, the BEV augmentation and dropout on
def test_a_killed_run_with_dropout_cache_and_bev_augmentation_resumes_bit_identically(tiny_dataset, micro,
                                                                                      tmp_path):
    cfg = load_config(micro)
    torch.manual_seed(3)
    encoder = CameraEncoder.from_config(cfg)
    ckpt = tmp_path / "encoder.pt"
    save_encoder(ckpt, encoder, cfg, ["test"], {}, 0, "test")
    cache = tmp_path / "cache"
    run = [sys.executable, "-m", "clfbev"]
    subprocess.run([*run, "cache-features", "--data", tiny_dataset, "--config", micro, "--image-init", ckpt,
                    "--out", cache, "--quiet"], env=ENV, check=True, capture_output=True)
    args = ["train", "--data", str(tiny_dataset), "--config", str(micro), "--variant", "concat", "--batch-size", "1",
            "--threads", "1", "--quiet", "--max-steps", "6", "--save-every-steps", "1", "--val-split", "",
            "--seed", "1", "--image-init", str(ckpt), "--image-freeze", "--feature-cache", str(cache),
            "--modality-dropout-lidar", "0.3", "--modality-dropout-camera", "0.5", "--precise-bn-batches", "2",
            "--gt-paste", "0"]
    a, b = tmp_path / "a", tmp_path / "b"
    subprocess.run([*run, *args, "--out", str(a)], env=ENV, check=True, capture_output=True)
    proc = subprocess.Popen([*run, *args, "--out", str(b)], env=ENV, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 300
    while time.monotonic() < deadline:
        if (b / "last.pt").exists() and load_checkpoint(b / "last.pt")["step"] >= 2:
            break
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert 2 <= load_checkpoint(b / "last.pt")["step"] < 6, "the run was not interrupted"
    subprocess.run([*run, *args, "--out", str(b), "--resume"], env=ENV, check=True, capture_output=True)
    ca, cb = load_checkpoint(a / "last.pt"), load_checkpoint(b / "last.pt")
    assert ca["step"] == cb["step"] == 6 and ca["train"]["feature_cache"] == str(cache)
    for k in ca["model"]:
        assert torch.equal(ca["model"][k], cb["model"][k]), k
    for sa, sb in zip(ca["optimizer"]["state"].values(), cb["optimizer"]["state"].values()):
        for k in sa:
            assert torch.equal(sa[k], sb[k]), k
    steps = [json.loads(line)["step"] for line in (b / "metrics.jsonl").read_text().splitlines()]
    assert steps == [1, 2, 3, 4, 5, 6]
