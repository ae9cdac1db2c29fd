"""Rain and snowfall on the LIDAR_TOP: the sweep's missed rays, the strongest-return bookkeeping
against the lidar equation computed here, the drawn particles against a brute-force draw of every
particle in the beams, the wet road, and the pipeline's paired bytes."""
from __future__ import annotations

import numpy as np
import pytest

from simgen import degrade, lidarseg
from simgen.config import load_preset, with_degradation, with_weather
from simgen.lidar import N_BEAMS, LidarScanner
from simgen.pipeline import build_world
from simgen.sensor_effects import degrade_sweep
from simgen.settings import MakeSettings, weather_streams
from simgen.weather import lidar_particles as LP
from simgen.weather import lidar_sweep as LS
from simgen.weather import rain_lidar, snow_lidar


@pytest.fixture(scope="module")
def scene():
    cfg = load_preset("tiny")
    s = MakeSettings(cfg, 1, 7, 2, "v1.0-sim")
    return cfg, s, LidarScanner(cfg.lidar, build_world(s, 0)).scan(0.5, np.random.default_rng(0), missed_rays=True)


def _rays(cfg, sweep, fog_alpha=0.0):
    pts = LS.with_ray_column(np.concatenate([sweep.points_lidar, sweep.label[:, None].astype(np.float32)], axis=1))
    return pts, LS.sweep_rays(pts, sweep, cfg.lidar.min_return, fog_alpha)


def test_missed_rays_complete_the_sweep(scene):
    cfg, _, sw = scene
    n_az = int(round(360.0 / cfg.lidar.azimuth_step_deg))
    t_col = 0.5 - 0.05 + (np.arange(n_az) + 0.5) / n_az * 0.05
    ids_hit = np.searchsorted(t_col, sw.time) * N_BEAMS + sw.points_lidar[:, 4].astype(np.int64)
    ids_miss = np.searchsorted(t_col, sw.miss_time) * N_BEAMS + sw.miss_ring
    assert np.array_equal(np.sort(np.concatenate([ids_hit, ids_miss])), np.arange(n_az * N_BEAMS))
    assert np.isinf(sw.miss_range).sum() > 100                      # the open sky
    np.testing.assert_allclose(np.linalg.norm(sw.miss_dir, axis=1), 1.0, atol=1e-12)
    # A missed ray leaves from where the returns of its column leave.
    origin_hit = sw.points_lidar[:, :3] - sw.dir_lidar * sw.range[:, None]
    col_origin = np.zeros((n_az, 3))
    col_origin[ids_hit // N_BEAMS] = origin_hit
    has = np.isin(ids_miss // N_BEAMS, ids_hit // N_BEAMS)
    np.testing.assert_allclose(sw.miss_origin[has], col_origin[ids_miss[has] // N_BEAMS], atol=1e-4)


def test_each_ray_reports_the_stronger_echo_by_the_lidar_equation():
    """Six rays with known particles; every echo computed here from the lidar equation."""
    rho = 0.2
    p_hard = np.array([0.1 / 30**2, 0.0, 5e-4, 5.5e-6, 1e-4, 2e-5])
    r_hard = np.array([30.0, np.inf, 12.0, 40.0, 20.0, 3.0])
    ray = np.array([0, 0, 1, 2, 3, 4, 5, 5])
    rng_ = np.array([4.0, 8.0, 5.0, 3.0, 30.0, 1.5, 2.5, 6.0])
    share = np.array([0.2, 0.01, 0.05, 0.001, 0.002, 0.95, 0.3, 0.5])
    alpha = 0.002
    depth, depth_hard = 2 * alpha * rng_, 2 * alpha * np.minimum(r_hard, 100)
    xi = degrade.overlap(rng_)
    e = LP.strongest_returns(p_hard, r_hard, depth_hard, LP.Particles(ray, rng_, share), depth, xi, rho, 5e-6)
    for j in range(6):
        mine = ray == j
        front = lambda r: np.prod((1 - share[mine & (rng_ < r)]) ** 2)     # noqa: E731
        p_i = [rho * s * x / r**2 * np.exp(-2 * alpha * r) * front(r) for r, s, x in zip(rng_[mine], share[mine], xi[mine])]
        p_h = p_hard[j] * np.exp(-depth_hard[j]) * front(r_hard[j]) if p_hard[j] > 0 else 0.0
        best = max(p_i, default=0.0)
        assert e.p_hard[j] == pytest.approx(p_h, rel=1e-12, abs=1e-300)
        assert e.p_particle[j] == pytest.approx(best, rel=1e-12, abs=1e-300)
        assert e.from_particle[j] == (best > p_h)
        assert e.power[j] == pytest.approx(max(best, p_h), rel=1e-12, abs=1e-300)
        assert e.kept[j] == (max(best, p_h) >= 5e-6)
        if e.from_particle[j]:
            assert e.range[j] == rng_[mine][int(np.argmax(p_i))]
        else:
            assert e.range[j] == r_hard[j]
    # The cases the six rays are meant to cover.
    assert list(e.from_particle) == [True, True, False, False, False, True]
    assert list(e.kept) == [True, True, True, False, False, True]
    assert e.p_hard[4] < 1e-6 < p_hard[4]       # a flake inside the overlap's blind range shadows the car
    # No particle at all: each echo attenuated by the continuous depth only.
    none = LP.Particles(np.zeros(0, np.int64), np.zeros(0), np.zeros(0))
    e = LP.strongest_returns(p_hard, r_hard, depth_hard, none, np.zeros(0), np.zeros(0), rho, 5e-6)
    np.testing.assert_allclose(e.power, p_hard * np.exp(-depth_hard), rtol=1e-12)
    assert not e.from_particle.any()


def _brute_force(field, limit, p_hard, n_rays, min_return, rng):
    """Every particle in n_rays beams to ``limit``: number Poisson(N V), ranges by the beam's
    cross-section, diameters from the whole distribution, each one shadowing those behind; the
    diffraction half of the extinction (efficiency 2 = shadow + diffraction) continuous. Returns
    per ray (particle wins, reported, hard echo after the particles)."""
    a = lambda r: field.optics.tx_radius + field.optics.tx_divergence * r       # noqa: E731
    grid = np.linspace(0.0, limit, 20001)
    vol = np.concatenate([[0.0], np.cumsum(np.pi * a(0.5 * (grid[1:] + grid[:-1])) ** 2 * np.diff(grid))])
    k = rng.poisson(field.dist.number_density() * vol[-1], n_rays)
    ray = np.repeat(np.arange(n_rays), k)
    r = np.interp(rng.random(len(ray)) * vol[-1], vol, grid)
    order = np.lexsort((r, ray))
    ray, r = ray[order], r[order]
    d_opt = field.dist.optical_diameter(field.dist.sample(rng.random(len(ray))))
    s = np.minimum((0.5e-3 * d_opt / a(r)) ** 2, 1.0)
    geo = np.pi / 4 * 1e-6 * field.dist.integral(lambda d: field.dist.optical_diameter(d) ** 2)
    diffraction = 2 * (field.alpha - geo)                  # two-way, per metre
    log_pass = 2 * np.log1p(-np.minimum(s, 1 - 1e-12))
    cum = np.concatenate([[0.0], np.cumsum(log_pass)])
    start = np.concatenate([[0], np.cumsum(k)])[:-1]
    in_front = cum[:-1] - cum[start][ray]
    p = field.reflectivity * s * degrade.overlap(r) / r**2 * np.exp(in_front - diffraction * r)
    best = np.zeros(n_rays)
    np.maximum.at(best, ray, p)
    hard = p_hard * np.exp(cum[start + k] - cum[start] - diffraction * limit)
    return best > hard, np.maximum(best, hard) >= min_return, hard


@pytest.mark.parametrize("kind, rate, p_hard", [("snow", 1.0, 6e-6), ("snow", 1.0, 1e-4), ("rain", 100.0, 6e-6)])
def test_drawn_particles_match_a_brute_force_draw_of_every_particle(scene, kind, rate, p_hard):
    """Drawing only the particles that can matter (and the rest as a continuous extinction) gives
    the rays the same statistics as drawing every particle in the beams: how often a particle is
    reported, how often the ray reports, and the mean transmission exp(-2 alpha L)."""
    cfg = scene[0]
    field = (snow_lidar.snow_field if kind == "snow" else rain_lidar.rain_field)(rate, cfg.lidar)
    n, limit = 3000, 30.0
    rng = np.random.default_rng(5)
    wins_b, kept_b, hard_b = _brute_force(field, limit, p_hard, n, cfg.lidar.min_return, rng)
    rays = LS.SweepRays(np.zeros((n, 3)), np.tile([1.0, 0, 0], (n, 1)), np.zeros(n, np.int64), np.full(n, limit),
                        np.ones(n), np.ones(n), 0.0, np.arange(n), np.full(n, p_hard), np.full(n, limit))
    _, e = LS.precipitation_echoes(rays, field, np.ones(n), cfg.lidar.min_return, rng)
    # (A particle below the threshold may "win" over a hard echo below it too; nothing is reported.)
    for model, brute in ((e.from_particle & e.kept, wins_b & kept_b), (e.kept, kept_b)):
        sigma = np.sqrt(max(brute.mean() * (1 - brute.mean()), 1e-4) * 2 / n)
        assert abs(model.mean() - brute.mean()) < 4 * sigma + 0.005
    assert (e.p_hard / p_hard).mean() == pytest.approx(np.exp(-2 * field.alpha * limit), rel=0.01)
    assert (hard_b / p_hard).mean() == pytest.approx(np.exp(-2 * field.alpha * limit), rel=0.01)


def test_particle_counts_are_poisson_and_ranges_follow_the_beam(scene):
    cfg = scene[0]
    field = snow_lidar.snow_field(2.5, cfg.lidar)
    n = 20000
    parts = LP.draw_particles(field, np.full(n, np.inf), np.zeros(n, np.int64), np.random.default_rng(3))
    k = np.bincount(parts.ray, minlength=n)
    assert k.mean() == pytest.approx(field.count[0, -1], rel=0.02)
    assert k.var() == pytest.approx(k.mean(), rel=0.05)
    assert np.all(np.diff(parts.range)[np.diff(parts.ray) == 0] >= 0)   # in order of range along each ray
    # Ranges: the share of particles before r is count(r) / count(inf).
    for r in (3.0, 6.0, 12.0, 25.0):
        assert (parts.range < r).mean() == pytest.approx(np.interp(r, field.r, field.count[0]) / field.count[0, -1],
                                                         abs=0.01)


def test_rain_and_snow_on_a_sweep_keep_every_return_the_lidar_equation_keeps(scene):
    cfg, _, sw = scene
    pts, rays = _rays(cfg, sw)
    field = snow_lidar.snow_field(2.5, cfg.lidar)
    _, e = LS.precipitation_echoes(rays, field, np.ones(len(pts)), cfg.lidar.min_return, np.random.default_rng(0))
    out, after = LS.echo_points(pts, rays, e, field.alpha, cfg.lidar.intensity_ref_range)
    ray = out[:, LS.RAY_COLUMN].astype(np.int64)
    assert np.array_equal(np.sort(ray), np.flatnonzero(e.kept))        # one row per reporting ray, no other
    assert np.all(e.kept[e.p_hard >= cfg.lidar.min_return])           # no ray silent that the equation keeps
    # Shadows only take away: the surviving echo is at most the mean field's continuous share of it.
    clean = np.zeros(len(rays.limit))
    clean[rays.row_ray] = rays.row_power
    assert np.all(e.p_hard <= clean + 1e-18)
    noise = out[:, LS.LABEL_COLUMN] == lidarseg.NOISE
    hard = ~noise & (ray < len(sw.range))
    np.testing.assert_array_equal(out[hard, :3], sw.points_lidar[ray[hard], :3])
    np.testing.assert_array_equal(out[hard, LS.LABEL_COLUMN], sw.label[ray[hard]])
    assert np.all(out[hard, 3] <= sw.points_lidar[ray[hard], 3])
    # Clutter lies on its ray, in front of the surface the ray met, from rays with and without returns.
    r = np.einsum("nd,nd->n", out[noise, :3] - rays.origin[ray[noise]], rays.direction[ray[noise]])
    np.testing.assert_allclose(out[noise, :3], rays.origin[ray[noise]] + rays.direction[ray[noise]] * r[:, None],
                               atol=1e-4)
    assert np.all(r < rays.limit[ray[noise]]) and np.all(out[noise, 4] == rays.ring[ray[noise]])
    assert noise.sum() > 100 and (ray[noise] >= len(sw.range)).sum() > 10      # clutter in the sky too
    assert np.median(r) < 10.0                                                 # near the sensor
    np.testing.assert_allclose(after.row_power, e.power[ray])


def _weather_points(cfg, s, sw, **weather):
    cfg = with_weather(cfg, **weather)
    return degrade_sweep(sw, cfg, np.zeros(0, int), np.random.default_rng(1), weather_streams(s, 0))


def test_rate_zero_gives_the_clean_bytes(scene):
    cfg, s, sw = scene
    pts, labels = _weather_points(cfg, s, sw, night=True)
    assert pts.tobytes() == sw.points_lidar.tobytes() and labels.tobytes() == sw.label.tobytes()
    p7, rays = _rays(cfg, sw)
    assert rain_lidar.rain_sweep(p7, rays, 0.0, cfg.lidar, np.random.default_rng(0))[0] is p7
    assert snow_lidar.snow_sweep(p7, rays, 0.0, cfg.lidar, np.random.default_rng(0))[0] is p7


def test_the_pipeline_runs_the_same_steps_and_is_a_function_of_its_seed(scene):
    cfg, s, sw = scene
    pts, labels = _weather_points(cfg, s, sw, rain=20.0, snow=1.0)
    again, _ = _weather_points(cfg, s, sw, rain=20.0, snow=1.0)
    assert pts.tobytes() == again.tobytes()
    p7, rays = _rays(cfg, sw)
    w = weather_streams(s, 0)
    p7, rays = rain_lidar.rain_sweep(p7, rays, 20.0, cfg.lidar, w.rain_lidar)
    p7, _ = snow_lidar.snow_sweep(p7, rays, 1.0, cfg.lidar, w.snow_lidar)
    assert pts.tobytes() == np.ascontiguousarray(p7[:, :5]).tobytes()
    assert np.array_equal(labels, p7[:, 5].astype(np.uint8))
    # With fog before, and beams dropped after: the label stays the clean one or becomes noise.
    cfg_all = with_degradation(cfg, fog=3, beam_drop=4)
    pts, labels = _weather_points(cfg_all, s, sw, rain=20.0, snow=1.0)
    assert len(pts) > 0.5 * len(sw.range) and set(np.unique(labels)) <= set(np.unique(sw.label)) | {lidarseg.NOISE}


def _counts(cfg, s, sw, **weather):
    pts, labels = _weather_points(cfg, s, sw, **weather)
    return int((labels != lidarseg.NOISE).sum()), int((labels == lidarseg.NOISE).sum())


def test_the_effect_grows_with_the_rate(scene):
    cfg, s, sw = scene
    for kind, rates in (("rain", (5.0, 50.0, 200.0)), ("snow", (0.5, 2.5, 10.0))):
        kept, clutter = zip(*[_counts(cfg, s, sw, **{kind: r}) for r in rates])
        assert kept[0] > kept[1] > kept[2] and clutter[0] < clutter[1] < clutter[2], (kind, kept, clutter)


def test_wet_road_gain_is_fresnel_and_the_trapped_light():
    n, rho = rain_lidar.WATER_INDEX, 0.12
    # Light scattered by the pavement inside the film, Lambertian: the share that escapes through
    # the surface, by Fresnel's transmission seen from inside (to the critical angle).
    tw = np.linspace(0.0, np.arcsin(1 / n), 200001)
    ta = np.arcsin(np.clip(n * np.sin(tw), 0, 1))
    rs = ((n * np.cos(tw) - np.cos(ta)) / (n * np.cos(tw) + np.cos(ta))) ** 2
    rp = ((np.cos(tw) - n * np.cos(ta)) / (np.cos(tw) + n * np.cos(ta))) ** 2
    y = (1 - 0.5 * (rs + rp)) * 2 * np.sin(tw) * np.cos(tw)
    escapes = float(np.sum(0.5 * (y[1:] + y[:-1]) * np.diff(tw)))
    assert rain_lidar.internal_reflectance() == pytest.approx(1 - escapes, abs=1e-4)
    r0 = ((n - 1) / (n + 1)) ** 2
    assert rain_lidar.wet_road_gain(np.array(1.0), rho) == pytest.approx((1 - r0) ** 2 / n**2 / (1 - rho * (1 - escapes)),
                                                                         rel=1e-4)
    g = rain_lidar.wet_road_gain(np.cos(np.deg2rad([0, 60, 80, 87])), rho)
    assert np.all(np.diff(g) < 0) and g[-1] < 0.06


def test_the_wet_road_gives_fewer_weaker_ground_returns(scene):
    cfg, s, sw = scene
    p7, rays = _rays(cfg, sw)
    out, _ = rain_lidar.rain_sweep(p7, rays, 1.0, cfg.lidar, np.random.default_rng(0))
    road_clean = sw.label == lidarseg.ROAD
    ray = out[:, LS.RAY_COLUMN].astype(np.int64)
    road = out[:, LS.LABEL_COLUMN] == lidarseg.ROAD
    far = sw.range > 20.0
    assert road.sum() < road_clean.sum()
    assert (road & far[np.minimum(ray, len(far) - 1)]).sum() < 0.5 * (road_clean & far).sum()
    # Every road return kept is at most the wet road's share of its clean power.
    g = rain_lidar.wet_road_gain(sw.cos_inc[ray[road]], sw.rho[ray[road]])
    clean_p = sw.rho[ray[road]] * sw.cos_inc[ray[road]] / sw.range[ray[road]] ** 2
    assert np.all(out[road, 3] <= np.round(255 * np.clip(clean_p * g * cfg.lidar.intensity_ref_range**2, 0, 1)))
    assert out[road, 3].sum() < sw.points_lidar[ray[road], 3].sum()
    # Surfaces the film does not cover lose only what 1 mm/h of drops takes (weak, far returns).
    other = ~np.isin(sw.label, rain_lidar.WET_SURFACES)
    assert np.isin(np.flatnonzero(other), ray).mean() > 0.99


def test_a_clear_scan_skips_the_missed_rays_and_the_weather_refuses_it(scene):
    """The missed rays are bookkept only when asked for (rain and snow read them): a clear scan's
    points are the same bytes without them, and a precipitation refuses a sweep that lacks them."""
    cfg, s, sw = scene
    clear = LidarScanner(cfg.lidar, build_world(s, 0)).scan(0.5, np.random.default_rng(0))
    assert clear.miss_dir is None and sw.miss_dir is not None
    assert clear.points_lidar.tobytes() == sw.points_lidar.tobytes()
    with pytest.raises(ValueError, match="missed_rays=True"):
        LS.sweep_rays(LS.with_ray_column(clear.points_lidar), clear, cfg.lidar.min_return, 0.0)
