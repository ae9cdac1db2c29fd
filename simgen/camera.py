"""Offscreen camera rendering with pyrender: rgb, metric depth and a per-pixel actor id.

This is the only module that knows OpenGL camera axes (x right, y up, looking along -z). Every
other module uses the nuScenes camera frame (x right, y down, z forward); the conversion is
``T_gl_from_cv`` below.

The platform is EGL by default and OSMesa as the fallback (``--gl osmesa`` or the environment
variable ``PYOPENGL_PLATFORM=osmesa``); it must be chosen before OpenGL is imported, so pyrender
is imported lazily. One :class:`Renderer` per process is reused across frames and scenes:
re-creating OffscreenRenderer leaks EGL contexts.
"""
from __future__ import annotations

import os

import numpy as np

from .config import CameraConfig
from .rig import Camera
from .world import World

# OpenGL camera from the nuScenes (OpenCV) camera frame: flip y and z.
T_CV_FROM_GL = np.diag([1.0, -1.0, -1.0, 1.0])
SKY = (0.62, 0.74, 0.88)
GL_PLATFORMS = ("egl", "osmesa")


def select_platform(platform: str | None) -> str:
    """Choose the OpenGL platform before anything imports OpenGL."""
    chosen = platform or os.environ.get("PYOPENGL_PLATFORM") or "egl"
    if chosen not in GL_PLATFORMS:
        raise ValueError(f"unknown GL platform {chosen!r} (allowed: {', '.join(GL_PLATFORMS)})")
    os.environ["PYOPENGL_PLATFORM"] = chosen
    return chosen


def encode_ids(ids: np.ndarray) -> np.ndarray:
    """(n,) non-negative int ids -> (n, 3) uint8 colours for the segmentation pass."""
    ids = np.asarray(ids, dtype=np.int64)
    return np.stack([ids & 255, (ids >> 8) & 255, (ids >> 16) & 255], -1).astype(np.uint8)


def decode_ids(rgb: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8 segmentation image -> (H, W) int32 ids."""
    rgb = rgb.astype(np.int32)
    return rgb[..., 0] | (rgb[..., 1] << 8) | (rgb[..., 2] << 16)


class Renderer:
    """Holds one OffscreenRenderer and the pyrender scene of the current world."""

    def __init__(self, cfg: CameraConfig, platform: str | None = None):
        select_platform(platform)
        import pyrender  # noqa: deferred on purpose, see the module docstring
        self._pr = pyrender
        self.cfg = cfg
        self.width, self.height = cfg.resolution
        self._gl = pyrender.OffscreenRenderer(self.width, self.height)
        self.scene = None
        self._world_key = None

    def close(self):
        if self._gl is not None:
            self._gl.delete()
            self._gl = None

    def set_world(self, world: World, key) -> None:
        """Build the pyrender scene for ``world`` (skipped when ``key`` is unchanged)."""
        if key == self._world_key:
            return
        pr = self._pr
        scene = pr.Scene(ambient_light=np.full(3, self.cfg.ambient), bg_color=(*SKY, 1.0))
        self.static_node = scene.add(pr.Mesh.from_trimesh(world.static_mesh, smooth=False))
        self.actor_nodes = {}
        for a in world.actors:
            if a.annotate:  # the ego is not rendered: no returns or pixels from the own car
                self.actor_nodes[a.id] = scene.add(pr.Mesh.from_trimesh(a.mesh, smooth=False))
        sun_az = float(world.meta.get("sun_azimuth", 0.8))
        sun_el = float(world.meta.get("sun_elevation", 0.9))
        d = np.array([np.cos(sun_el) * np.cos(sun_az), np.cos(sun_el) * np.sin(sun_az), np.sin(sun_el)])
        scene.add(pr.DirectionalLight(color=np.ones(3), intensity=self.cfg.sun_intensity), pose=_look_along(-d))
        self.cam_node = scene.add(pr.IntrinsicsCamera(1, 1, 0, 0, znear=0.1, zfar=self.cfg.zfar))
        self.seg_map = {self.static_node: (0, 0, 0)}
        for aid, node in self.actor_nodes.items():
            self.seg_map[node] = tuple(int(c) for c in encode_ids([aid])[0])
        self.scene = scene
        self._world_key = key

    def render(self, cam: Camera, T_global_from_cam: np.ndarray, actor_poses: dict[int, np.ndarray]):
        """Render one camera.

        Parameters
        ----------
        cam : the camera (intrinsics for this renderer's resolution).
        T_global_from_cam : (4, 4) camera pose, nuScenes camera frame.
        actor_poses : actor id -> (4, 4) T_global_from_box at this camera's time.

        Returns
        -------
        rgb : (H, W, 3) uint8.  depth : (H, W) float32 camera-frame z (m), 0 where nothing was hit.
        ids : (H, W) int32 actor id per pixel, 0 for the static world and the sky.
        """
        pr = self._pr
        K = cam.K
        self.cam_node.camera = pr.IntrinsicsCamera(K[0, 0], K[1, 1], K[0, 2], K[1, 2], znear=0.1, zfar=self.cfg.zfar)
        self.scene.set_pose(self.cam_node, T_global_from_cam @ T_CV_FROM_GL)
        for aid, node in self.actor_nodes.items():
            self.scene.set_pose(node, actor_poses[aid])
        rgb, depth = self._gl.render(self.scene)
        seg, _ = self._gl.render(self.scene, flags=pr.RenderFlags.SEG, seg_node_map=self.seg_map)
        return np.ascontiguousarray(rgb[..., :3]), depth.astype(np.float32), decode_ids(seg)


def _look_along(direction: np.ndarray) -> np.ndarray:
    """A pose whose -z axis points along ``direction`` (pyrender lights shine along -z)."""
    z = -direction / np.linalg.norm(direction)
    x = np.cross([0.0, 0.0, 1.0], z)
    x = x / np.linalg.norm(x) if np.linalg.norm(x) > 1e-6 else np.array([1.0, 0.0, 0.0])
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, y, z], 1)
    return T


def depth_to_range(depth: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(H, W) camera-frame z -> (H, W) range along each pixel's ray (m); 0 stays 0."""
    H, W = depth.shape
    u = (np.arange(W) + 0.5 - K[0, 2]) / K[0, 0]
    v = (np.arange(H) + 0.5 - K[1, 2]) / K[1, 1]
    return depth * np.sqrt(1.0 + u[None, :] ** 2 + v[:, None] ** 2)
