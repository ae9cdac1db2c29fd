"""Cast shadows in the pyrender cameras: where the geometry puts them, from the sun Mitsuba uses,
in the rgb only, and switched by the preset."""
from __future__ import annotations

import dataclasses
import importlib.util
import types

import cv2
import numpy as np
import pytest
import trimesh

from simgen.camera import Renderer
from simgen.config import CameraConfig, ConfigError, load_preset
from simgen.mitsuba_camera import sun_and_sky
from simgen.sun import sun_direction

W, H = 640, 480
K = np.array([[500.0, 0.0, 317.3], [0.0, 500.0, 243.9], [0.0, 0.0, 1.0]])
BOX = 2.0                                  # metres: a cube standing on the plane at the origin
SUN = {"sun_azimuth": 2.3, "sun_elevation": 0.7}
PLANE_ALBEDO, BOX_ALBEDO = (150, 150, 150), (200, 60, 40)


def box_on_plane(meta: dict):
    """A stand-in world: a 60 m grey plane at z = 0 and a red cube on it, no actors."""
    plane = trimesh.creation.box(extents=(60.0, 60.0, 0.02))
    plane.apply_translation((0.0, 0.0, -0.01))
    plane.visual.face_colors = (*PLANE_ALBEDO, 255)
    box = trimesh.creation.box(extents=(BOX, BOX, BOX))
    box.apply_translation((0.0, 0.0, BOX / 2))
    box.visual.face_colors = (*BOX_ALBEDO, 255)
    return types.SimpleNamespace(static_mesh=trimesh.util.concatenate([plane, box]), actors=[], meta=dict(meta),
                                 speed=np.zeros((0, 2)), yaw=np.zeros(0), boxes_at=lambda t: np.zeros((0, 7)))


def look_at(eye, target) -> np.ndarray:
    """(4, 4) T_global_from_cam of a camera at ``eye`` looking at ``target`` (nuScenes camera axes:
    x right, y down, z forward)."""
    z = np.subtract(target, eye) / np.linalg.norm(np.subtract(target, eye))
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, np.cross(z, x), z], 1)
    T[:3, 3] = eye
    return T


def render(meta: dict, shadows: bool, eye=(-7.0, -9.0, 8.0)):
    cfg = dataclasses.replace(CameraConfig(), resolution=(W, H), shadows=shadows)
    r = Renderer(cfg)
    try:
        r.set_world(box_on_plane(meta), key=("shadow-test", shadows))
        cam = types.SimpleNamespace(K=K, resolution=(W, H))
        T_global_from_cam = look_at(np.array(eye), (1.0, 1.0, 0.0))
        return (*r.render(cam, T_global_from_cam, {}), T_global_from_cam)
    finally:
        r.close()


def analytic_shadow(meta: dict, T_global_from_cam: np.ndarray) -> np.ndarray:
    """(H, W) bool: the pixels whose centre lies in the box's shadow on the plane, the convex hull
    of its footprint and its top corners moved along -sun down to z = 0."""
    sun = sun_direction(meta)
    c = BOX / 2 * np.array([[-1, -1], [-1, 1], [1, 1], [1, -1]], float)
    top = np.c_[c, np.full(4, BOX)]
    ground = np.r_[np.c_[c, np.zeros(4)], top - (BOX / sun[2]) * sun]
    p_cam = (ground - T_global_from_cam[:3, 3]) @ T_global_from_cam[:3, :3]
    uv = (p_cam @ K.T)[:, :2] / p_cam[:, 2:]
    hull = cv2.convexHull(np.round((uv - 0.5) * 16).astype(np.int32))      # pixel centres, 1/16 px
    mask = np.zeros((H, W), np.uint8)
    cv2.fillPoly(mask, [hull], 1, lineType=cv2.LINE_8, shift=4)
    return mask.astype(bool)


def test_box_shadow_falls_where_the_geometry_puts_it():
    rgb_on, depth_on, ids_on, T = render(SUN, shadows=True)
    rgb_off, depth_off, ids_off, _ = render(SUN, shadows=False)
    plane = np.all(rgb_off == rgb_off[H - 1, W // 2], axis=-1)           # the lit plane's colour
    assert plane.mean() > 0.5
    dark = plane & np.any(rgb_on != rgb_off, axis=-1)
    expected = plane & analytic_shadow(SUN, T)
    assert expected.sum() > 2000                                           # the shadow is in view
    assert (dark & expected).sum() / (dark | expected).sum() >= 0.8
    # A shadowed pixel keeps the ambient share of the shading: albedo * ambient.
    ambient = np.floor(np.array(PLANE_ALBEDO) * CameraConfig().ambient).astype(np.uint8)
    assert np.all(rgb_on[dark] == ambient)


def test_shadows_change_the_rgb_only():
    rgb_on, depth_on, ids_on, _ = render(SUN, shadows=True)
    rgb_off, depth_off, ids_off, _ = render(SUN, shadows=False)
    np.testing.assert_array_equal(ids_on, ids_off)
    np.testing.assert_array_equal(depth_on, depth_off)
    changed = np.any(rgb_on != rgb_off, axis=-1)
    assert changed.any() and np.all(rgb_on[changed] <= rgb_off[changed])   # only ever darker


def test_the_shadow_turns_with_the_sun():
    """Opposite suns, opposite shadows: the test above is not passing by luck of one layout."""
    other = {**SUN, "sun_azimuth": SUN["sun_azimuth"] + np.pi}
    rgb_on, _, _, T = render(other, shadows=True)
    rgb_off, _, _, _ = render(other, shadows=False)
    plane = np.all(rgb_off == rgb_off[H - 1, W // 2], axis=-1)
    dark = plane & np.any(rgb_on != rgb_off, axis=-1)
    expected = plane & analytic_shadow(other, T)
    assert expected.sum() > 500
    assert (dark & expected).sum() / (dark | expected).sum() >= 0.8
    assert (dark & analytic_shadow(SUN, T)).sum() < 0.05 * dark.sum()


def test_mitsuba_shines_along_the_same_sun():
    cfg = CameraConfig()
    sun = sun_direction(SUN)
    np.testing.assert_array_equal(sun_and_sky(SUN, cfg)["sun"]["direction"], -sun)
    np.testing.assert_allclose(sun, [np.cos(0.7) * np.cos(2.3), np.cos(0.7) * np.sin(2.3), np.sin(0.7)])


@pytest.mark.skipif(importlib.util.find_spec("mitsuba") is None, reason="mitsuba is not installed")
def test_mitsuba_shadow_is_the_pyrender_shadow():
    from simgen.mitsuba_camera import MitsubaRenderer
    rgb_on, _, _, T = render(SUN, shadows=True)
    rgb_off, _, _, _ = render(SUN, shadows=False)
    plane = np.all(rgb_off == rgb_off[H - 1, W // 2], axis=-1)
    dark_gl = plane & np.any(rgb_on != rgb_off, axis=-1)
    cfg = dataclasses.replace(CameraConfig(), resolution=(W, H))
    mi = MitsubaRenderer(cfg, spp=8)
    try:
        rgb_mi, _ = mi.render(box_on_plane(SUN), types.SimpleNamespace(K=K, resolution=(W, H)), T, {},
                              with_ids=False)
    finally:
        mi.close()
    # Mitsuba's shadow holds the sky's light only (about 0.6 of the lit plane's level here); its
    # sampling noise is averaged over 5x5 pixels, then split halfway between the two levels.
    lum = cv2.blur(rgb_mi.astype(np.float32).mean(-1), (5, 5))
    dark_mi = plane & (lum < 0.75 * np.median(lum[plane & ~dark_gl]))
    assert (dark_mi & dark_gl).sum() / (dark_mi | dark_gl).sum() >= 0.8


def test_preset_switch(tmp_path):
    assert load_preset("urban").camera.shadows is True
    assert load_preset("tiny").camera.shadows is True
    off = tmp_path / "off.yaml"
    off.write_text("camera:\n  shadows: false\n")
    assert load_preset(str(off)).camera.shadows is False
    bad = tmp_path / "bad.yaml"
    bad.write_text("camera:\n  shadows: 1\n")
    with pytest.raises(ConfigError, match=r"camera\.shadows: expected true or false, got 1"):
        load_preset(str(bad))
