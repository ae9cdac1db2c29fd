"""Rain and snowfall in the camera: Koschmieder's veil with the precipitation's extinction, the
streaks of the particles near the lens (length, place, mass, occlusion, count), the wet road's
darkening and mirror, rate 0 and seeds."""
from __future__ import annotations

import math

import numpy as np
import pytest

from simgen import rig
from simgen.camera import depth_to_range
from simgen import degrade
from simgen.weather import particles, rain_camera, snow_camera, streaks, veil, wet_road

SIZE = (320, 180)
CAM = rig.cameras(SIZE)[0]
K = CAM.K
DOWN = np.array([0.0, 1.0, 0.0])             # a level camera: gravity along its y
SHARP = streaks.CameraOptics(exposure_s=0.005, aperture_m=0.0, focus_m=1.0)
DAY_SKY = (158, 188, 224)                     # the renderer's sky, int(255 * (0.62, 0.74, 0.88))


def _koschmieder(J, d, alpha, A):
    t = np.exp(-alpha * d)[..., None]
    return np.round(J * t + np.asarray(A) * (1 - t))


def _uniform(value, depth_m):
    W, H = SIZE
    return np.full((H, W, 3), value, np.uint8), np.full((H, W), depth_m, np.float32)


def test_overcast_airlight_is_the_grey_of_the_skys_luminance():
    A = veil.overcast_airlight(DAY_SKY)
    assert np.all(A == A[0]) and A[0] == pytest.approx(0.2126 * 158 + 0.7152 * 188 + 0.0722 * 224)
    # The sky's colour is read off the image; with none in view, the renderer's sky by day or night.
    J, depth = _uniform(40, 10.0)
    J[:5], depth[:5] = (10, 20, 30), 0.0
    np.testing.assert_allclose(veil.sky_colour(J, depth), [10, 20, 30])
    np.testing.assert_allclose(veil.sky_colour(J[5:], depth[5:], veil.rendered_sky(False)), DAY_SKY)
    night = veil.sky_colour(J[5:], depth[5:], veil.rendered_sky(True))
    assert (night < 40).all() and (night != DAY_SKY).all()


@pytest.mark.parametrize("veil_of, extinction, rate", [(rain_camera.rain_veil, particles.rain_extinction, 25.0),
                                                        (snow_camera.snow_veil, particles.snow_extinction, 1.0)])
def test_veil_is_koschmieder_with_the_precipitations_extinction(veil_of, extinction, rate):
    """A uniform image at a uniform depth: each pixel is round(J t + A (1 - t)), t = exp(-alpha d)
    on its own range, with alpha the precipitation's; 1.1 alpha misses; the sky is the airlight."""
    J, depth = _uniform(30, 300.0)
    depth[:20] = 0.0                                            # a band of sky
    A = veil.overcast_airlight(DAY_SKY)
    alpha = extinction(rate)
    out = veil_of(J, depth_to_range(depth, K), rate, A).astype(float)
    d = depth * np.sqrt(1 + ((np.arange(SIZE[0]) + 0.5 - K[0, 2]) / K[0, 0])[None, :] ** 2
                        + ((np.arange(SIZE[1]) + 0.5 - K[1, 2]) / K[1, 1])[:, None] ** 2)
    ground = depth > 0
    assert np.abs(out - _koschmieder(J, d, alpha, A))[ground].max() <= 1.0
    assert np.abs(out - _koschmieder(J, d, 1.1 * alpha, A))[ground].max() > 3.0
    assert (out[~ground] == np.round(A)).all()


def test_the_veil_is_the_fogs_law():
    """The fused veil and simgen.degrade.fog_image (OpenCV's blend) agree to a level (each rounds
    the same law once)."""
    rng = np.random.default_rng(0)
    J = rng.integers(0, 256, (SIZE[1], SIZE[0], 3), dtype=np.uint8)
    depth = rng.uniform(0, 400, SIZE[::-1]).astype(np.float32)
    depth[:30] = 0
    A = veil.overcast_airlight(DAY_SKY)
    d = depth_to_range(depth, K)
    ours = rain_camera.rain_veil(J, d, 25.0, A).astype(int)
    fog = degrade.fog_image(J, d, particles.rain_extinction(25.0), A).astype(int)
    assert np.abs(ours - fog).max() <= 1


def test_rain_image_is_the_veil_wherever_no_drop_passed():
    """Without a wet road, the rain image is the exact veil on every pixel no streak covers."""
    J, depth = _uniform(60, 80.0)
    A = veil.overcast_airlight(DAY_SKY)
    out = rain_camera.rain_image(J, depth, K, 25.0, np.random.default_rng(3), DOWN, np.zeros(3), None, DAY_SKY)
    veiled = rain_camera.rain_veil(J, depth_to_range(depth, K), 25.0, A)
    rng = np.random.default_rng(3)
    drops = streaks.sample_particles(particles.rain_distribution(25.0), K, SIZE, streaks.DAY_OPTICS, DOWN,
                                     np.zeros(3), rng, 0.1)
    cover = streaks.coverage(streaks.project(drops, K, SIZE, streaks.DAY_OPTICS, 0.1), SIZE, depth)
    assert (cover > 0).any() and (cover == 0).any()
    np.testing.assert_array_equal(out[cover == 0], veiled[cover == 0])
    assert (out[cover > 0] != veiled[cover > 0]).any()


def test_rate_0_returns_the_image_itself():
    J, depth = _uniform(90, 20.0)
    assert rain_camera.rain_image(J, depth, K, 0.0, np.random.default_rng(0), DOWN, np.zeros(3)) is J
    assert snow_camera.snow_image(J, depth, K, 0.0, np.random.default_rng(0), DOWN, np.zeros(3)) is J


def _one(p_mid, velocity, diameter):
    return streaks.Particles(np.array([p_mid], float), np.array([velocity], float), np.array([diameter], float))


def _moments(cover):
    """Mass, centroid (x, y) and variances (x, y) of a coverage image, pixel centres at +0.5."""
    H, W = cover.shape
    y, x = np.mgrid[:H, :W] + 0.5
    m = cover.sum(dtype=np.float64)
    cx, cy = (cover * x).sum() / m, (cover * y).sum() / m
    return m, (cx, cy), ((cover * (x - cx) ** 2).sum() / m, (cover * (y - cy) ** 2).sum() / m)


def test_a_streak_is_the_fall_during_the_exposure_projected_through_K():
    """One drop at a known place: its coverage integrates to its disc's area, is centred on the
    projection of its mid-exposure position, and is as long as v T projected: the spread along the
    fall is L^2 / 12 + r^2 / 4 (a uniform sweep of a disc) plus at most 1/4 px^2 of the bilinear
    splat, so L is recovered to 0.05 px; a 2% longer exposure would be 0.5 px off."""
    p, v, D, T = np.array([0.05, -0.02, 0.5]), 8.0, 1e-3, SHARP.exposure_s
    s = streaks.project(_one(p, [0.0, v, 0.0], D), K, SIZE, SHARP, 0.1)
    cover = streaks.coverage(s, SIZE, np.zeros(SIZE[::-1], np.float32))
    f = K[0, 0]
    d, L = f * D / p[2], K[1, 1] * v * T / p[2]
    a_expected = K @ (p - [0, v * T / 2, 0]) / p[2]
    np.testing.assert_allclose(s.a[0], a_expected[:2], atol=1e-9)
    m, (cx, cy), (vx, vy) = _moments(cover)
    assert m == pytest.approx(math.pi * d**2 / 4, rel=1e-5)
    assert (cx, cy) == pytest.approx(tuple((K @ p / p[2])[:2]), abs=0.02)
    L_seen = math.sqrt(12 * (vy - d**2 / 16))
    assert L_seen == pytest.approx(L, abs=0.05 + 12 * 0.25 / (2 * L))
    assert abs(L_seen - 1.02 * L) > 0.3
    rows = np.flatnonzero(cover.sum(axis=1) > 0) + 0.5
    assert rows.min() >= a_expected[1] - d / 2 - 1 and rows.max() <= a_expected[1] + L + d / 2 + 1


def test_defocus_spreads_a_near_drop_but_keeps_its_mass():
    p, D = np.array([0.0, 0.0, 0.4]), 2e-3
    optics = streaks.DAY_OPTICS
    sharp = streaks.coverage(streaks.project(_one(p, [0, 0, 0], D), K, SIZE, SHARP, 0.1), SIZE,
                             np.zeros(SIZE[::-1], np.float32))
    blurred = streaks.coverage(streaks.project(_one(p, [0, 0, 0], D), K, SIZE, optics, 0.1), SIZE,
                               np.zeros(SIZE[::-1], np.float32))
    b = K[0, 0] * optics.aperture_m * abs(1 / p[2] - 1 / optics.focus_m)
    assert b > 1.0
    assert blurred.sum(dtype=np.float64) == pytest.approx(sharp.sum(dtype=np.float64), rel=1e-5)
    # A resting disc of diameter d_eff: variance d_eff^2 / 16 per axis (plus the splat's < 1/4).
    _, _, (vx, _) = _moments(blurred)
    d_eff = math.hypot(K[0, 0] * D / p[2], b)
    assert d_eff**2 / 16 - 0.05 <= vx <= d_eff**2 / 16 + 0.3


def test_a_streak_behind_a_nearer_surface_is_not_drawn():
    """A wall 1 m away over the left half: a drop crossing the middle 2 m away is drawn only on
    the right (in proportion to its path there); one 0.5 m away, in front of the wall, on both."""
    W, H = SIZE
    depth = np.zeros((H, W), np.float32)
    depth[:, : W // 2] = 1.0
    for z, both in ((2.0, False), (0.5, True)):
        x_mid = ((W / 2 + 0.5) - K[0, 2]) / K[0, 0] * z     # just right of the wall's edge
        s = streaks.project(_one([x_mid, 0.0, z], [6.0 * z, 0.0, 0.0], 1e-3), K, SIZE, SHARP, 0.1)
        cover = streaks.coverage(s, SIZE, depth)
        left, right = cover[:, : W // 2].sum(), cover[:, W // 2:].sum()
        assert right > 0
        if both:
            assert left > 0
        else:
            assert left == 0
            a_u, b_u = s.a[0, 0], s.b[0, 0]
            m = math.pi * (K[0, 0] * 1e-3 / z) ** 2 / 4
            assert right == pytest.approx(m * (b_u - W / 2) / (b_u - a_u), rel=0.05)


def _expected_count(dist, margin, z_min, d_min_px=1.0):
    """The mean number of drawn particles by a 2-d midpoint rule over (D, z), independently of
    streaks.depth_profile: N(D) dD times the widened window's volume from z_min to f D_opt / d_min."""
    W, H = SIZE
    wx, wy = W / K[0, 0], H / K[1, 1]
    D = (np.arange(6000) + 0.5) / 6000 * dist.d_max
    z_max = K[0, 0] * dist.optical_diameter(D) * 1e-3 / d_min_px
    u = np.linspace(0, 1, 801)[None, :]
    z = z_min + (np.maximum(z_max, z_min)[:, None] - z_min) * (u[:, :-1] + u[:, 1:]) / 2
    area = (wx * z + 2 * margin) * (wy * z + 2 * margin)
    volume = area.mean(axis=1) * np.maximum(z_max - z_min, 0)
    return float(np.sum(dist.density(D) * volume) * dist.d_max / 6000)


@pytest.mark.parametrize("kind, rates", [("rain", (0.5, 2.0, 10.0, 25.0, 100.0, 200.0)),
                                         ("snow", (0.1, 0.5, 1.0, 2.5, 10.0))])
def test_the_number_of_particles_follows_the_distribution_and_grows_with_the_rate(kind, rates):
    counts, drawn = [], []
    for rate in rates:
        dist = particles.rain_distribution(rate) if kind == "rain" else particles.snow_distribution(rate)
        _, cum = streaks.depth_profile(dist, K, SIZE, 0.02, 0.1, 1.0)
        assert cum[-1] == pytest.approx(_expected_count(dist, 0.02, 0.1), rel=0.01)
        counts.append(cum[-1])
        p = streaks.sample_particles(dist, K, SIZE, SHARP, DOWN, np.zeros(3), np.random.default_rng(5), 0.1)
        drawn.append(len(p.diameter))
        # Every drawn particle is resolved (its image at least a pixel wide) and beyond the near plane.
        assert (K[0, 0] * p.diameter / p.p_mid[:, 2] >= 1 - 1e-9).all() and (p.p_mid[:, 2] >= 0.1).all()
    assert np.all(np.diff(counts) > 0) and np.all(np.diff(drawn) > 0)
    assert abs(drawn[-1] - counts[-1]) < 5 * math.sqrt(counts[-1])


def test_particles_fall_at_their_speed_relative_to_a_moving_camera():
    v_cam = np.array([0.0, 0.0, 10.0])
    dist = particles.rain_distribution(25.0)
    p = streaks.sample_particles(dist, K, SIZE, SHARP, DOWN, v_cam, np.random.default_rng(1), 0.1)
    fall = p.velocity + v_cam
    np.testing.assert_allclose(fall, particles.rain_fall_speed(p.diameter * 1e3)[:, None] * DOWN, atol=1e-12)


@pytest.mark.parametrize("image", [rain_camera.rain_image, snow_camera.snow_image])
def test_same_seed_same_bytes(image):
    J, depth = _uniform(70, 30.0)
    rate = 25.0 if image is rain_camera.rain_image else 1.0
    a, b, c = (image(J, depth, K, rate, np.random.default_rng(seed), DOWN, np.array([0.0, 0.0, 8.0]))
               for seed in (11, 11, 12))
    assert a.tobytes() == b.tobytes() and a.tobytes() != c.tobytes()


def test_flakes_blend_toward_their_radiance():
    """Each changed pixel is the veil blended toward the flakes' radiance 0.9 (A + G) / 2 by one
    coverage for all three channels; heavier snowfall covers more of the image."""
    J = np.zeros((SIZE[1], SIZE[0], 3), np.uint8)
    J[..., 0], J[..., 1], J[..., 2] = 20, 60, 110
    depth = np.full(J.shape[:2], 50.0, np.float32)
    A = veil.overcast_airlight(DAY_SKY)
    covered = []
    for rate in (0.5, 2.0):
        veiled = snow_camera.snow_veil(J, depth_to_range(depth, K), rate, A).astype(float)
        out = snow_camera.snow_image(J, depth, K, rate, np.random.default_rng(2), DOWN, np.zeros(3)).astype(float)
        E = 0.9 * (A + veiled[int(K[1, 2]):][::4, ::4].reshape(-1, 3).mean(axis=0)) / 2
        changed = np.any(out != veiled, axis=-1)
        # The coverage read off the channel farthest from E, then every channel is that blend.
        k = int(np.argmax(np.abs(E - veiled[0, 0])))
        c = (out[changed, k] - veiled[changed, k]) / (E[k] - veiled[changed, k])
        assert changed.sum() > 20 and (c > -0.5 / abs(E[k] - veiled[0, 0, k])).all() and (c <= 1 + 1e-6).all()
        blended = np.round(veiled[changed] + c[:, None] * (E - veiled[changed]))
        assert np.abs(out[changed] - blended).max() <= 1.0
        covered.append(changed.mean())
    assert covered[1] > covered[0]


# ---------------------------------------------------------------- the wet road

def _fresnel(cos_i, n=1.333):
    sin_t = np.sqrt(1 - cos_i**2) / n
    cos_t = np.sqrt(1 - sin_t**2)
    rs = (cos_i - n * cos_t) / (cos_i + n * cos_t)
    rp = (cos_t - n * cos_i) / (cos_t + n * cos_i)
    return (rs**2 + rp**2) / 2


def test_wet_albedo_is_lekner_and_dorfs():
    """r_e by a trapezoid over the angle (not the module's Gauss-Legendre over the cosine), then
    a_w / a = (1 - r_e)(1 - r_i) / (1 - a r_i), r_i = 1 - (1 - r_e) / n^2: 0.066 and 0.52 for asphalt."""
    theta = np.linspace(0, np.pi / 2, 200001)
    g = _fresnel(np.cos(theta)) * 2 * np.sin(theta) * np.cos(theta)
    r_e = float(np.sum((g[1:] + g[:-1]) / 2 * np.diff(theta)))
    assert wet_road.diffuse_fresnel() == pytest.approx(r_e, rel=1e-6) and r_e == pytest.approx(0.066, abs=0.001)
    r_i = 1 - (1 - r_e) / 1.333**2
    for a in (0.0, 0.1, 0.3, 0.6, 1.0):
        assert wet_road.wet_albedo_ratio(a) == pytest.approx((1 - r_e) * (1 - r_i) / (1 - a * r_i), rel=1e-9)
    assert wet_road.wet_albedo_ratio(0.1) == pytest.approx(0.515, abs=0.005)


def _street(h=1.5, Z_w=20.0, wall_h=3.0):
    """A level camera h above a flat road (grey 60) that ends at a wall (red) Z_w ahead, wall_h
    tall, sky above: per pixel its rgb, camera z and which is road; and the road points' mirrored
    rays' height where they reach the wall's plane."""
    W, H = SIZE
    u = ((np.arange(W) + 0.5 - K[0, 2]) / K[0, 0])[None, :]
    v = ((np.arange(H) + 0.5 - K[1, 2]) / K[1, 1])[:, None] * np.ones((1, W))
    with np.errstate(divide="ignore"):
        z_road = np.where(v > 0, h / v, np.inf)
    road = z_road < Z_w
    wall = ~road & (v * Z_w >= h - wall_h)
    depth = np.where(road, z_road, np.where(wall, Z_w, 0.0)).astype(np.float32)
    rgb = np.zeros((H, W, 3), np.uint8)
    rgb[road], rgb[wall], rgb[~road & ~wall] = (60, 60, 60), (200, 40, 40), DAY_SKY
    # The mirrored ray rises by v per unit of z from the road (height 0): height at the wall's plane.
    rise = np.where(road, (Z_w - np.where(road, z_road, 0)) * v, np.nan)
    return rgb, depth, road, rise, u, v


def test_the_wet_road_mirrors_the_wall_and_the_sky(monkeypatch):
    """A smooth film (no roughness): road pixels whose mirrored ray reaches the wall below its top
    show the wall, those whose ray passes above it the sky, away from that edge by the march's
    grid (2 px here: 0.16 m of height on the wall, the rise being 20 m x v)."""
    monkeypatch.setattr(wet_road, "ROUGHNESS", 0.0)
    rgb, depth, road, rise, u, v = _street()
    A = veil.overcast_airlight(DAY_SKY)
    M = wet_road.mirrored(rgb, depth, road, K, -DOWN, A)
    margin = 3 / K[1, 1] * 20.0 + 0.2
    sees_wall = road & (rise < 3.0 - margin) & (rise > margin)
    sees_sky = road & (rise > 3.0 + margin)
    assert sees_wall.sum() > 100 and sees_sky.sum() > 50
    assert np.abs(M[sees_wall] - [200, 40, 40]).max() <= 1.0
    assert np.abs(M[sees_sky] - A).max() <= 1.0


def test_the_wet_road_darkens_by_lekner_dorf_and_mirrors_by_fresnel():
    """Each wet pixel is 60 a_w/a (1 - R)/(1 - r_e) + M R, R Fresnel's at its own incidence, M
    the (rough) mirror's radiance; dry pixels keep their bytes."""
    rgb, depth, road, rise, u, v = _street()
    A = veil.overcast_airlight(DAY_SKY)
    up = -DOWN
    M = wet_road.mirrored(rgb, depth, road, K, up, A)
    out = wet_road.wet_road(rgb, depth, road, K, up, A).astype(float)
    cos_i = v / np.sqrt(u**2 + v**2 + 1)
    R = _fresnel(cos_i)[..., None]
    r_e = wet_road.diffuse_fresnel()
    expected = 60 * wet_road.wet_albedo_ratio(60 / 255) * (1 - R) / (1 - r_e) + M * R
    assert np.abs(out - np.round(expected))[road].max() <= 1.0
    np.testing.assert_array_equal(out[~road], rgb[~road])
    # Grazing road far away mirrors more than the road under the camera.
    assert R[road].max() > 0.6 and R[road].min() < 0.2
