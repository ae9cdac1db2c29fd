"""The Mitsuba cameras agree with the pyrender cameras geometrically, and plug into `make`."""
from __future__ import annotations

import pytest
from conftest import run_simgen

from simgen import rig
from simgen.camera import Renderer
from simgen.config import load_preset, with_resolution
from simgen.mitsuba_camera import MitsubaRenderer, actor_poses_at
from simgen.pipeline import MakeSettings, build_world


@pytest.mark.parametrize("channel", ["CAM_FRONT", "CAM_BACK_LEFT"])
def test_silhouettes_match_pyrender(channel):
    cfg = with_resolution(load_preset("tiny"), 800, 450)
    world = build_world(MakeSettings(cfg, 1, 7, 2, "v1.0-sim"), 0)
    cam = next(c for c in rig.cameras(cfg.camera.resolution) if c.channel == channel)
    t = 0.5
    T_global_from_cam = world.ego_pose(t) @ cam.T_ego_from_cam
    poses = actor_poses_at(world, t)
    gl = Renderer(cfg.camera, None)
    gl.set_world(world, key=("mitsuba-test", channel))
    _, _, ids_gl = gl.render(cam, T_global_from_cam, poses)
    mi = MitsubaRenderer(cfg.camera, spp=1)
    try:
        rgb, ids_mi = mi.render(world, cam, T_global_from_cam, poses)
    finally:
        mi.close()
    a, b = ids_gl > 0, ids_mi > 0
    assert a.sum() > 2000                                     # actors are in view
    assert (a & b).sum() / (a | b).sum() >= 0.95               # silhouettes (all actors)
    assert (ids_gl == ids_mi)[a | b].mean() >= 0.95            # and the same actor per pixel
    assert rgb.shape == (450, 800, 3) and rgb.mean() > 30


def test_make_with_mitsuba(tmp_path):
    out = tmp_path / "mi"
    run_simgen("make", "--out", out, "--workers", "1", "--preset", "tiny", "--scenes", "1", "--samples-per-scene",
               "1", "--seed", "7", "--resolution", "160x90", "--renderer", "mitsuba", "--spp", "2", "--quiet")
    import cv2
    img = cv2.imread(str(next((out / "samples" / "CAM_FRONT").glob("*.jpg"))))
    assert img.shape == (90, 160, 3) and 30 < img.mean() < 250
