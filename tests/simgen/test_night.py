"""Night: street and vehicle lights shade each pixel by I cos / r^2, the camera's photometric model
(EMVA 1288) adds its shot and read noise, and the day's images, the labels and the lidar stay as
they were."""
from __future__ import annotations

import dataclasses
import types

import numpy as np
import pytest
import trimesh

from simgen.camera import Renderer
from simgen.config import CameraConfig, load_preset, with_weather
from simgen.layout import Grid
from simgen.weather import night, night_sensor

W, H = 320, 240
K = np.array([[250.0, 0.0, 160.0], [0.0, 250.0, 120.0], [0.0, 0.0, 1.0]])
GREY = 150                                       # 8-bit sRGB albedo of the test surfaces
SENSOR = night_sensor.CAMERA


def _srgb_to_linear(v):
    v = np.asarray(v, np.float64) / 255.0
    return np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4)


def _linear_to_8bit(x):
    x = np.clip(x, 0.0, 1.0)
    return np.round(255.0 * np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055))


def _full_scale_luminance() -> float:
    """cd/m^2 that fills the pixel at the night exposure, from the camera equation: photons per
    lux s m^2 at 555 nm from Planck's constant and 683 lm/W."""
    photons = 1.0 / (683.0 * 6.62607015e-34 * 299792458.0 / 555e-9)
    s = SENSOR
    image_lux_per_nit = np.pi * s.lens_transmission / (4 * s.f_number ** 2)
    e_per_nit_s = s.quantum_efficiency * photons * image_lux_per_nit * s.pixel_pitch ** 2
    return s.full_well / (s.max_gain * e_per_nit_s * s.max_exposure)


def _stand_in_world(*meshes):
    """A world of static meshes, no actors (what Renderer.set_world reads), and a cube far behind
    the cameras (the shadow pass needs something that can cast)."""
    meshes = (*meshes, _box((1.0, 1.0, 1.0), (0.0, -38.0, 0.5)))
    return types.SimpleNamespace(static_mesh=trimesh.util.concatenate(meshes), actors=[], meta={},
                                 speed=np.zeros((0, 2)), yaw=np.zeros(0), boxes_at=lambda t: np.zeros((0, 7)))


def _box(extents, centre):
    m = trimesh.creation.box(extents=extents)
    m.apply_translation(centre)
    m.visual.face_colors = (GREY, GREY, GREY, 255)
    return m


def _look_at(eye, target) -> np.ndarray:
    z = np.subtract(target, eye) / np.linalg.norm(np.subtract(target, eye))
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, np.cross(z, x), z], 1)
    T[:3, 3] = eye
    return T


def _lights(pos, kind, forward=(1.0, 0.0, 0.0), left=(0.0, 1.0, 0.0), footprint=(0.0, 0.0, 0.0)) -> night.Lights:
    return night.Lights(np.array([pos], float), np.array([forward]), np.array([left]), np.array([kind]),
                        np.array([[1.0, 1.0, 1.0]]), np.array([200.0]), np.array([footprint], float),
                        np.zeros(0, np.int64))


def _render(world, T_global_from_cam, lights=None, shadows=True):
    cfg = dataclasses.replace(CameraConfig(), resolution=(W, H), shadows=shadows)
    r = Renderer(cfg)
    try:
        r.set_world(world, key="night-test")
        cam = types.SimpleNamespace(K=K, resolution=(W, H))
        return r.render(cam, T_global_from_cam, {}, night=lights)
    finally:
        r.close()


def _rays(T_global_from_cam):
    """(H, W, 3) each pixel centre's ray direction, global frame (camera z = 1)."""
    u, v = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    rays_cam = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
    return rays_cam @ T_global_from_cam[:3, :3].T


def _plane_points(T_global_from_cam):
    """(H, W, 3) each pixel centre's ray met with the plane z = 0, and (H, W) whether it meets it
    ahead of the camera."""
    rays = _rays(T_global_from_cam)
    t = -T_global_from_cam[2, 3] / rays[..., 2]
    return T_global_from_cam[:3, 3] + t[..., None] * rays, (t > 0) & (t < 200)


def test_a_street_light_adds_I_cos_over_r2_times_the_albedo():
    """A luminaire 9 m over a grey plane: every pixel inside its lit ellipse gets E = I0 / h^2 on
    top of the ambient (its I0 / cos^3 gamma intensity times cos gamma / r^2, with r = h / cos gamma),
    every pixel beyond its taper the ambient alone: each to within one 8-bit level of
    rho E / pi through the night exposure and the sRGB curve, computed here from the geometry."""
    world = _stand_in_world(_box((80.0, 80.0, 0.02), (0.0, 0.0, -0.01)))
    T = _look_at((0.0, -25.0, 2.0), (0.0, 5.0, 0.0))
    lamp = (0.0, 0.0, night.LAMP_HEIGHT)
    rgb, _, _ = _render(world, T, _lights(lamp, night.STREET, footprint=(12.0, 12.0, 12.0)))
    p, on_plane = _plane_points(T)
    on_plane &= np.all(np.abs(p[..., :2]) < 39.0, axis=-1)
    rho_ground = np.hypot(p[..., 0] - lamp[0], p[..., 1] - lamp[1])
    lit = on_plane & (rho_ground < 11.5)                                  # inside the ellipse
    dark = on_plane & (rho_ground > 12.0 * (1 + night.LAMP_TAPER) + 0.5)  # beyond its taper
    assert lit.sum() > 3000 and dark.sum() > 3000
    albedo = _srgb_to_linear(GREY)
    e_lamp = night.LAMP_I0 / night.LAMP_HEIGHT ** 2
    for mask, e in ((lit, night.AMBIENT_LUX + e_lamp), (dark, night.AMBIENT_LUX)):
        expected = _linear_to_8bit(albedo * e / np.pi / _full_scale_luminance())
        assert np.abs(rgb[mask].astype(int) - expected).max() <= 1, e
    # The two differ by the light's share alone: decoded, rho I0 / (pi h^2) of the full scale.
    diff = _srgb_to_linear(rgb[lit].mean(0)) - _srgb_to_linear(rgb[dark].mean(0))
    np.testing.assert_allclose(diff, albedo * e_lamp / np.pi / _full_scale_luminance(), rtol=0.02)


def test_a_low_beam_lights_a_wall_by_its_intensity_cos_over_r2():
    """A head lamp 0.7 m up, 20 m before a grey wall facing it: each wall pixel's irradiance is the
    beam's intensity toward it times cos / r^2 (r and the incidence from the geometry)."""
    wall_x = 20.0
    world = _stand_in_world(_box((0.2, 60.0, 30.0), (wall_x + 0.1, 0.0, 1.5)))
    T = _look_at((0.0, -1.0, 1.5), (wall_x, -1.0, 1.5))
    lamp = np.array([0.0, 0.0, 0.7])
    rgb, depth, _ = _render(world, T, _lights(lamp, night.HEAD))
    rays = _rays(T)
    p = T[:3, 3] + ((wall_x - T[0, 3]) / rays[..., 0])[..., None] * rays
    d = p - lamp
    r = np.linalg.norm(d, axis=-1)
    intensity = np.vectorize(night.headlamp_intensity)(d[..., 0], d[..., 1], d[..., 2])
    e = night.AMBIENT_LUX + intensity * (d[..., 0] / r) / r ** 2
    expected = _linear_to_8bit(_srgb_to_linear(GREY) * e / np.pi / _full_scale_luminance())
    on_wall = depth > 0
    assert on_wall.all() and expected.max() > 200 and expected.min() < 60     # the beam and its dark skirts
    assert np.abs(rgb.astype(int) - expected[..., None]).max() <= 1


def test_the_low_beam_meets_ecer112_class_b_on_its_25m_screen():
    """ECE Regulation 112's test points (lux at 25 m, right-hand traffic): angles (left +, up +)."""
    def lux(left_deg, up_deg):
        h, v = np.radians(left_deg), np.radians(up_deg)
        return night.headlamp_intensity(np.cos(v) * np.cos(h), np.cos(v) * np.sin(h), np.sin(v)) / 25.0 ** 2
    assert lux(-1.72, -0.86) >= 12 and lux(-1.15, -0.57) >= 12          # 50R, 75R
    assert lux(0.0, -0.86) >= 6                                          # 50V
    assert lux(9.0, -1.72) >= 2 and lux(-9.0, -1.72) >= 2                # 25L, 25R
    assert lux(3.43, 0.57) <= 0.4                                        # B50L, the glare point
    assert night.headlamp_intensity(-1.0, 0.0, 0.0) == 0.0               # nothing behind the lamp


@pytest.mark.parametrize("preset", ["tiny", "urban"])
def test_street_lighting_is_en13201_class_c3(preset):
    """The placed luminaires give a straight road between two junctions 15 lux on average (class
    C3: >= 15 lux maintained, here within 13-18) with Emin / Emean >= 0.4 (computed over a 0.5 m
    grid across the road, from every luminaire's I cos / r^2)."""
    grid = Grid(load_preset(preset).layout)
    lamps = night.street_lights(grid)
    hw = grid.road_half_width
    y0 = grid.ys[1]
    x, y = np.meshgrid(np.arange(grid.xs[0] + hw + 6, grid.xs[1] - hw - 6, 0.5),      # clear of the junctions
                       np.arange(y0 - hw + 0.25, y0 + hw, 0.5))
    p = np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], 1)
    d = lamps.pos[None] - p[:, None]                                    # (points, lamps, 3)
    r = np.linalg.norm(d, axis=-1)
    w = -d / r[..., None]
    intensity = np.vectorize(night.street_intensity)(
        (w * lamps.forward).sum(-1), (w * lamps.left).sum(-1), w[..., 2],
        lamps.footprint[:, 0], lamps.footprint[:, 1], lamps.footprint[:, 2])
    e = (intensity * (d[..., 2] / r) / r ** 2).sum(1)
    assert 13.0 <= e.mean() <= 18.0 and e.min() / e.mean() >= 0.4, (e.mean(), e.min())
    # Placement: a pure function of the layout, 30 m apart along each kerb, 9 m up over the road.
    assert np.array_equal(lamps.pos, night.street_lights(grid).pos)
    assert np.all(lamps.pos[:, 2] == night.LAMP_HEIGHT)


@pytest.mark.parametrize("value,bins", [(60, 1.0), (120, 1.0), (40, 16.0)])
def test_noise_has_the_models_variance_on_a_flat_grey_patch(value, bins):
    """Shot noise (Poisson on the patch's electrons) plus read noise, through the gain, the 12-bit
    ADC and the sRGB curve: the 8-bit variance is (dT/dx)^2 (mu_e + b sigma_d^2) / n_fs^2 plus the
    two quantisations, within 10%, and the mean stays the patch's value within a level."""
    patch = np.full((200, 200, 3), value, np.uint8)
    out = night_sensor.add_noise(patch, bins, np.random.default_rng(3)).astype(np.float64)
    x = _srgb_to_linear(value)
    n_fs = bins * SENSOR.full_well / SENSOR.max_gain                   # electrons at full scale
    var_x = (x * n_fs + bins * SENSOR.read_noise ** 2) / n_fs ** 2 + 1 / (12 * 4095.0 ** 2)
    slope = 255.0 * 1.055 / 2.4 * x ** (1 / 2.4 - 1)                   # d(8-bit) / d(linear)
    predicted = slope ** 2 * var_x + 1 / 12
    assert predicted > 2.0                                             # the test sees the noise, not the rounding
    assert abs(out.var() / predicted - 1) < 0.10, (out.var(), predicted)
    assert abs(out.mean() - value) < 1.0


def test_noise_is_a_function_of_its_generator_and_leaves_saturation_alone():
    img = np.random.default_rng(0).integers(0, 256, (50, 60, 3), dtype=np.uint8)
    a = night_sensor.add_noise(img, 1.0, np.random.default_rng(5))
    assert np.array_equal(a, night_sensor.add_noise(img, 1.0, np.random.default_rng(5)))
    assert not np.array_equal(a, night_sensor.add_noise(img, 1.0, np.random.default_rng(6)))
    assert np.all(a[img == 255] == 255)


def test_night_off_leaves_the_day_image_byte_for_byte():
    """A night render in between changes nothing of the day's: the renderer's day shading keeps no
    state from it (and the sun's shadows are back)."""
    world = _stand_in_world(_box((80.0, 80.0, 0.02), (0.0, 0.0, -0.01)), _box((2.0, 2.0, 2.0), (0.0, 0.0, 1.0)))
    T = _look_at((-7.0, -9.0, 8.0), (1.0, 1.0, 0.0))
    cfg = dataclasses.replace(CameraConfig(), resolution=(W, H))
    r = Renderer(cfg)
    try:
        r.set_world(world, key="day-night-day")
        cam = types.SimpleNamespace(K=K, resolution=(W, H))
        day = r.render(cam, T, {})
        dark = r.render(cam, T, {}, night=_lights((0.0, 0.0, 9.0), night.STREET, footprint=(12.0, 12.0, 12.0)))
        again = r.render(cam, T, {})
    finally:
        r.close()
    assert not np.array_equal(day[0], dark[0])
    for a, b in zip(day, again):
        assert np.array_equal(a, b)
    assert np.array_equal(day[2], dark[2])                                # the ids are the geometry's


def test_lit_vehicles_have_lamps_at_their_front_and_glowing_lenses():
    """In a tiny world: the ego and every unparked vehicle have their lights on, a car two head
    lamps at its front, symmetric about its axis, within its height; parked ones none. Lenses
    glow only on lit actors: head lamps white, tail lamps red."""
    from simgen.pipeline import build_world
    from simgen.settings import MakeSettings
    from simgen.parts import HEADLIGHT, TAILLIGHT
    s = MakeSettings(load_preset("tiny"), 1, 7, 1, "v1.0-sim")
    world = build_world(s, 0)
    scene = night.night_scene(world, Grid(s.cfg.layout))
    on = night.lights_on(world)
    assert on[0] and not any(on[i] for i, a in enumerate(world.actors) if a.parked)
    cars = [i for i, a in enumerate(world.actors) if a.cls == "car" and on[i]]
    assert cars
    for i in cars:
        lamps = scene.lamp_box[scene.lamp_actor == i]
        l, w, h = world.actors[i].size
        assert len(lamps) == 2 and np.allclose(lamps[:, 0], l / 2 + night.HEAD_AHEAD, atol=0.03)
        assert np.isclose(lamps[0, 1], -lamps[1, 1]) and abs(lamps[0, 1]) < w / 2
        lift = h / 2 if i == 0 else 0.0                                  # the ego's pose is on the ground
        assert np.all(np.abs(lamps[:, 2] - lift) < h / 2)
    colours = np.array([HEADLIGHT, TAILLIGHT, TAILLIGHT, (90, 90, 90)], np.uint8)
    owner = np.array([cars[-1], cars[-1], 999, cars[-1]])
    emit = night.emission(colours, owner, scene.lit_ids)
    assert emit[0].min() > 1e3 and emit[1, 0] > 50 * emit[1, 1:].max() and not emit[2:].any()


def test_labels_and_dense_labels_are_the_days_at_night():
    """One tiny scene by day and by night: every file but the camera images is the same bytes
    (the lidar, its lidarseg labels, the dense depth and class images), and so is every table row
    but the scene's description, which records the night."""
    from simgen.pipeline import scene_records
    from simgen.settings import MakeSettings
    cfg = load_preset("tiny")
    recs = [scene_records(MakeSettings(with_weather(cfg, night=n), 1, 7, 1, "v1.0-sim", dense_labels=True), 0)
            for n in (False, True)]
    day, dark = (r.files for r in recs)
    assert day.keys() == dark.keys()
    cams = [k for k in day if k.startswith("samples/CAM_")]
    assert len(cams) == 6 and all(day[k] != dark[k] for k in cams)
    assert all(day[k] == dark[k] for k in day if k not in cams)
    assert any("LIDAR_TOP" in k for k in day) and any(k.startswith("dense/") for k in day)
    for table, rows in recs[0].tables.items():
        if table != "scene":
            assert rows == recs[1].tables[table], table
    assert "night" in recs[1].tables["scene"][0]["description"]
