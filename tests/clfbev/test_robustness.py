"""Load-time corruptions do exactly what they say; the robustness suite writes its report."""
from __future__ import annotations

import json
import math
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import TINY_ARGS, run_simgen

from clfbev.config import tiny
from clfbev.config_file import config_from_dict
from clfbev.corruptions import Corruption, parse
from clfbev.data import NuScenesDetection
from clfbev.model import CLFusionBEV
from clfbev.run.checkpoint import save_checkpoint
from clfbev.run.robustness import conditions_of

pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def clean(tiny_dataset):
    ds = NuScenesDetection(tiny_dataset, "v1.0-sim", "sim-val", tiny().data_config())
    return tiny_dataset, ds


def _corrupted(root, *corruptions):
    return NuScenesDetection(root, "v1.0-sim", "sim-val", tiny().data_config(), corruptions)


def _rings(ds, i):
    sample = ds.nusc.get("sample", ds.sample_tokens[i])
    sd = ds.nusc.get("sample_data", sample["data"]["LIDAR_TOP"])
    T = np.linalg.inv(ds._T_global_from_sensor(sd))
    return ds._points(sd, T)[1]


def test_beam_missing_leaves_exactly_the_other_rings(clean):
    root, ds = clean
    c = Corruption("beam_missing", 16)
    bad = _corrupted(root, c)
    for i in range(len(ds)):
        rings = _rings(ds, i)
        dropped = c.rng(ds.sample_tokens[i]).choice(32, size=16, replace=False)
        keep = ~np.isin(rings.astype(int), dropped)
        np.testing.assert_array_equal(np.asarray(bad[i].points), np.asarray(ds[i].points)[keep])
        assert len(set(rings[keep].astype(int))) == len(set(rings.astype(int)) - set(dropped.tolist()))
        assert len(set(rings[keep].astype(int))) <= 16


def test_fov_density_and_lidar_missing(clean):
    root, ds = clean
    s, s_fov = ds[0], _corrupted(root, Corruption("fov", 120))[0]
    # The ego's forward axis in LIDAR_TOP is close to +y.
    fwd = np.array([0.0, 1.0])
    az = lambda p: np.degrees(np.abs(np.angle(np.exp(1j * (np.arctan2(p[:, 1], p[:, 0]) - np.arctan2(fwd[1], fwd[0]))))))
    assert len(s_fov.points) > 0 and az(np.asarray(s_fov.points)).max() <= 60.5
    inside = az(np.asarray(s.points)) <= 59.5
    assert len(s_fov.points) >= inside.sum()          # nothing inside the sector is lost
    assert len(_corrupted(root, parse("lidar_missing"))[0].points) == 0
    n, k = len(s.points), len(_corrupted(root, Corruption("density", 0.5))[0].points)
    assert abs(k - n / 2) < 5 * math.sqrt(n / 4)       # binomial(n, 1/2), 5 sigma


def test_camera_crash_zeroes_and_marks_exactly_k_cameras(clean):
    root, ds = clean
    s = ds[1]
    images, points = np.asarray(s.images), np.asarray(s.points)
    assert s.camera_missing is None
    for k in (1, 3, 6):
        bad = _corrupted(root, Corruption("camera_crash", k))[1]
        bad_images = np.asarray(bad.images)
        zero = (bad_images.reshape(len(bad_images), -1) == 0).all(1)
        assert int(zero.sum()) == k and np.array_equal(bad.camera_missing, zero)
        np.testing.assert_array_equal(bad_images[~zero], images[~zero])
        np.testing.assert_array_equal(np.asarray(bad.points), points)
    again = _corrupted(root, Corruption("camera_crash", 3))[1]
    np.testing.assert_array_equal(np.asarray(again.images),
                                  np.asarray(_corrupted(root, Corruption("camera_crash", 3))[1].images))


def test_extrinsic_noise_moves_only_the_extrinsics(clean):
    root, ds = clean
    s, bad = ds[0], _corrupted(root, Corruption("extrinsic_noise", 2))[0]
    np.testing.assert_array_equal(np.asarray(bad.images), np.asarray(s.images))
    R, R_bad = np.asarray(s.T_lidar_from_cam)[:, :3, :3], np.asarray(bad.T_lidar_from_cam)[:, :3, :3]
    dR = np.einsum("nji,njk->nik", R, R_bad)
    angle = np.degrees(np.arccos(np.clip((np.trace(dR, axis1=1, axis2=2) - 1) / 2, -1, 1)))
    assert (angle > 0.05).all() and (angle < 15).all()


def test_parse_rejects_bad_corruptions():
    for text in ("beam_missing:40", "fog:2", "density:1.5", "camera_crash:2.5", "beam_missing"):
        with pytest.raises(ValueError, match="--corrupt"):
            parse(text)


def _ckpt(path, cfg, variant, seed):
    torch.manual_seed(seed)
    model = CLFusionBEV(cfg, variant)
    save_checkpoint(path, {"model": model.state_dict(), "config": cfg.to_dict(), "variant": variant,
                           "step": 0, "epoch": 0, "best_nds": -1.0})
    return path


def test_robustness_report_on_paired_sets(tiny_dataset, tmp_path):
    fog = tmp_path / "fog"
    run_simgen("make", "--out", fog, "--workers", "1", *TINY_ARGS, "--fog", "3")
    cfg = config_from_dict({"image_size": [64, 176], "cam_width": 8, "fpn_ch": 32, "context_ch": 16, "vfe_ch": 16,
                            "fusion_dim": 32, "attn_heads": 2, "bev_channels": [16, 32], "bev_blocks": 1,
                            "bev_up_ch": 16, "prior_prob": 0.9, "lidar_bev_stride": 4})
    # Untrained models with a high prior put boxes everywhere; on a coarse (1.6 m) grid, where the
    # 500 boxes kept per sample cover an eighth of the cells, these seeds give a clean NDS > 0
    # (some boxes land near the GT), so that RR is defined.
    a = _ckpt(tmp_path / "full.pt", cfg, "full", 0)
    b = _ckpt(tmp_path / "concat.pt", cfg, "concat", 4)
    out = tmp_path / "rob"
    cmd = [sys.executable, "-m", "clfbev", "robustness", "--ckpt", f"full={a}", "--ckpt", f"concat={b}",
           "--set", f"clean={tiny_dataset}", "--set", f"fog3={fog}", "--corrupt", "camera_crash:6", "--out", str(out)]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr[-3000:]
    rec = json.loads((out / "robustness.json").read_text())
    assert rec["conditions"] == ["clean", "fog3", "camera_crash:6"]
    assert rec["family"] == {"clean": [None, 0.0], "fog3": ["fog", 3.0], "camera_crash:6": ["camera_crash", 6.0]}
    # The oracle sees everything on the clean set; fog hides some objects from the lidar.
    assert rec["oracle"]["clean"]["NDS"] == pytest.approx(1.0)
    assert rec["oracle"]["fog3"]["counts"]["lidar"] < rec["oracle"]["clean"]["counts"]["lidar"]
    for m in rec["models"].values():
        assert m["metrics"]["clean"]["NDS"] > 0
        assert m["RR"]["clean"] == pytest.approx(1.0)
        assert m["share"]["clean"] == pytest.approx(m["metrics"]["clean"]["NDS"])
        assert all(math.isfinite(m["metrics"][c]["NDS"]) for c in rec["conditions"])
    assert rec["baseline"] == "concat"
    assert rec["models"]["concat"]["CE"]["fog3"] == pytest.approx(1.0)
    md = (out / "robustness.md").read_text()
    assert "| full | full |" in md and "mRR" in md
    assert (out / "robustness.png").stat().st_size > 10_000

    # A rerun reuses every cell it has (nothing is evaluated again) and writes the same record.
    cells = sorted(out.glob("*/*/metrics_summary.json"))
    assert len(cells) == 3 * 3
    stamps = [c.stat().st_mtime_ns for c in cells]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert [c.stat().st_mtime_ns for c in cells] == stamps
    assert json.loads((out / "robustness.json").read_text()) == rec

    # A set that is not paired with the clean one is refused.
    other = tmp_path / "other"
    run_simgen("make", "--out", other, "--workers", "1", "--preset", "tiny", "--scenes", "2",
               "--samples-per-scene", "3", "--seed", "8", "--quiet")
    cmd[cmd.index(f"fog3={fog}")] = f"other={other}"
    proc = subprocess.run(cmd, capture_output=True, text=True)
    assert proc.returncode == 2 and "not paired" in proc.stderr and "Traceback" not in proc.stderr


def test_pairing_allows_only_what_occluders_change(tmp_path):
    """Occluded sets may differ in visibility and point counts; any other label change is refused."""
    from clfbev.errors import DataError
    from clfbev.run.robustness import check_paired
    anns = [{"token": f"a{i}", "instance_token": f"i{i}", "translation": [float(i), 0.0, 1.0], "size": [2.0, 4.0, 1.5],
             "rotation": [1.0, 0.0, 0.0, 0.0], "visibility_token": "4", "num_lidar_pts": 10 + i, "num_radar_pts": 0}
            for i in range(3)]

    def make(name, records):
        root = tmp_path / name
        (root / "v").mkdir(parents=True)
        for table in ("instance", "sample", "ego_pose"):
            (root / "v" / f"{table}.json").write_text("[]")
        (root / "v" / "sample_annotation.json").write_text(json.dumps(records, indent=0))
        return root

    clean = make("clean", anns)
    occluded = [dict(a) for a in anns]
    occluded[1].update(visibility_token="1", num_lidar_pts=0)
    check_paired(clean, make("occ", occluded), "v", "occ")          # accepted
    moved = [dict(a) for a in anns]
    moved[2]["translation"] = [2.0, 0.5, 1.0]
    with pytest.raises(DataError, match=r"not paired.*record a2: translation"):
        check_paired(clean, make("moved", moved), "v", "moved")
    with pytest.raises(DataError, match="3 against 2 records"):
        check_paired(clean, make("fewer", anns[:2]), "v", "fewer")


def test_plot_has_a_panel_per_family_and_one_of_bars(tmp_path):
    """Fog sets only: the fog panel alone (no empty bar chart beside it); another condition of no
    family adds the bar chart; a second family adds its own panel."""
    import cv2

    from clfbev.run.robustness import plot

    conds = ("clean", "fog3", "occlusion", "beam_missing:16")
    models = {name: {"variant": "lidar", "metrics": {c: {"NDS": 0.3 - 0.01 * k} for k, c in enumerate(conds)}}
              for name in ("a", "b")}
    oracle = {c: {"NDS": 1.0 - 0.1 * k} for k, c in enumerate(conds)}
    family = {"clean": [None, 0.0], "fog3": ["fog", 3.0], "occlusion": [None, 0.0],
              "beam_missing:16": ["beam_missing", 16.0]}
    widths = []
    for k, shown in enumerate((["clean", "fog3"], ["clean", "fog3", "occlusion"], list(conds))):
        rec = {"clean": "clean", "family": family, "conditions": shown, "models": models, "oracle": oracle}
        plot(rec, tmp_path / f"{k}.png")
        widths.append(cv2.imread(str(tmp_path / f"{k}.png")).shape[1])
    assert widths == [495, 990, 1485]      # 1, 2 and 3 panels of 4.5 inches at 110 dpi


def test_a_set_is_a_point_of_a_curve_only_when_it_changes_one_thing(tiny_dataset, tmp_path):
    """The clean set is severity 0; a set with fog, rain or snowfall alone is a point of that
    curve at its severity or rate; a set with anything else (occluders, night, a combination)
    is a bar of its own, not a second point at severity 0."""
    sets = [("clean", tiny_dataset)]
    for name, settings, weather in [("occlusion", {"fog": 0, "occlusion": "heavy"}, {}), ("fog2", {"fog": 2}, {}),
                                    ("rain25", {"fog": 0}, {"rain": 25.0}), ("snow1", {"fog": 0}, {"snow": 1.0}),
                                    ("night", {"fog": 0}, {"night": True}),
                                    ("fog1_rain10", {"fog": 1}, {"rain": 10.0})]:
        root = tmp_path / name
        shutil.copytree(tiny_dataset / "v1.0-sim", root / "v1.0-sim", ignore=shutil.ignore_patterns("degradation.json"))
        (root / "v1.0-sim" / "degradation.json").write_text(json.dumps({"settings": settings, "weather": weather}))
        sets.append((name, root))
    corruptions = [parse("beam_missing:16"), parse("lidar_missing"), parse("misalign:CAM_FRONT:2"), parse("fov:120")]
    family = {c.name: (c.family, c.severity) for c in conditions_of(sets, corruptions, "v1.0-sim")}
    assert family == {"clean": (None, 0.0), "occlusion": (None, 0.0), "fog2": ("fog", 2.0), "rain25": ("rain", 25.0),
                      "snow1": ("snow", 1.0), "night": (None, 0.0), "fog1_rain10": (None, 0.0),
                      "beam_missing:16": ("beam_missing", 16.0), "lidar_missing": (None, 0.0),
                      "misalign:CAM_FRONT:2": ("misalign:CAM_FRONT", 2.0), "fov:120": (None, 0.0)}


@pytest.mark.parametrize("args", [(), ("--quick",)])
def test_the_suite_without_models_is_one_line_exit_2_and_writes_nothing(tmp_path, args):
    """Both sizes of scripts/robustness.sh reach their check of the models (a full run once ended
    silently with exit 1 before it) and refuse, writing nothing, when no model is there."""
    root = Path(__file__).resolve().parents[2]
    env = {**os.environ, "OUT": str(tmp_path / "out"), "BENCH": str(tmp_path / "bench"),
           "RECORD": str(tmp_path / "records")}
    proc = subprocess.run(["bash", str(root / "scripts" / "robustness.sh"), *args], capture_output=True, text=True,
                          env=env, timeout=300)
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.strip().splitlines() == [
        f"robustness: no model to test: run scripts/benchmark.sh first (or restore its records in {tmp_path / 'records'})"]
    left_out = [line.split()[1] for line in proc.stdout.splitlines() if line.startswith("robustness:")]
    assert left_out == ["lidar_s0", "camera_s0", "concat_s0", "mcm_s0", "full_s0", "fullmd_s0", "experts_s0"]
    assert list(tmp_path.iterdir()) == []
