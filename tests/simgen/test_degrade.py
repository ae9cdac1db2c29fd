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
from simgen.pipeline import MakeSettings, build_world
from simgen.sensor_effects import degrade_sweep
from simgen.settings import weather_streams
from simgen.rig import T_ego_from_lidar


def _streams(cfg):
    """A scene's weather streams (unused in clear weather, drawn as the pipeline draws them)."""
    return weather_streams(MakeSettings(cfg, 1, 0, 1, "v1.0-sim"), 0)


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
    _, _, fog_r = degrade.fog_table(degrade.FOG_ALPHA[5])
    sigma = degrade.fog_returns(rho_cos, ranges, degrade.FOG_ALPHA[5], 5e-6).range_sigma
    k = np.rint(ranges / degrade.TABLE_STEP).astype(int)
    assert (np.abs(r - fog_r[k]) < 5 * sigma + 1e-4).all() and (r < 10.0).all()   # near the sensor
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


def _overlap_by_chords(r, optics=degrade.HDL32E, n=2001):
    """The overlap at ranges r (m,) by integrating, across the beam's disc (radius a, centre 0),
    the length of each chord that also lies in the field's disc (radius b, centre ``offset``),
    over the beam's area: a quadrature independent of degrade.overlap's closed form."""
    r = np.asarray(r, float)[:, None]
    a = optics.tx_radius + optics.tx_divergence * r
    b = optics.rx_radius + optics.rx_fov * r
    y = a * np.linspace(-1.0, 1.0, n)[None, :]
    half_a = np.sqrt(np.maximum(a * a - y * y, 0.0))
    half_b = np.sqrt(np.maximum(b * b - y * y, 0.0))
    inside_b = b * b > y * y
    lo, hi = np.maximum(-half_a, optics.offset - half_b), np.minimum(half_a, optics.offset + half_b)
    chord = np.where(inside_b, np.maximum(hi - lo, 0.0), 0.0)
    return np.trapz(chord, y, axis=1) / np.trapz(2 * half_a, y, axis=1)


def test_overlap_is_the_biaxial_geometry():
    """0 before the beam enters the receiver's field, 1 once the field holds the whole beam,
    monotone between, and equal to the area fraction of the two discs (by chords)."""
    o = degrade.HDL32E
    r1, r2 = o.onset(), o.full()
    assert 1.0 < r1 < r2 < 20.0
    # The onset: the discs touch (a + b = offset); full overlap: the field holds the beam (b - a = offset).
    assert o.tx_radius + o.tx_divergence * r1 + o.rx_radius + o.rx_fov * r1 == pytest.approx(o.offset)
    assert (o.rx_radius + o.rx_fov * r2) - (o.tx_radius + o.tx_divergence * r2) == pytest.approx(o.offset)
    r = np.linspace(0.0, 30.0, 30001)
    xi = degrade.overlap(r)
    assert (xi[r <= r1] == 0).all() and (xi[r >= r2] == 1).all() and (xi[(r > r1) & (r < r2)] > 0).all()
    assert (np.diff(xi) >= 0).all()
    probe = np.linspace(r1, r2, 25)
    np.testing.assert_allclose(degrade.overlap(probe), _overlap_by_chords(probe), atol=2e-3)


@pytest.mark.parametrize("alpha", [degrade.FOG_ALPHA[1], degrade.FOG_ALPHA[5]])
def test_fog_table_is_the_soft_target_integral(alpha):
    """The table against a direct quadrature of the soft-target echo (degrade.py's derivation):
    pi beta int sin^2(pi (R - R') / (c tau_H)) xi(R') exp(-2 alpha R') / R'^2 dR' over the fog in
    front of the target (R' <= R0), its maximum over the waveform range R, reported at R - c tau_H / 2."""
    width = degrade.C_LIGHT * degrade.TAU_H
    beta = degrade.BETA_PER_INV_MOR / degrade.visibility_of(alpha)
    r_tab, best, fog_r = degrade.fog_table(alpha)
    dr = 0.004
    assert best[: int(degrade.HDL32E.onset() / degrade.TABLE_STEP)].max() == 0   # no fog echo before the onset
    for R0 in (2.3, 3.0, 4.0, 6.0, 8.0, 10.0, 60.0):
        # The fog in front of the target (midpoints); waveform ranges up to 15 m, past which the
        # echo only falls (1/R^2 and exp(-2 alpha R), checked at the end).
        Rp = np.arange(dr / 2, min(R0, 15.0), dr)
        h = np.pi * beta * _overlap_by_chords(Rp) * np.exp(-2 * alpha * Rp) / Rp**2
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
        far = sweep.range > 12.0                                             # past the fog's own peak
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
        pts, seg = degrade_sweep(sweep, c, np.zeros(0, int), np.random.default_rng(1), _streams(c))
        same, is_fog = degrade.fog_lidar(sweep.points_lidar, sweep.rho * sweep.cos_inc, sweep.range, sweep.dir_lidar,
                                   degrade.FOG_ALPHA[sev], cfg.lidar.min_return, cfg.lidar.intensity_ref_range,
                                   np.random.default_rng(1))
        np.testing.assert_array_equal(same, pts)
        # Fog returns are labelled noise; the hard returns keep their surface's class.
        assert (seg[is_fog] == lidarseg.NOISE).all() and (seg[~is_fog] != lidarseg.NOISE).all()
        # They sit in the fog in front of their target, a few metres out: the fog's echo peaks
        # once the beam is in the receiver's field, read as the pulse's lead.
        ray, _, _ = _fog_by_ray(sweep, cfg, degrade.FOG_ALPHA[sev])
        r_fog = np.linalg.norm(pts[is_fog, :3] - (sweep.points_lidar[ray[is_fog], :3]
                                                  - sweep.dir_lidar[ray[is_fog]] * sweep.range[ray[is_fog], None]), axis=1)
        assert is_fog.any() and (r_fog >= degrade.MIN_RANGE - 1e-4).all()
        assert (r_fog <= sweep.range[ray[is_fog]] + 1e-4).all() and np.median(r_fog) < degrade.HDL32E.full()


def _soft_echo_by_quadrature(alpha, r0_grid, dr=0.005, span=15.0):
    """The fog's strongest echo in front of a target at each R0 of ``r0_grid``, by the test's own
    quadrature of the lidar equation: max over the waveform range R of
    pi beta int_{R' < R0} sin^2(pi (R - R') / W) xi(R') exp(-2 alpha R') / R'^2 dR' (W = c tau_H),
    xi by chords. Past ``span`` (beyond the fog's own peak) the value at ``span`` holds."""
    width = degrade.C_LIGHT * degrade.TAU_H
    beta = degrade.BETA_PER_INV_MOR / degrade.visibility_of(alpha)
    Rp = np.arange(dr / 2, span, dr)
    h = np.pi * beta * _overlap_by_chords(Rp) * np.exp(-2 * alpha * Rp) / Rp**2
    lag = np.arange(int(np.ceil(width / dr)) + 1)
    pulse = np.where(lag > 0, np.sin(np.pi * np.clip((lag - 0.5) * dr / width, 0.0, 1.0)) ** 2, 0.0)
    return np.array([(np.convolve(h * (Rp < min(R0, span)), pulse) * dr).max() for R0 in r0_grid])


def test_each_ray_reports_the_stronger_echo_by_the_lidar_equation(clean_sweep):
    """Per ray, against an independent computation of both echoes: the hard echo
    rho cos exp(-2 alpha R0) / R0^2 and the fog's (quadrature above, the overlap by chords). The
    ray reports the stronger, with its power as intensity, when it reaches min_return; rays within
    1% of a tie are left out (at most 2% of them)."""
    cfg, sweep = clean_sweep
    rho_cos, R0, thr, ref = sweep.rho * sweep.cos_inc, sweep.range, cfg.lidar.min_return, cfg.lidar.intensity_ref_range
    step = 0.05
    grid = np.arange(0.0, 15.0 + step, step)
    for alpha in degrade.FOG_ALPHA[1:]:
        soft_grid = _soft_echo_by_quadrature(alpha, grid)
        k = np.minimum((R0 / step).astype(int), len(grid) - 2)
        lo, hi = soft_grid[k], soft_grid[k + 1]                  # the echo only grows with R0
        p_hard = rho_cos / R0**2 * np.exp(-2 * alpha * R0)
        fog = p_hard < 0.99 * lo
        hard = p_hard > 1.01 * hi
        stronger = np.where(fog, lo, p_hard)
        sure = (fog | hard) & (np.abs(stronger - thr) > 0.01 * thr)
        assert sure.mean() > 0.98, sure.mean()
        ray, is_fog, out = _fog_by_ray(sweep, cfg, alpha)
        delivered = np.zeros(len(R0), bool)
        delivered[ray] = True
        won = np.zeros(len(R0), bool)
        won[ray[is_fog]] = True
        np.testing.assert_array_equal(delivered[sure], (stronger >= thr)[sure])
        np.testing.assert_array_equal(won[sure & delivered], fog[sure & delivered])
        row = np.full(len(R0), -1)
        row[ray] = np.arange(len(ray))
        got = out[row[sure & delivered], 3]
        want = 255 * np.clip(np.where(fog, (lo + hi) / 2, p_hard) * ref**2, 0, 1)[sure & delivered]
        assert (np.abs(got - want) <= 0.5 + 0.01 * want).all()


def test_haze_makes_no_fog_returns(clean_sweep):
    """At a visibility of 2 km and more the fog's strongest echo stays below the clear-weather
    threshold: no fog return, and every hard return the lidar equation keeps is delivered."""
    cfg, sweep = clean_sweep
    for mor in (2000.0, 5000.0):
        alpha = degrade.alpha_of_visibility(mor)
        assert degrade.fog_table(alpha)[1].max() < cfg.lidar.min_return
        ray, is_fog, _ = _fog_by_ray(sweep, cfg, alpha)
        p_hard = sweep.rho * sweep.cos_inc / sweep.range**2 * np.exp(-2 * alpha * sweep.range)
        assert not is_fog.any() and np.array_equal(ray, np.nonzero(p_hard >= cfg.lidar.min_return)[0])


def _located_range(sweep, ray, out):
    """Distance (k,) from each delivered row's ray origin to its point."""
    origin = sweep.points_lidar[ray, :3] - sweep.dir_lidar[ray] * sweep.range[ray, None]
    return np.linalg.norm(out[:, :3] - origin, axis=1)


def test_fog_returns_are_a_cloud_located_with_the_receivers_noise(clean_sweep):
    """Each fog return lies at the fog's peak plus the receiver's noise of one sigma
    ``range_sigma`` (standardised: mean 0, sigma 1), far wider than a hard echo's 2 cm and wider
    for a weaker fog (the peak of a weaker echo is located less precisely)."""
    cfg, sweep = clean_sweep
    medians = []
    for alpha in degrade.FOG_ALPHA[1:]:
        ray, is_fog, out = _fog_by_ray(sweep, cfg, alpha)
        f = degrade.fog_returns(sweep.rho * sweep.cos_inc, sweep.range, alpha, cfg.lidar.min_return)
        r = ray[is_fog]
        located = _located_range(sweep, r, out[is_fog])
        free = (located > degrade.MIN_RANGE + 1e-3) & (located < sweep.range[r] - 1e-3)   # not clipped
        z = (located - f.fog_range[r])[free] / f.range_sigma[r][free]
        assert free.mean() > 0.95 and abs(z.mean()) < 0.15 and abs(z.std() - 1.0) < 0.15, (alpha, z.mean(), z.std())
        medians.append(float(np.median(f.range_sigma[r])))
    assert min(medians) > 2.5 * degrade.RANGE_SIGMA and all(b < a for a, b in zip(medians, medians[1:])), medians


def test_lidar_fog_is_a_function_of_its_seed(clean_sweep):
    """Same seed, same bytes; another seed moves only the fog returns, along their rays."""
    cfg, sweep = clean_sweep
    a = _fog_by_ray(sweep, cfg, degrade.FOG_ALPHA[3])
    b = _fog_by_ray(sweep, cfg, degrade.FOG_ALPHA[3])
    assert a[2].tobytes() == b[2].tobytes() and (a[0] == b[0]).all()
    pts = np.concatenate([sweep.points_lidar, np.arange(len(sweep.range), dtype=np.float32)[:, None]], axis=1)
    c, is_fog = degrade.fog_lidar(pts, sweep.rho * sweep.cos_inc, sweep.range, sweep.dir_lidar, degrade.FOG_ALPHA[3],
                                  cfg.lidar.min_return, cfg.lidar.intensity_ref_range, np.random.default_rng(2))
    np.testing.assert_array_equal(c[~is_fog], a[2][~a[1]])
    assert (c[is_fog, 3:] == a[2][a[1], 3:]).all() and (c[is_fog, :3] != a[2][a[1], :3]).any(axis=1).mean() > 0.99


def test_one_alpha_drives_camera_and_lidar():
    """One setting, one alpha: a pixel's transmittance is exp(-alpha d) and a hard return's power
    exp(-2 alpha R), through the pipeline's own degrade functions."""
    from simgen import rig
    from simgen.camera import depth_to_range
    from simgen.lidar import Sweep
    from simgen.sensor_effects import degrade_image
    cfg = with_degradation(load_preset("tiny"), fog_visibility=150.0)
    alpha = cfg.degrade.alpha
    assert alpha == pytest.approx(math.log(20) / 150.0)
    cam = rig.cameras((160, 90))[0]
    depth = np.full((90, 160), 40.0, np.float32)
    J = np.full((90, 160, 3), 30, np.uint8)
    s = MakeSettings(cfg, 1, 7, 1, "v1.0-sim")
    img = degrade_image(J, depth, cam, cfg, s, 0, 0, weather_streams(s, 0), 0.0).astype(float)
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
    got, _ = degrade_sweep(sweep, cfg, np.zeros(0, int), np.random.default_rng(0), _streams(cfg))

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
    pts, seg = degrade_sweep(sweep, with_degradation(cfg, beam_drop=5), rings, np.random.default_rng(1), _streams(cfg))
    keep = ~np.isin(sweep.points_lidar[:, 4], rings)
    np.testing.assert_array_equal(seg, sweep.label[keep])          # the labels follow their points
    kept = set(np.unique(pts[:, 4]).astype(int))
    before = set(np.unique(sweep.points_lidar[:, 4]).astype(int))
    assert kept == before - set(rings.tolist()) and len(rings) == 5
    n_expected = (~np.isin(sweep.points_lidar[:, 4], rings)).sum()
    assert len(pts) == n_expected

    pts, seg = degrade_sweep(sweep, with_degradation(cfg, lidar_fov=90.0), rings[:0], np.random.default_rng(1),
                             _streams(cfg))
    # The ego's forward axis in the LIDAR_TOP frame: about +y (the mount is rotated by -90 deg).
    fwd = T_ego_from_lidar()[:3, :3].T @ np.array([1.0, 0.0, 0.0])
    assert fwd[1] > 0.99

    def azimuth(p):
        a = np.degrees(np.arctan2(p[:, 1], p[:, 0]) - np.arctan2(fwd[1], fwd[0]))
        return (a + 180) % 360 - 180

    assert np.abs(azimuth(pts)).max() <= 45.0 and len(pts) > 0
    assert len(pts) == (np.abs(azimuth(sweep.points_lidar)) <= 45.0).sum()
    np.testing.assert_array_equal(seg, sweep.label[np.abs(azimuth(sweep.points_lidar)) <= 45.0])
    pts, seg = degrade_sweep(sweep, with_degradation(cfg, drop_sensors="LIDAR_TOP"), rings[:0],
                             np.random.default_rng(1), _streams(cfg))
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
