"""clfbev.feature_cache and `clfbev cache-features`: an entry is the frozen encoder's output on its
image bit for bit, a changed image or encoder is refused, and a killed caching run resumes to
the bytes of an uninterrupted one.

The encoder is a seeded micro encoder saved as an encoder checkpoint (the micro config of
tests/conftest.py), except for the kill test, which caches with the shipped tiny encoder so that
the run lasts long enough to be interrupted.
"""
from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from clfbev.camera_encoder import CameraEncoder
from clfbev.config_file import load_config
from clfbev.data import CAMERAS, NuScenesDetection, collate
from clfbev.errors import ConfigError, DataError
from clfbev.feature_cache import (CachedFeatureDataset, FeatureCache, camera_files, encoder_identity, fill_cache,
                                  image_key)
from clfbev.model import CLFusionBEV
from clfbev.run.image_init import load_image_init, save_encoder
from clfbev.run.train import check_sensor_settings
from clfbev.run.train_config import TrainConfig
from clfbev.sensor_files import IMAGE_MEAN, IMAGE_STD

pytestmark = pytest.mark.usefixtures("one_thread")

VERSION = "v1.0-sim"
ENV = {**os.environ, "OMP_NUM_THREADS": "1"}


def clfbev(*args) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "clfbev", *map(str, args)], capture_output=True, text=True, env=ENV)


def micro_encoder(micro, seed: int) -> tuple[CameraEncoder, object]:
    cfg = load_config(micro)
    torch.manual_seed(seed)
    encoder = CameraEncoder.from_config(cfg)
    encoder.freeze_image_features()
    return encoder.eval(), cfg


@pytest.fixture(scope="module")
def encoder_ckpt(tmp_path_factory, micro) -> Path:
    """An encoder checkpoint of a seeded micro encoder (BatchNorm statistics made non-trivial)."""
    encoder, cfg = micro_encoder(micro, 3)
    g = torch.Generator().manual_seed(5)
    for m in encoder.modules():
        if isinstance(m, torch.nn.BatchNorm2d):
            m.running_mean.copy_(torch.randn(m.running_mean.shape, generator=g) * 0.1)
            m.running_var.copy_(torch.rand(m.running_var.shape, generator=g) + 0.5)
    path = tmp_path_factory.mktemp("enc") / "encoder.pt"
    save_encoder(path, encoder, cfg, ["test"], {}, 0, "test")
    return path


@pytest.fixture(scope="module")
def cache(tiny_dataset, micro, encoder_ckpt, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("cache") / "c"
    proc = clfbev("cache-features", "--data", tiny_dataset, "--config", micro, "--image-init", encoder_ckpt,
                  "--split", "all", "--out", out, "--quiet")
    assert proc.returncode == 0, proc.stderr
    assert "36 images of 6 samples (36 computed" in proc.stdout
    return out


def loaded_encoder(micro, encoder_ckpt) -> CameraEncoder:
    encoder, cfg = micro_encoder(micro, 0)
    load_image_init(encoder, encoder_ckpt, cfg)
    return encoder.eval()


def test_an_entry_is_the_encoders_output_on_its_image_bit_for_bit(tiny_dataset, micro, encoder_ckpt, cache):
    encoder = loaded_encoder(micro, encoder_ckpt)
    cfg = load_config(micro)
    H, W = cfg.image_size
    store = FeatureCache.open(cache)
    ds = NuScenesDetection(tiny_dataset, VERSION, "all", cfg.data_config())
    entries = sorted(cache.glob("*/*.feat"))
    assert len(entries) == 36
    for path in camera_files(ds, 0) + camera_files(ds, 5):
        # The network image, decoded and resized here: the image's aspect kept at width W, the
        # top rows cropped, normalised with the ImageNet statistics.
        rgb = cv2.cvtColor(cv2.imread(str(path)), cv2.COLOR_BGR2RGB)
        h1 = round(rgb.shape[0] * W / rgb.shape[1])
        interp = cv2.INTER_AREA if (h1 < rgb.shape[0] and W < rgb.shape[1]) else cv2.INTER_LINEAR
        image = cv2.resize(rgb, (W, h1), interpolation=interp)[h1 - H:]
        image = ((image.astype(np.float32) / 255.0 - IMAGE_MEAN) / IMAGE_STD).transpose(2, 0, 1)
        with torch.no_grad():
            expected = encoder.fpn_features(torch.from_numpy(np.ascontiguousarray(image))[None, None])[0].numpy()
        key = image_key(path.read_bytes())
        features, img_aug = store.read(key, path)
        assert features.dtype == np.float32 and features.shape == (32, H // 8, W // 8)
        assert np.array_equal(features, expected)                  # float32 storage: exact
        A = np.array([[W / rgb.shape[1], 0, 0], [0, h1 / rgb.shape[0], -(h1 - H)], [0, 0, 1]])
        np.testing.assert_array_equal(img_aug, A)
        # The file is the header and these features, byte for byte.
        assert (cache / key[:2] / f"{key}.feat").read_bytes() == store.entry_bytes(key, expected, A)


def test_the_cached_dataset_is_the_loaders_sample_with_features_for_pixels(tiny_dataset, micro, encoder_ckpt, cache):
    cfg = load_config(micro)
    plain = NuScenesDetection(tiny_dataset, VERSION, "sim-train", cfg.data_config())
    cached = CachedFeatureDataset(tiny_dataset, VERSION, "sim-train", cfg.data_config(), FeatureCache.open(cache))
    a, b = plain[1], cached[1]
    assert b.images.shape == (len(CAMERAS), 3, 0, 0) and b.image_features.shape == (len(CAMERAS), 32, 8, 22)
    for name in ("intrinsics", "T_lidar_from_cam", "img_aug", "points", "gt_boxes", "gt_labels", "T_global_from_lidar"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name
    # The detector reads the cached features in place of running its frozen ResNet and FPN: the
    # same outputs up to the last bits (the features of six images computed together differ
    # from those computed one by one in the last bits).
    torch.manual_seed(0)
    model = CLFusionBEV(cfg, "camera")
    load_image_init(model.camera_encoder, encoder_ckpt, cfg)
    model.camera_encoder.freeze_image_features()
    model.eval()
    with torch.no_grad():
        out_images, out_cache = model(collate([a])), model(collate([b]))
    ref = out_images.head.cls_logits
    assert torch.allclose(out_cache.head.cls_logits, ref, rtol=0, atol=1e-4 * float(ref.abs().max()))
    assert torch.allclose(out_cache.depth, out_images.depth, rtol=0, atol=1e-5)


def test_a_changed_image_or_encoder_is_refused(tiny_dataset, micro, encoder_ckpt, cache, tmp_path):
    cfg = load_config(micro)
    data = tmp_path / "data"
    shutil.copytree(tiny_dataset, data)
    ds = NuScenesDetection(data, VERSION, "sim-train", cfg.data_config())
    image = camera_files(ds, 0)[2]
    bgr = cv2.imread(str(image))
    bgr[10, 10] = 255 - bgr[10, 10]
    cv2.imwrite(str(image), bgr)
    cached = CachedFeatureDataset(data, VERSION, "sim-train", cfg.data_config(), FeatureCache.open(cache))
    cached[1]                                                   # the other samples still read
    with pytest.raises(DataError, match=f"no features of image {image}"):
        cached[0]
    proc = clfbev("train", "--data", data, "--config", micro, "--variant", "camera", "--out", tmp_path / "run",
                  "--image-init", encoder_ckpt, "--image-freeze", "--feature-cache", cache, "--max-steps", "3",
                  "--batch-size", "1", "--val-split", "", "--threads", "1", "--quiet")   # every sample
    errors = [line for line in proc.stderr.splitlines() if line.startswith("clfbev: error")]
    assert proc.returncode == 2 and "Traceback" not in proc.stderr and len(errors) == 1
    assert "no features of image" in errors[0]

    # Another encoder (one weight changed): the cache is of the other, for filling and training.
    other, _ = micro_encoder(micro, 0)
    load_image_init(other, encoder_ckpt, cfg)
    with torch.no_grad():
        weight = next(other.backbone.parameters())
        weight[(0,) * weight.dim()] += 1e-3
    assert encoder_identity(other)["id"] != FeatureCache.open(cache).identity["id"]
    with pytest.raises(DataError, match="another encoder .*weights_sha256"):
        FeatureCache.create(cache, encoder_identity(other))
    other_ckpt = tmp_path / "other.pt"
    save_encoder(other_ckpt, other, cfg, ["test"], {}, 0, "test")
    proc = clfbev("train", "--data", tiny_dataset, "--config", micro, "--variant", "camera", "--out",
                  tmp_path / "run2", "--image-init", other_ckpt, "--image-freeze", "--feature-cache", cache,
                  "--max-steps", "1", "--batch-size", "1", "--val-split", "", "--threads", "1", "--quiet")
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr
    assert "holds the features of another encoder (differs in: weights_sha256)" in proc.stderr


def test_a_stale_or_damaged_entry_is_refused(cache, tmp_path):
    copy = tmp_path / "c"
    shutil.copytree(cache, copy)
    store = FeatureCache.open(copy)
    a, b = sorted(copy.glob("*/*.feat"))[:2]
    key_a, key_b = a.stem, b.stem
    store.read(key_a)
    shutil.copy(b, a)                                           # image a's name, image b's features
    with pytest.raises(DataError, match="features of another image"):
        store.read(key_a)
    b.write_bytes(b.read_bytes()[:-4])                          # cut short
    with pytest.raises(DataError, match="bytes of features"):
        store.read(key_b)
    assert not store.valid(key_a) and not store.valid(key_b)
    (copy / "encoder.json").write_text("{}")
    with pytest.raises(DataError, match="is not a clfbev-feature-cache-v1 manifest"):
        FeatureCache.open(copy)


def test_training_needs_a_frozen_encoder_and_refuses_other_input(tiny_dataset, micro, tmp_path):
    tc = TrainConfig(feature_cache="CACHE", image_freeze=True)
    check_sensor_settings(tc, "camera")
    for tc, variant, needle in ((replace(tc, image_freeze=False), "camera", "needs --image-freeze"),
                                (tc, "lidar", "has no camera"),
                                (replace(tc, modality_dropout=0.2), "concat", "use --modality-dropout-lidar")):
        with pytest.raises(ConfigError, match=needle):
            check_sensor_settings(tc, variant)
    proc = clfbev("cache-features", "--data", tiny_dataset, "--config", micro, "--image-init", "", "--out",
                  tmp_path / "c")
    assert proc.returncode == 2 and "Traceback" not in proc.stderr and "no encoder checkpoint" in proc.stderr


def entries(cache: Path) -> list[Path]:
    """The entries written (not the temporary files of writes under way, whose names start with a dot)."""
    return [p for p in cache.glob("*/*.feat") if not p.name.startswith(".")]


def test_a_killed_caching_run_resumes_to_the_bytes_of_an_uninterrupted_one(tiny_dataset, tmp_path):
    args = ["cache-features", "--data", str(tiny_dataset), "--config", "tiny", "--image-init", "shipped",
            "--split", "all", "--quiet"]
    whole = tmp_path / "whole"
    assert clfbev(*args, "--out", whole).returncode == 0
    files = sorted(p.relative_to(whole) for p in whole.rglob("*") if p.is_file())
    assert len(files) == 37                                     # 36 entries and the manifest

    killed = tmp_path / "killed"
    proc = subprocess.Popen([sys.executable, "-m", "clfbev", *args, "--out", str(killed)], env=ENV,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and not entries(killed):
        time.sleep(0.001)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    done = len(entries(killed))
    assert 1 <= done < 36, f"the run was not interrupted ({done} entries)"
    # What a kill during a write leaves: a temporary file beside the entries.
    stale = next(killed.glob("*/")) / ".0abc.xyz.tmp.feat"
    stale.write_bytes(b"half")

    out = clfbev(*args, "--out", killed)
    assert out.returncode == 0 and f"({36 - done} computed, {done} already there)" in out.stdout, out.stdout
    assert sorted(p.relative_to(killed) for p in killed.rglob("*") if p.is_file()) == files
    for name in files:
        assert (whole / name).read_bytes() == (killed / name).read_bytes(), name
