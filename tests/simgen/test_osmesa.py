"""The OSMesa fallback renders what EGL renders: one Renderer gives the same rgb, depth and face
ids on both platforms, and `simgen make --gl osmesa` the same dataset bytes (labels, lidar and
images) as EGL with the same seed.

PyOpenGL binds its platform when it is first imported, so each platform renders in a process of
its own. Byte identity holds where both platforms reach the same rasteriser (Mesa's llvmpipe on
a machine without a GPU driver); where they do not, the comparison is skipped and says why.
"""
from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]
ACTOR_ID = 7

# One Renderer in a fresh process: a grey plane, a static box and a moving box (actor 7) in the
# sun, rendered with the sun's shadows and without; argv: platform, output .npz. Prints what the
# platform was (its class, whether simgen patched it, the GL renderer string) as one JSON line.
RENDER = r"""
import dataclasses, json, sys, types
import numpy as np, trimesh
from simgen.camera import Renderer
from simgen.config import CameraConfig

platform, out = sys.argv[1], sys.argv[2]
W, H = 320, 240
K = np.array([[250.0, 0.0, 158.7], [0.0, 250.0, 121.9], [0.0, 0.0, 1.0]])

def coloured_box(extents, centre, rgb):
    m = trimesh.creation.box(extents=extents)
    m.apply_translation(centre)
    m.visual.face_colors = (*rgb, 255)
    return m

static = trimesh.util.concatenate([coloured_box((60.0, 60.0, 0.02), (0.0, 0.0, -0.01), (150, 150, 150)),
                                   coloured_box((2.0, 2.0, 2.0), (0.0, 0.0, 1.0), (200, 60, 40))])
actor = types.SimpleNamespace(id=ACTOR_ID, annotate=True, size=np.array([4.0, 1.8, 1.5]),
                              mesh=coloured_box((4.0, 1.8, 1.5), (0.0, 0.0, 0.0), (40, 90, 200)))
box = np.array([[4.0, -3.0, 0.75, 4.0, 1.8, 1.5, 0.4]])          # x, y, z, l, w, h, yaw
world = types.SimpleNamespace(static_mesh=static, actors=[actor], meta={"sun_azimuth": 2.3, "sun_elevation": 0.7},
                              speed=np.ones((1, 2)), yaw=np.full((1, 2), 0.4), boxes_at=lambda t: box)
T_global_from_box = np.eye(4)
T_global_from_box[:2, :2] = [[np.cos(0.4), -np.sin(0.4)], [np.sin(0.4), np.cos(0.4)]]
T_global_from_box[:3, 3] = box[0, :3]
eye, target = np.array([-7.0, -9.0, 8.0]), np.array([1.0, 1.0, 0.0])
z = (target - eye) / np.linalg.norm(target - eye)
x = np.cross(z, [0.0, 0.0, 1.0]); x /= np.linalg.norm(x)
T_global_from_cam = np.eye(4)
T_global_from_cam[:3, :3] = np.stack([x, np.cross(z, x), z], 1)
T_global_from_cam[:3, 3] = eye

cfg = dataclasses.replace(CameraConfig(), resolution=(W, H), shadows=True)
r = Renderer(cfg, platform)
r.set_world(world, key="osmesa-test")
cam = types.SimpleNamespace(K=K, resolution=(W, H))
images = {}
for shadows in (True, False):
    r.cfg = dataclasses.replace(cfg, shadows=shadows)
    rgb, depth, ids = r.render(cam, T_global_from_cam, {ACTOR_ID: T_global_from_box}, lazy_ids=True)
    images.update({f"rgb_{shadows}": rgb, f"depth_{shadows}": depth, f"face_{shadows}": ids.face,
                   f"ids_{shadows}": np.asarray(ids)})
np.savez(out, **images)
from OpenGL.GL import GL_RENDERER, glGetString
r._gl._platform.make_current()
# Renderers beside it, one closed and one collected, leave it working (EGL shares one display).
others = [Renderer(cfg, platform) for _ in range(2)]
others.pop().close()
del others
import gc; gc.collect()
r.cfg = cfg
again = r.render(cam, T_global_from_cam, {ACTOR_ID: T_global_from_box}, lazy_ids=True)[0]
print(json.dumps({"platform": type(r._gl._platform).__name__, "same_after_others": bool((again == images["rgb_True"]).all()),
                  "patched": "supports_framebuffers" in vars(r._gl._platform),
                  "gl_renderer": glGetString(GL_RENDERER).decode()}))
r.close()
""".replace("ACTOR_ID", str(ACTOR_ID))

# The label tables, checked to be there and not empty; every file of the dataset is compared.
LABEL_TABLES = ("sample_annotation.json", "instance.json", "sample.json", "ego_pose.json")
MAKE_ARGS = ["--preset", "tiny", "--scenes", "1", "--samples-per-scene", "2", "--seed", "5", "--workers", "1",
             "--quiet"]


def _env(platform: str) -> dict[str, str]:
    return {**os.environ, "PYOPENGL_PLATFORM": platform, "OMP_NUM_THREADS": "1"}


@pytest.fixture(scope="module")
def renders(tmp_path_factory) -> dict[str, tuple[dict, dict[str, np.ndarray]]]:
    """platform -> (what the process says its platform was, the saved images)."""
    out = {}
    for platform in ("egl", "osmesa"):
        path = tmp_path_factory.mktemp(platform) / "render.npz"
        proc = subprocess.run([sys.executable, "-c", RENDER, platform, str(path)], capture_output=True, text=True,
                              cwd=ROOT, env=_env(platform), timeout=300)
        assert proc.returncode == 0, f"{platform} render failed:\n{proc.stderr}"
        with np.load(path) as saved:
            out[platform] = json.loads(proc.stdout.strip().splitlines()[-1]), dict(saved)
    return out


def _same_rasteriser(renders) -> None:
    egl, osmesa = renders["egl"][0]["gl_renderer"], renders["osmesa"][0]["gl_renderer"]
    if egl != osmesa:
        pytest.skip(f"EGL renders on {egl!r}, OSMesa on {osmesa!r}: byte identity is a property of one rasteriser")


def test_each_platform_is_the_one_asked_for(renders):
    """The OSMesa process really ran on OSMesa, and only its platform object was told it has
    framebuffers (EGL's are used as they are)."""
    assert renders["egl"][0]["platform"] == "EGLPlatform" and renders["egl"][0]["patched"] is False
    assert renders["osmesa"][0]["platform"] == "OSMesaPlatform" and renders["osmesa"][0]["patched"] is True


@pytest.mark.parametrize("platform", ["egl", "osmesa"])
def test_a_renderer_outlives_others_closed_or_collected(renders, platform):
    """Two more renderers made beside one, one closed and one garbage-collected: the first still
    renders, the same bytes as before, and closes (on EGL pyrender's close terminated the shared
    display under it: EGL_BAD_DISPLAY)."""
    assert renders[platform][0]["same_after_others"] is True


def test_one_render_gives_the_same_bytes_on_osmesa_and_egl(renders):
    _same_rasteriser(renders)
    egl, osmesa = renders["egl"][1], renders["osmesa"][1]
    assert egl.keys() == osmesa.keys()
    # The scene is not trivial: the actor is seen, many faces are, and the sun's shadows change
    # the rgb (so the shadow pass, with its own depth read, ran on both platforms).
    assert set(np.unique(egl["ids_True"])) == {0, ACTOR_ID}
    assert len(np.unique(egl["face_True"])) > 8
    assert (egl["depth_True"] > 0).mean() > 0.5
    for images in (egl, osmesa):
        assert np.any(images["rgb_True"] != images["rgb_False"])
    for key in egl:
        assert egl[key].dtype == osmesa[key].dtype and egl[key].shape == osmesa[key].shape, key
        np.testing.assert_array_equal(osmesa[key], egl[key], err_msg=key)


def _file_hashes(root: Path) -> dict[str, str]:
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


def _image_difference(a: Path, b: Path) -> str:
    """Mean and largest absolute difference (levels) of two jpg images, and the share of pixels
    whose channels all differ by 2 levels or less."""
    d = np.abs(cv2.imread(str(a)).astype(np.int16) - cv2.imread(str(b)).astype(np.int16))
    return f"mean {d.mean():.4f}, max {d.max()}, within 2 levels {(d.max(-1) <= 2).mean():.5f}"


def test_make_on_osmesa_gives_the_egl_dataset(renders, tmp_path):
    """`simgen make --gl osmesa` and `--gl egl` with one seed: every file byte-identical, the label
    tables and lidar files included (a mismatch lists each file, with the pixel statistics of a
    differing image)."""
    _same_rasteriser(renders)
    roots = {}
    for platform in ("egl", "osmesa"):
        roots[platform] = tmp_path / platform
        proc = subprocess.run([sys.executable, "-m", "simgen.cli", "make", "--out", str(roots[platform]),
                               "--gl", platform, *MAKE_ARGS], capture_output=True, text=True, cwd=ROOT,
                              env=_env(platform), timeout=300)
        assert proc.returncode == 0, f"simgen make --gl {platform} failed:\n{proc.stderr}"
    egl, osmesa = _file_hashes(roots["egl"]), _file_hashes(roots["osmesa"])
    assert egl.keys() == osmesa.keys()
    tables = roots["egl"] / "v1.0-sim"
    assert all(json.loads((tables / name).read_text()) for name in LABEL_TABLES)
    assert sum(name.endswith(".pcd.bin") for name in egl) >= 2 and sum(name.endswith(".jpg") for name in egl) == 12
    differ = [name + (f" ({_image_difference(roots['egl'] / name, roots['osmesa'] / name)})"
                      if name.endswith(".jpg") else "")
              for name in egl if egl[name] != osmesa[name]]
    assert not differ, "files that differ:\n" + "\n".join(differ)
