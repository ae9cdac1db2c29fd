"""The Mitsuba cameras agree with the pyrender cameras geometrically, and plug into `make`."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import run_simgen

from simgen import rig
from simgen.camera import Renderer
from simgen.config import load_preset, with_resolution
from simgen.mitsuba_camera import MitsubaRenderer, actor_poses_at
from simgen.pipeline import MakeSettings, build_world

ROOT = Path(__file__).resolve().parents[2]


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


def test_render_has_no_nan_sample():
    """The urban world (seed 3) holds 66 m x 1 cm sliver faces, on which vertex colours came out
    NaN (black pixels); the face colours give every sample a finite value."""
    cfg = with_resolution(load_preset("urban"), 320, 180)
    world = build_world(MakeSettings(cfg, 1, 3, 1, "v1.0-sim"), 0)
    cam = rig.cameras(cfg.camera.resolution)[0]
    r = MitsubaRenderer(cfg.camera, spp=4)
    try:
        rgb, _ = r.render(world, cam, world.ego_pose(0.5) @ cam.T_ego_from_cam, actor_poses_at(world, 0.5),
                          with_ids=False)
    finally:
        r.close()
    assert np.isfinite(r.last_linear).all()
    # A black pixel is a dark one (the shade under a car), never a NaN turned black.
    np.testing.assert_array_equal(rgb.max(-1) == 0, r.last_linear.max(-1) < (0.5 / 255) ** 2.2)


def test_mitsuba_log_goes_to_stderr(capfd):
    cfg = with_resolution(load_preset("tiny"), 160, 90)
    r = MitsubaRenderer(cfg.camera, spp=1)
    r.mi.Log(r.mi.LogLevel.Warn, "fog-probe")
    r.close()
    out, err = capfd.readouterr()
    assert "fog-probe" in err and out == ""


@pytest.mark.slow
def test_bench_json_parses_with_mitsuba():
    """`scripts/bench.py --json` prints one JSON object on stdout, Mitsuba's log aside."""
    proc = subprocess.run([sys.executable, "scripts/bench.py", "--json", "--quick", "--only", "mitsuba", "fog"],
                          cwd=ROOT, capture_output=True, text=True, check=True)
    result = json.loads(proc.stdout)
    assert result["mitsuba_s_per_image_800x450"] > 0 and result["lidar_fog_silent_rays_by_severity"] == [0] * 6
