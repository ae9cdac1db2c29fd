"""Degradation: exact fog on both sensors, lens dirt, rings, sector, dead sensors, pairing."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest
from conftest import TINY_ARGS, run_simgen

from simgen import degrade as D
from simgen import lidarseg as LS
from simgen.config import load_preset, with_degradation
from simgen.lidar import LidarScanner
from simgen.pipeline import MakeSettings, build_world, degrade_sweep
from simgen.rig import T_ego_from_lidar


def test_camera_fog_is_koschmieder_exactly():
    rng = np.random.default_rng(0)
    J = rng.integers(0, 256, (40, 60, 3)).astype(np.uint8)
    d = rng.uniform(0.5, 300.0, (40, 60))
    d[:5] = 0.0                                          # sky: no hit
    alpha = D.FOG_ALPHA[4]
    out = D.fog_image(J, d, alpha)
    t = np.where(d > 0, np.exp(-alpha * d), 0.0)[..., None]
    expected = J * t + D.AIRLIGHT * (1 - t)                  # float64 reference
    assert np.abs(out - expected).max() <= 0.5 + 1e-3       # the formula, rounded to the nearest level
    assert (out[:5] == np.round(D.AIRLIGHT).astype(np.uint8)).all()      # the sky is all airlight
    np.testing.assert_array_equal(D.fog_image(J, d, 0.0)[5:], J[5:])     # alpha 0 changes nothing


def test_visibility_and_alpha_are_inverse():
    for a in D.FOG_ALPHA[1:]:
        assert D.alpha_of_visibility(D.visibility_of(a)) == pytest.approx(a)
    assert D.visibility_of(0.06) == pytest.approx(math.log(20) / 0.06)


def _synthetic_returns(ranges, rho_cos):
    n = len(ranges)
    dirs = np.tile([[0.0, 1.0, 0.0]], (n, 1))
    pts = np.zeros((n, 5), np.float32)
    pts[:, :3] = dirs * ranges[:, None]
    return pts, dirs


def test_lidar_fog_hard_returns_attenuate_as_exp_minus_2_alpha_r():
    """Strong targets (the fog cannot beat them) keep their place; power scales exp(-2 alpha R)."""
    ranges = np.linspace(5.0, 40.0, 36)
    rho_cos = np.full(36, 0.9)
    pts, dirs = _synthetic_returns(ranges, rho_cos)
    ref = 2.0                                          # intensity unsaturated: P ref^2 < 1
    alpha = D.FOG_ALPHA[2]
    out, is_fog = D.fog_lidar(pts, rho_cos, ranges, dirs, alpha, 1e-9, ref, np.random.default_rng(0),
                              background_gain=0.0)
    assert not is_fog.any() and len(out) == 36
    np.testing.assert_allclose(out[:, :3], pts[:, :3])                  # not moved
    clean = 255 * rho_cos / ranges**2 * ref**2
    ratio = out[:, 3] / clean
    np.testing.assert_allclose(ratio, np.exp(-2 * alpha * ranges), rtol=0, atol=0.5 / clean.min() + 1e-6)


def test_lidar_fog_moves_weak_far_returns_to_the_fog_range_along_the_ray():
    ranges = np.array([60.0, 80.0])
    rho_cos = np.array([0.05, 0.05])
    pts, dirs = _synthetic_returns(ranges, rho_cos)
    out, is_fog = D.fog_lidar(pts, rho_cos, ranges, dirs, D.FOG_ALPHA[5], 5e-6, 6.0, np.random.default_rng(0),
                              background_gain=0.0)
    assert is_fog.all()
    r = np.linalg.norm(out[:, :3], axis=1)
    assert ((r > 1.0) & (r < 5.0)).all()                                # near the sensor
    np.testing.assert_allclose(out[:, :3] / r[:, None], dirs, atol=1e-6)  # on the same ray
    # A return lost to attenuation when the fog response is below the threshold too.
    out2, _ = D.fog_lidar(pts, rho_cos, ranges, dirs, D.FOG_ALPHA[5], 1.0, 6.0, np.random.default_rng(0),
                          background_gain=0.0)
    assert len(out2) == 0


def test_lidar_fog_threshold_rises_with_the_airlight_along_the_beam():
    """A hard return is kept exactly when P_hard >= min_return (1 + G (1 - exp(-alpha R0)))."""
    alpha, t0, gain = D.FOG_ALPHA[3], 5e-6, 200.0
    ranges = np.array([10.0, 20.0, 30.0])
    threshold = t0 * (1 + gain * (1 - np.exp(-alpha * ranges)))
    for factor, kept in ((1.01, True), (0.99, False)):
        rho_cos = factor * threshold * ranges**2 * np.exp(2 * alpha * ranges)   # P_hard = factor * T
        assert (rho_cos / ranges**2 > D.fog_table(alpha)[1][-1]).all()          # the fog cannot win
        pts, dirs = _synthetic_returns(ranges, rho_cos)
        out, is_fog = D.fog_lidar(pts, rho_cos, ranges, dirs, alpha, t0, 6.0, np.random.default_rng(0),
                                  background_gain=gain)
        assert len(out) == (3 if kept else 0) and not is_fog.any()


@pytest.fixture(scope="module")
def clean_sweep():
    cfg = load_preset("tiny")
    s = MakeSettings(cfg, 1, 7, 2, "v1.0-sim")
    world = build_world(s, 0)
    return cfg, LidarScanner(cfg.lidar, world).scan(0.5, np.random.default_rng(0))


def test_lidar_fog_on_a_scene_monotone_in_severity(clean_sweep):
    cfg, sweep = clean_sweep
    far, total, fog_near = [], [], []
    for sev in range(6):
        c = with_degradation(cfg, fog=sev)
        pts, seg = degrade_sweep(sweep, c, np.zeros(0, int), np.random.default_rng(1))
        r = np.linalg.norm(pts[:, :3], axis=1)
        far.append(int((r > 30).sum()))
        total.append(len(pts))
        same, is_fog = D.fog_lidar(sweep.points_lidar, sweep.rho * sweep.cos_inc, sweep.range, sweep.dir_lidar,
                                   D.FOG_ALPHA[sev], cfg.lidar.min_return, cfg.lidar.intensity_ref_range,
                                   np.random.default_rng(1), background_gain=cfg.lidar.fog_background_gain)
        np.testing.assert_array_equal(same, pts)
        # Fog returns are labelled noise; the hard returns keep their surface's class.
        assert (seg[is_fog] == LS.NOISE).all() and (seg[~is_fog] != LS.NOISE).all()
        fog_near.append(int((is_fog & (r < 10)).sum()))
    assert all(b < a for a, b in zip(total, total[1:])), total     # every severity loses points
    assert far == sorted(far, reverse=True) and far[5] < far[0] // 4   # the far scene fades away
    assert fog_near == sorted(fog_near) and fog_near[0] == 0        # fog clutter near the sensor ...
    assert fog_near[5] > 1000 and fog_near[5] > 10 * fog_near[3]    # ... appears in dense fog


def test_beam_drop_and_sector(clean_sweep):
    cfg, sweep = clean_sweep
    rings = D.choose_rings(5, np.random.default_rng(3))
    pts, seg = degrade_sweep(sweep, with_degradation(cfg, beam_drop=5), rings, np.random.default_rng(1))
    keep = ~np.isin(sweep.points_lidar[:, 4], rings)
    np.testing.assert_array_equal(seg, sweep.label[keep])          # the labels follow their points
    kept = set(np.unique(pts[:, 4]).astype(int))
    before = set(np.unique(sweep.points_lidar[:, 4]).astype(int))
    assert kept == before - set(rings.tolist()) and len(rings) == 5
    n_expected = (~np.isin(sweep.points_lidar[:, 4], rings)).sum()
    assert len(pts) == n_expected

    pts, seg = degrade_sweep(sweep, with_degradation(cfg, lidar_fov=90.0), rings[:0], np.random.default_rng(1))
    # The ego's forward axis in the LIDAR_TOP frame: about +y (the mount is rotated by -90 deg).
    fwd = T_ego_from_lidar()[:3, :3].T @ np.array([1.0, 0.0, 0.0])
    assert fwd[1] > 0.99

    def azimuth(p):
        a = np.degrees(np.arctan2(p[:, 1], p[:, 0]) - np.arctan2(fwd[1], fwd[0]))
        return (a + 180) % 360 - 180

    assert np.abs(azimuth(pts)).max() <= 45.0 and len(pts) > 0
    assert len(pts) == (np.abs(azimuth(sweep.points_lidar)) <= 45.0).sum()
    np.testing.assert_array_equal(seg, sweep.label[np.abs(azimuth(sweep.points_lidar)) <= 45.0])
    pts, seg = degrade_sweep(sweep, with_degradation(cfg, drop_sensors="LIDAR_TOP"), rings[:0], np.random.default_rng(1))
    assert len(pts) == 0 and len(seg) == 0


def test_lens_dirt_is_deterministic_and_grows_with_severity():
    img = np.full((90, 160, 3), 200, np.uint8)
    a = D.lens_dirt(img, 2, np.random.default_rng(5))
    b = D.lens_dirt(img, 2, np.random.default_rng(5))
    np.testing.assert_array_equal(a, b)
    covered = [int((np.abs(D.lens_dirt(img, s, np.random.default_rng(5)).astype(int) - 200).sum(-1) > 30).sum())
               for s in (1, 3, 5)]
    assert 0 < covered[0] < covered[1] < covered[2]


def test_paired_sets_and_dead_sensors(tmp_path, tiny_dataset):
    """A fog-5 run with dead sensors pairs with the clean tiny set: identical annotation tables,
    black images and empty clouds where sensors failed, and the devkit loads it."""
    out = tmp_path / "fog"
    run_simgen("make", "--out", out, "--workers", "1", *TINY_ARGS, "--fog", "5", "--beam-drop", "4",
               "--drop-sensor", "CAM_FRONT,LIDAR_TOP")
    for table in ("sample_annotation", "instance", "ego_pose", "sample"):
        assert (out / "v1.0-sim" / f"{table}.json").read_bytes() == \
               (tiny_dataset / "v1.0-sim" / f"{table}.json").read_bytes(), table
    rec = json.loads((out / "v1.0-sim" / "degradation.json").read_text())
    assert rec["settings"]["fog"] == 5 and rec["failed_sensors"] == ["CAM_FRONT", "LIDAR_TOP"]
    assert len(rec["dropped_rings"]["scene-0000"]) == 4

    from nuscenes import NuScenes
    from nuscenes.utils.data_classes import LidarPointCloud
    import cv2
    nusc = NuScenes("v1.0-sim", str(out), verbose=False)
    assert "fog" in nusc.scene[0]["description"] and "CAM_FRONT" in nusc.scene[0]["description"]
    sample = nusc.sample[0]
    front = cv2.imread(str(out / nusc.get("sample_data", sample["data"]["CAM_FRONT"])["filename"]))
    assert front is not None and front.max() == 0
    back = cv2.imread(str(out / nusc.get("sample_data", sample["data"]["CAM_BACK"])["filename"]))
    assert back.mean() > 100                                  # foggy, bright, not black
    path, boxes, _ = nusc.get_sample_data(sample["data"]["LIDAR_TOP"])
    assert LidarPointCloud.from_file(path).points.shape[1] == 0 and len(boxes) > 0


def test_bad_degradation_settings_exit_2(tmp_path):
    for args, needle in ((["--fog", "7"], "--fog"), (["--fog-visibility", "-5"], "--fog-visibility"),
                         (["--drop-sensor", "CAM_TOP"], "CAM_TOP"), (["--beam-drop", "33"], "--beam-drop")):
        proc = run_simgen("make", "--out", tmp_path / "x", *TINY_ARGS, *args, check=False)
        assert proc.returncode == 2, (args, proc.stderr)
        line = proc.stderr.strip()
        assert len(line.splitlines()) == 1 and needle in line and "Traceback" not in line
        assert not (tmp_path / "x").exists()


def test_occluders_keep_every_object_and_only_lower_visibility_and_points(tmp_path, tiny_dataset):
    out = tmp_path / "occ"
    run_simgen("make", "--out", out, "--workers", "1", *TINY_ARGS, "--occlusion", "heavy")
    for table in ("instance", "ego_pose", "sample"):
        assert (out / "v1.0-sim" / f"{table}.json").read_bytes() == \
               (tiny_dataset / "v1.0-sim" / f"{table}.json").read_bytes(), table
    occ = json.loads((out / "v1.0-sim" / "sample_annotation.json").read_text())
    ref = json.loads((tiny_dataset / "v1.0-sim" / "sample_annotation.json").read_text())
    assert [a["token"] for a in occ] == [a["token"] for a in ref]           # every object still exists
    for a, b in zip(occ, ref):
        assert {k: v for k, v in a.items() if k not in ("visibility_token", "num_lidar_pts")} == \
               {k: v for k, v in b.items() if k not in ("visibility_token", "num_lidar_pts")}
        assert a["num_lidar_pts"] <= b["num_lidar_pts"]                      # occluders only block rays
    assert sum(a["num_lidar_pts"] for a in occ) < sum(a["num_lidar_pts"] for a in ref)
    assert sum(int(a["visibility_token"]) for a in occ) < sum(int(b["visibility_token"]) for b in ref)


def test_occluders_never_touch_an_actor():
    from simgen import geometry as geo
    cfg = with_degradation(load_preset("tiny"), occlusion="heavy")
    for idx in range(3):
        world = build_world(MakeSettings(cfg, 3, 7, 3, "v1.0-sim"), idx)
        clean = build_world(MakeSettings(load_preset("tiny"), 3, 7, 3, "v1.0-sim"), idx)
        n_new = len(world.static_boxes) - len(clean.static_boxes)
        assert n_new == world.meta["occluders"] >= 4
        np.testing.assert_array_equal(world.xy, clean.xy)                   # the same tracks
        new = world.static_boxes[-n_new:]
        for k in range(0, len(world.times), 5):
            boxes = world.boxes_at(float(world.times[k]))
            a = np.repeat(new, len(boxes), 0)
            b = np.tile(boxes, (len(new), 1))
            assert not geo.bev_overlap_pairwise(a, b).any()
