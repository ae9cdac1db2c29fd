"""Degradation: exact fog on both sensors, lens dirt, rings, sector, dead sensors, pairing."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest
from conftest import TINY_ARGS, run_simgen
from scipy.special import lambertw

from simgen import degrade
from simgen import lidarseg
from simgen.config import load_preset, with_degradation
from simgen.lidar import LidarScanner
from simgen.pipeline import MakeSettings, build_world, degrade_sweep
from simgen.rig import T_ego_from_lidar


def test_camera_fog_is_koschmieder_exactly():
    rng = np.random.default_rng(0)
    J = rng.integers(0, 256, (40, 60, 3)).astype(np.uint8)
    d = rng.uniform(0.5, 300.0, (40, 60))
    d[:5] = 0.0                                          # sky: no hit
    alpha = degrade.FOG_ALPHA[4]
    out = degrade.fog_image(J, d, alpha)
    t = np.where(d > 0, np.exp(-alpha * d), 0.0)[..., None]
    expected = J * t + degrade.AIRLIGHT * (1 - t)                  # float64 reference
    assert np.abs(out - expected).max() <= 0.5 + 1e-3       # the formula, rounded to the nearest level
    assert (out[:5] == np.round(degrade.AIRLIGHT).astype(np.uint8)).all()      # the sky is all airlight
    np.testing.assert_array_equal(degrade.fog_image(J, d, 0.0)[5:], J[5:])     # alpha 0 changes nothing


def test_visibility_and_alpha_are_inverse():
    for a in degrade.FOG_ALPHA[1:]:
        assert degrade.alpha_of_visibility(degrade.visibility_of(a)) == pytest.approx(a)
    assert degrade.visibility_of(0.06) == pytest.approx(math.log(20) / 0.06)


def _synthetic_returns(ranges, rho_cos):
    n = len(ranges)
    dirs = np.tile([[0.0, 1.0, 0.0]], (n, 1))
    pts = np.zeros((n, 5), np.float32)
    pts[:, :3] = dirs * ranges[:, None]
    return pts, dirs


def test_lidar_fog_hard_returns_attenuate_as_exp_minus_2_alpha_r():
    """Strong targets (the fog cannot beat them) keep their place; power scales exp(-2 alpha R)."""
    ranges = np.linspace(5.0, 25.0, 21)
    rho_cos = np.full(21, 0.9)
    pts, dirs = _synthetic_returns(ranges, rho_cos)
    ref = 2.0                                          # intensity unsaturated: P ref^2 < 1
    alpha = degrade.FOG_ALPHA[2]
    p_hard = rho_cos / ranges**2 * np.exp(-2 * alpha * ranges)
    assert (p_hard > degrade.fog_table(alpha)[1].max()).all()                 # the fog cannot win
    out, is_fog = degrade.fog_lidar(pts, rho_cos, ranges, dirs, alpha, 1e-9, ref, np.random.default_rng(0))
    assert not is_fog.any() and len(out) == 21
    np.testing.assert_allclose(out[:, :3], pts[:, :3])                  # not moved
    clean = 255 * rho_cos / ranges**2 * ref**2
    ratio = out[:, 3] / clean
    np.testing.assert_allclose(ratio, np.exp(-2 * alpha * ranges), rtol=0, atol=0.5 / clean.min() + 1e-6)


def test_lidar_fog_moves_weak_far_returns_to_the_fog_range_along_the_ray():
    ranges = np.array([60.0, 80.0])
    rho_cos = np.array([0.05, 0.05])
    pts, dirs = _synthetic_returns(ranges, rho_cos)
    out, is_fog = degrade.fog_lidar(pts, rho_cos, ranges, dirs, degrade.FOG_ALPHA[5], 5e-6, 6.0, np.random.default_rng(0))
    assert is_fog.all()
    r = np.linalg.norm(out[:, :3], axis=1)
    assert ((r > 1.0) & (r < 3.0)).all()                                # near the sensor
    np.testing.assert_allclose(out[:, :3] / r[:, None], dirs, atol=1e-6)  # on the same ray
    # A return lost to attenuation when the fog response is below the threshold too.
    out2, _ = degrade.fog_lidar(pts, rho_cos, ranges, dirs, degrade.FOG_ALPHA[5], 1.0, 6.0, np.random.default_rng(0))
    assert len(out2) == 0


def test_lidar_fog_keeps_the_clear_weather_threshold():
    """A hard return the fog cannot beat is kept exactly when exp(-2 alpha R0) rho cos / R0^2
    reaches min_return: fog raises no threshold."""
    alpha = degrade.FOG_ALPHA[3]
    ranges = np.array([10.0, 20.0, 30.0])
    t0 = 2 * degrade.fog_table(alpha)[1].max()                                # above every fog echo
    for factor, kept in ((1.01, True), (0.99, False)):
        rho_cos = factor * t0 * ranges**2 * np.exp(2 * alpha * ranges)   # p_hard = factor * t0
        pts, dirs = _synthetic_returns(ranges, rho_cos)
        out, is_fog = degrade.fog_lidar(pts, rho_cos, ranges, dirs, alpha, t0, 6.0, np.random.default_rng(0))
        assert len(out) == (3 if kept else 0) and not is_fog.any()


@pytest.mark.parametrize("alpha", [degrade.FOG_ALPHA[1], degrade.FOG_ALPHA[5]])
def test_fog_table_is_the_soft_target_integral(alpha):
    """The table against a direct quadrature of the soft-target echo (degrade.py's derivation):
    pi beta int sin^2(pi (R - R') / (c tau_H)) xi(R') exp(-2 alpha R') / R'^2 dR' over the fog in
    front of the target (R' <= R0), its maximum over the waveform range R, reported at R - c tau_H / 2."""
    width = degrade.C_LIGHT * degrade.TAU_H
    beta = degrade.BETA_PER_INV_MOR / degrade.visibility_of(alpha)
    r_tab, best, fog_r = degrade.fog_table(alpha)
    dr = 0.004
    for R0 in (1.2, 2.0, 3.0, 4.0, 10.0, 60.0):
        # The fog in front of the target (midpoints); waveform ranges up to 15 m, past which the
        # echo only falls (1/R^2 and exp(-2 alpha R), checked at the end).
        Rp = np.arange(dr / 2, min(R0, 15.0), dr)
        h = np.pi * beta * degrade.crossover(Rp) * np.exp(-2 * alpha * Rp) / Rp**2
        R = np.arange(0.0, min(R0 + width, 15.0), 0.01)[:, None]
        s = R - Rp[None, :]
        w = np.where((s >= 0) & (s <= width), np.sin(np.pi * s / width) ** 2, 0.0)
        wave = (w * h).sum(1) * dr
        k = int(round(R0 / degrade.TABLE_STEP))
        assert best[k] == pytest.approx(wave.max(), rel=0.01), R0
        assert fog_r[k] == pytest.approx(R[np.argmax(wave), 0] - width / 2, abs=0.03), R0
    # Far from the sensor the echo of fog alone is the textbook volume return pi beta (c tau_H / 2) / R^2.
    far = 40.0
    Rp = np.arange(far - width, far, dr)
    wave = (np.sin(np.pi * (far - Rp) / width) ** 2 * np.pi * beta * np.exp(-2 * alpha * Rp) / Rp**2).sum() * dr
    assert wave == pytest.approx(np.pi * beta * width / 2 * np.exp(-2 * alpha * (far - width / 2)) / (far - width / 2) ** 2,
                                 rel=0.02)


@pytest.fixture(scope="module")
def clean_sweep():
    cfg = load_preset("tiny")
    s = MakeSettings(cfg, 1, 7, 2, "v1.0-sim")
    world = build_world(s, 0)
    return cfg, LidarScanner(cfg.lidar, world).scan(0.5, np.random.default_rng(0))


BANDS = (0.0, 10.0, 30.0, 50.0, np.inf)


def _fog_by_ray(sweep, cfg, alpha):
    """Run fog with each ray's index carried as an extra column: (delivered ray indices, is_fog)."""
    pts = np.concatenate([sweep.points_lidar, np.arange(len(sweep.range), dtype=np.float32)[:, None]], axis=1)
    out, is_fog = degrade.fog_lidar(pts, sweep.rho * sweep.cos_inc, sweep.range, sweep.dir_lidar, alpha,
                              cfg.lidar.min_return, cfg.lidar.intensity_ref_range, np.random.default_rng(1))
    return out[:, 5].astype(np.int64), is_fog, out


def test_lidar_fog_follows_the_lidar_equation_on_a_sweep(clean_sweep):
    """Strongest return, on a generated sweep: no ray whose attenuated hard return reaches the
    clear-weather threshold goes silent; the hard returns per band are exactly the lidar
    equation's minus the rays the fog wins, never more; the fog wins the weakest first."""
    cfg, sweep = clean_sweep
    band = np.digitize(sweep.range, BANDS[1:-1])
    rho_cos = sweep.rho * sweep.cos_inc
    loss, n_fog = [], []
    for alpha in degrade.FOG_ALPHA:
        p_hard = rho_cos / sweep.range**2 * np.exp(-2 * alpha * sweep.range)     # the lidar equation
        expected = p_hard >= cfg.lidar.min_return
        ray, is_fog, out = _fog_by_ray(sweep, cfg, alpha)
        assert (np.diff(ray) > 0).all()                                    # rows in ray order
        delivered = np.zeros(len(expected), bool)
        delivered[ray] = True
        assert not (expected & ~delivered).any()                            # no silent ray
        hard = np.zeros(len(expected), bool)
        hard[ray[~is_fog]] = True
        won = np.zeros(len(expected), bool)
        won[ray[is_fog]] = True
        assert not (hard & ~expected).any()                                  # never above the equation
        xyz_ring = [0, 1, 2, 4]                                              # hard rows stay in place
        np.testing.assert_array_equal(out[~is_fog][:, xyz_ring], sweep.points_lidar[ray[~is_fog]][:, xyz_ring])
        for b in range(len(BANDS) - 1):
            in_b = band == b
            assert (hard & in_b).sum() == (expected & in_b).sum() - (expected & won & in_b).sum()
        far = sweep.range > 5.0                                              # past the fog's own peak
        if (won & far).any() and (hard & far).any():
            assert p_hard[won & far].max() <= p_hard[hard & far].min()       # the weakest go first
        loss.append([int((~hard & (band == b)).sum()) for b in range(len(BANDS) - 1)])
        n_fog.append(int(is_fog.sum()))
    loss = np.array(loss)
    assert (np.diff(loss, axis=0) >= 0).all(), loss                         # loss grows in every band
    assert (np.diff(loss.sum(1)) > 0).all(), loss
    assert n_fog[0] == 0 and all(b > a for a, b in zip(n_fog, n_fog[1:])), n_fog


def test_lidar_fog_on_a_scene_labels_and_places_the_fog_returns(clean_sweep):
    cfg, sweep = clean_sweep
    for sev in range(1, 6):
        c = with_degradation(cfg, fog=sev)
        pts, seg = degrade_sweep(sweep, c, np.zeros(0, int), np.random.default_rng(1))
        same, is_fog = degrade.fog_lidar(sweep.points_lidar, sweep.rho * sweep.cos_inc, sweep.range, sweep.dir_lidar,
                                   degrade.FOG_ALPHA[sev], cfg.lidar.min_return, cfg.lidar.intensity_ref_range,
                                   np.random.default_rng(1))
        np.testing.assert_array_equal(same, pts)
        # Fog returns are labelled noise; the hard returns keep their surface's class.
        assert (seg[is_fog] == lidarseg.NOISE).all() and (seg[~is_fog] != lidarseg.NOISE).all()
        # They sit near the sensor: the fog's echo peaks a few metres out, read as the pulse's lead.
        ray, _, _ = _fog_by_ray(sweep, cfg, degrade.FOG_ALPHA[sev])
        r_fog = np.linalg.norm(pts[is_fog, :3] - (sweep.points_lidar[ray[is_fog], :3]
                                                  - sweep.dir_lidar[ray[is_fog]] * sweep.range[ray[is_fog], None]), axis=1)
        assert is_fog.any() and (r_fog > 1.0).all() and (r_fog < 2.5).all()


def test_one_alpha_drives_camera_and_lidar():
    """One setting, one alpha: a pixel's transmittance is exp(-alpha d) and a hard return's power
    exp(-2 alpha R), through the pipeline's own degrade functions."""
    from simgen import rig
    from simgen.camera import depth_to_range
    from simgen.lidar import Sweep
    from simgen.pipeline import degrade_image
    cfg = with_degradation(load_preset("tiny"), fog_visibility=150.0)
    alpha = cfg.degrade.alpha
    assert alpha == pytest.approx(math.log(20) / 150.0)
    cam = rig.cameras((160, 90))[0]
    depth = np.full((90, 160), 40.0, np.float32)
    J = np.full((90, 160, 3), 30, np.uint8)
    img = degrade_image(J, depth, cam, cfg, MakeSettings(cfg, 1, 7, 1, "v1.0-sim"), 0, 0).astype(float)
    d = depth_to_range(depth, cam.K)

    def pixel(a):
        t = np.exp(-a * d)[..., None]
        return np.round(J * t + degrade.AIRLIGHT * (1 - t))

    assert np.abs(img - pixel(alpha)).max() <= 1.0 and np.abs(img - pixel(1.1 * alpha)).max() > 3.0
    n = 16
    ranges = np.linspace(5.0, 20.0, n)
    dirs = np.tile([[0.0, 1.0, 0.0]], (n, 1))
    pts = np.zeros((n, 5), np.float32)
    pts[:, :3] = dirs * ranges[:, None]
    rho = np.full(n, 0.9, np.float32)
    ref2 = cfg.lidar.intensity_ref_range ** 2
    pts[:, 3] = np.round(255 * np.clip(0.9 / ranges**2 * ref2, 0, 1))
    sweep = Sweep(pts, np.zeros(n), np.zeros(n, np.int32), rho, np.ones(n), ranges, dirs, np.ones(n, np.uint8))
    got, _ = degrade_sweep(sweep, cfg, np.zeros(0, int), np.random.default_rng(0))

    def intensity(a):
        return np.round(255 * np.clip(0.9 / ranges**2 * np.exp(-2 * a * ranges) * ref2, 0, 1))

    np.testing.assert_array_equal(got[:, 3], intensity(alpha))
    assert (got[:, 3] != intensity(1.1 * alpha)).any()


def test_removed_fog_background_gain_is_refused(tmp_path):
    from simgen.config import list_presets
    from simgen.errors import ConfigError
    bad = tmp_path / "old.yaml"
    bad.write_text("lidar:\n  fog_background_gain: 200.0\n")
    with pytest.raises(ConfigError) as e:
        load_preset(str(bad))
    msg = str(e.value)
    assert "lidar: unknown key 'fog_background_gain'" in msg and "removed" in msg and str(bad) in msg and "\n" not in msg
    for name in list_presets():                                          # no preset still sets it
        load_preset(name)


def test_beam_drop_and_sector(clean_sweep):
    cfg, sweep = clean_sweep
    rings = degrade.choose_rings(5, np.random.default_rng(3))
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
    a = degrade.lens_dirt(img, 2, np.random.default_rng(5))
    b = degrade.lens_dirt(img, 2, np.random.default_rng(5))
    np.testing.assert_array_equal(a, b)
    covered = [int((np.abs(degrade.lens_dirt(img, s, np.random.default_rng(5)).astype(int) - 200).sum(-1) > 30).sum())
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
    from simgen import geometry
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
            assert not geometry.bev_overlap_pairwise(a, b).any()


def test_hard_range_limit_is_where_the_target_stops_being_the_strongest_return():
    """The docs' detection range: the lidar equation's own limit (rho e^{-2 alpha R} / R^2 =
    min_return) where the threshold binds first, else the crossing with the fog's echo."""
    for alpha in degrade.FOG_ALPHA[1:]:
        r, p_fog, _ = degrade.fog_table(alpha)
        for rho, thr in ((0.1, 5e-6), (0.5, 5e-6), (0.5, 2e-3)):
            lim = degrade.hard_range_limit(rho, alpha, thr)
            p = lambda R: rho / R**2 * np.exp(-2 * alpha * R)                # noqa: E731
            k = int(round(lim / degrade.TABLE_STEP))
            assert p(lim) >= max(thr, p_fog[k]) and p(lim + degrade.TABLE_STEP) < max(thr, p_fog[k + 1])
            analytic = float(np.real(lambertw(alpha * math.sqrt(rho / thr)))) / alpha   # R e^{alpha R} = sqrt(rho/thr)
            assert lim <= analytic + degrade.TABLE_STEP
            if thr > p_fog.max():                                                # the threshold binds first
                assert lim == pytest.approx(analytic, abs=degrade.TABLE_STEP)
