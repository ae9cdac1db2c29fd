"""The camera encoder shipped with clfbev (clfbev/weights/): the `tiny` recipe's camera variants
start from it, it is exactly what its record says, and it never saw an evaluation set."""
from __future__ import annotations

import json

import pytest
import torch

from clfbev.config import VARIANTS, tiny
from clfbev.config_file import load_config
from clfbev.data import CAMERAS
from clfbev.run.image_init import (WEIGHTS_DIR, camera_fields, load_encoder_checkpoint, recorded_camera,
                                  resolve_image_init)
from clfbev.run.train import start_state
from clfbev.run.train_config import SHIPPED, recipe

PRETRAIN_SEED = 1001          # scripts/pretrain_encoder.sh's SEED
OTHER_SEEDS = (0, 1)          # the demo's and the benchmark's data seeds (scripts/demo.sh, scripts/benchmark.sh)


@pytest.fixture(scope="module")
def shipped():
    path = resolve_image_init(SHIPPED, tiny())
    assert path is not None and path.is_file(), f"no encoder ships for tiny's camera in {WEIGHTS_DIR}"
    return path, json.loads(path.with_suffix(".json").read_text())


def test_tinys_camera_variants_start_from_the_shipped_encoder(shipped):
    """Every variant with a camera loads every tensor of the shipped encoder before its first
    step; the lidar variant has no camera to load."""
    path, _ = shipped
    weights = load_encoder_checkpoint(path)["encoder"]
    for variant in VARIANTS:
        tc = recipe("tiny", variant)
        assert tc.image_init == ("" if variant == "lidar" else SHIPPED), variant
    state = start_state(tiny(), "camera", recipe("tiny", "camera"), torch.device("cpu"), None, path)
    mine = state.model.camera_encoder.state_dict()
    assert set(mine) == set(weights)
    assert all(torch.equal(mine[k], weights[k]) for k in weights)


def test_its_record_says_how_and_from_what_it_was_made(shipped):
    """The record beside the weights: tiny's camera, the pretraining command and set, a set of
    its own seed (no log of the demo's or the benchmark's seeds), the images seen."""
    path, record = shipped
    ckpt = load_encoder_checkpoint(path)
    assert record["camera"] == ckpt["camera"] and recorded_camera(record["camera"]) == camera_fields(tiny())
    assert record["pretrain_command"] == ckpt["command"] and record["steps"] == ckpt["step"]
    assert record["pretraining_set"] == ckpt["data"]
    logs = record["pretraining_set"]["logs"]
    assert logs and all(log.startswith(f"simgen-{PRETRAIN_SEED}-") for log in logs)
    assert not any(log.startswith(f"simgen-{s}-") for s in OTHER_SEEDS for log in logs)
    assert f"--seed {PRETRAIN_SEED}" in record["data_command"] and "--dense-labels" in record["data_command"]
    batch = int(ckpt["command"][ckpt["command"].index("--batch-size") + 1]) if "--batch-size" in ckpt["command"] else 2
    assert record["images_seen"] == record["steps"] * batch * len(CAMERAS)
    assert all(v > 0 for v in record["wall_seconds"].values())


def test_a_camera_with_no_shipped_encoder_starts_from_scratch(tmp_path, capsys):
    """A config whose camera differs from every shipped one resolves 'shipped' to nothing: the
    encoder keeps its seeded initialisation, and the run says so."""
    yaml = tmp_path / "wide.yaml"
    yaml.write_text("preset: tiny\ncam_width: 8\n")
    cfg = load_config(str(yaml))
    assert resolve_image_init(SHIPPED, cfg) is None
    tc = recipe("tiny", "camera")
    state = start_state(cfg, "camera", tc, torch.device("cpu"), None, tmp_path / "last.pt")
    torch.manual_seed(tc.seed)
    from clfbev.model import CLFusionBEV
    seeded = CLFusionBEV(cfg, "camera").camera_encoder.state_dict()
    got = state.model.camera_encoder.state_dict()
    assert all(torch.equal(got[k], seeded[k]) for k in seeded)
    assert "from scratch (no encoder ships for this camera" in capsys.readouterr().err
