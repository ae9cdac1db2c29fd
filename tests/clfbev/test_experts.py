"""The sensor experts (clfbev experts): each sample is answered by exactly the expert its
delivered sensors pick, the file round-trips, and `clfbev eval` of the file without a lidar gives
the camera expert's own results, byte for byte."""
from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import replace

import numpy as np
import pytest
import torch

from clfbev.config_file import config_from_dict
from clfbev.data import NuScenesDetection, collate
from clfbev.errors import CheckpointError, ConfigError
from clfbev.experts import CAMERA, FUSED, LIDAR, SensorExperts, route
from clfbev.model import CLFusionBEV
from clfbev.run.checkpoint import save_checkpoint
from clfbev.run.experts_file import EXPERTS_FORMAT, assemble, load_predictor

pytestmark = pytest.mark.usefixtures("one_thread")

VERSION = "v1.0-sim"
# The micro model with a high prior on a coarse grid: untrained, it puts boxes everywhere, so
# every expert answers with many boxes and two experts' answers differ.
MICRO = {"image_size": [64, 176], "cam_width": 8, "fpn_ch": 32, "context_ch": 16, "vfe_ch": 16, "fusion_dim": 32,
         "attn_heads": 2, "bev_channels": [16, 32], "bev_blocks": 1, "bev_up_ch": 16, "prior_prob": 0.9,
         "lidar_bev_stride": 4}


def _model(variant: str, seed: int, **changes) -> CLFusionBEV:
    torch.manual_seed(seed)
    return CLFusionBEV(config_from_dict({**MICRO, **changes}), variant).eval()


def _save(path, model: CLFusionBEV):
    save_checkpoint(path, {"model": model.state_dict(), "config": model.cfg.to_dict(), "variant": model.variant,
                           "step": 0, "epoch": 0, "best_nds": -1.0})
    return path


@pytest.fixture(scope="module")
def models():
    return {FUSED: _model("full", 0), CAMERA: _model("camera", 1), LIDAR: _model("lidar", 2)}


@pytest.fixture(scope="module")
def samples(tiny_dataset, models):
    """Four samples: both sensors, no lidar point, every camera missing, one camera missing."""
    ds = NuScenesDetection(tiny_dataset, VERSION, "all", models[FUSED].cfg.data_config())
    s = [ds[i] for i in range(4)]
    one_missing = np.zeros(6, bool)
    one_missing[2] = True
    return [s[0], replace(s[1], points=s[1].points[:0]), replace(s[2], camera_missing=np.ones(6, bool)),
            replace(s[3], camera_missing=one_missing)]


def test_route_by_what_each_sample_delivered(samples):
    assert route(collate(samples)) == [FUSED, CAMERA, LIDAR, FUSED]
    nothing = replace(samples[2], points=samples[2].points[:0])       # neither sensor: the fused model's
    assert route(collate([nothing, samples[1]])) == [FUSED, CAMERA]


def _same(a, b) -> bool:
    return all((x is None and y is None) or torch.equal(x, y) for x, y in zip(a, b))


def test_each_sample_gets_exactly_its_experts_detections(samples, models):
    # One sample per expert, so that each expert's batch is that sample alone (a batch of two
    # may differ from two of one in the last bits of a convolution).
    experts = SensorExperts(**models).eval()
    got = experts.predict(collate(samples[:3]), score_thr=0.05)
    assert len(got) == 3
    for sample, role, dets in zip(samples, [FUSED, CAMERA, LIDAR], got):
        alone = models[role].predict(collate([sample]), score_thr=0.05)[0]
        assert len(alone.scores) > 0 and _same(dets, alone)
    # The routing decides: the fused model's answer to the lidar-less sample is another.
    assert not _same(got[1], models[FUSED].predict(collate([samples[1]]), score_thr=0.05)[0])
    # Without a camera expert the lidar-less sample falls back to the fused model.
    no_camera = SensorExperts(models[FUSED], lidar=models[LIDAR]).eval()
    assert _same(no_camera.predict(collate([samples[1]]), score_thr=0.05)[0],
                 models[FUSED].predict(collate([samples[1]]), score_thr=0.05)[0])


def test_experts_are_refused_unless_they_fit_together(models):
    with pytest.raises(ConfigError, match="fused expert is of variant 'camera'"):
        SensorExperts(models[CAMERA])
    with pytest.raises(ConfigError, match="camera expert is of variant 'lidar'"):
        SensorExperts(models[FUSED], camera=models[LIDAR])
    with pytest.raises(ConfigError, match="reads other data"):
        SensorExperts(models[FUSED], camera=_model("camera", 1, image_size=[96, 176]))
    with pytest.raises(ConfigError, match="cam_oracle_depth"):
        SensorExperts(models[FUSED], camera=_model("camera", 1, cam_oracle_depth=True))


def _cli(*args):
    return subprocess.run([sys.executable, "-m", "clfbev", *map(str, args)], capture_output=True, text=True)


def test_the_file_evaluates_without_a_lidar_exactly_as_the_camera_expert(tiny_dataset, models, tmp_path):
    paths = {role: _save(tmp_path / f"{role}.pt", m) for role, m in models.items()}
    out = tmp_path / "experts.pt"
    proc = _cli("experts", "--fused", paths[FUSED], "--camera", paths[CAMERA], "--lidar", paths[LIDAR], "--out", out)
    assert proc.returncode == 0, proc.stderr[-2000:]
    loaded, record = load_predictor(out)
    assert record["variant"] == "full+experts" and record["experts"][CAMERA] == str(paths[CAMERA])
    for role, model in models.items():
        assert all(torch.equal(a, b) for a, b in zip(loaded.expert(role).state_dict().values(),
                                                    model.state_dict().values()))

    ev = {}
    # (A sample with both sensors is the fused model's: test_each_sample_gets_exactly_its_experts_detections.)
    for name, ckpt, corrupt in (("experts", out, ["--corrupt", "lidar_missing"]), ("camera", paths[CAMERA], [])):
        proc = _cli("eval", "--data", tiny_dataset, "--split", "sim-train", "--ckpt", ckpt, "--out", tmp_path / name,
                    "--no-plots", *corrupt)
        assert proc.returncode == 0, proc.stderr[-2000:]
        ev[name] = (tmp_path / name / "results.json").read_bytes()
    assert ev["experts"] == ev["camera"] and sum(map(len, json.loads(ev["camera"])["results"].values())) > 0


def test_bad_experts_files_are_one_line(models, tmp_path):
    paths = {role: _save(tmp_path / f"{role}.pt", m) for role, m in models.items()}
    proc = _cli("experts", "--fused", paths[LIDAR], "--out", tmp_path / "x.pt")
    assert proc.returncode == 2 and "fused expert is of variant 'lidar'" in proc.stderr
    assert str(paths[LIDAR]) in proc.stderr and "Traceback" not in proc.stderr and not (tmp_path / "x.pt").exists()

    good = assemble({FUSED: paths[FUSED], CAMERA: paths[CAMERA]}, tmp_path / "good.pt")
    assert good.lidar is None
    data = (tmp_path / "good.pt").read_bytes()
    (tmp_path / "cut.pt").write_bytes(data[: len(data) // 2])
    with pytest.raises(CheckpointError, match="cut.pt is corrupt"):
        load_predictor(tmp_path / "cut.pt")
    raw = torch.load(tmp_path / "good.pt", weights_only=True)
    assert raw["format"] == EXPERTS_FORMAT
    torch.save({**raw, "experts": {"radar": raw["experts"][FUSED]}}, tmp_path / "role.pt")
    with pytest.raises(CheckpointError, match="not a mapping of"):
        load_predictor(tmp_path / "role.pt")
    proc = _cli("eval", "--data", tmp_path, "--ckpt", tmp_path / "role.pt", "--out", tmp_path / "ev")
    assert proc.returncode == 2 and "role.pt" in proc.stderr and "Traceback" not in proc.stderr
