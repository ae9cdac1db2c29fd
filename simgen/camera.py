"""Offscreen camera rendering with pyrender: rgb, metric depth and a per-pixel actor id.

This is the only module that knows OpenGL camera axes (x right, y up, looking along -z). Every
other module uses the nuScenes camera frame (x right, y down, z forward); the conversion is
``T_gl_from_cv`` below.

Shading is Lambertian (ambient plus a sun), evaluated per face on the CPU and baked into the
face colours; the GPU pass is then pyrender's unlit FLAT pass. On a software rasteriser
(llvmpipe) this is several times faster than pyrender's PBR shader and shows shape just as well.
Actors whose bounding sphere is outside a camera's view are not drawn.

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
        sun_az = float(world.meta.get("sun_azimuth", 0.8))
        sun_el = float(world.meta.get("sun_elevation", 0.9))
        sun = np.array([np.cos(sun_el) * np.cos(sun_az), np.cos(sun_el) * np.sin(sun_az), np.sin(sun_el)])
        scene = pr.Scene(ambient_light=np.zeros(3), bg_color=(*SKY, 1.0))
        self.static_node = scene.add(pr.Mesh.from_trimesh(self._shaded(world.static_mesh, sun), smooth=False))
        self.actor_nodes, radius = {}, {}
        for a, yaw in zip(world.actors, world.yaw):
            if a.annotate:  # the ego is not rendered: no returns or pixels from the own car
                c, s = np.cos(yaw), np.sin(yaw)
                sun_box = np.array([c * sun[0] + s * sun[1], -s * sun[0] + c * sun[1], sun[2]])  # yaw is constant
                self.actor_nodes[a.id] = scene.add(pr.Mesh.from_trimesh(self._shaded(a.mesh, sun_box), smooth=False))
                radius[a.id] = float(np.linalg.norm(a.size)) / 2
        self.radius = radius
        self.cam_node = scene.add(pr.IntrinsicsCamera(1, 1, 0, 0, znear=0.1, zfar=self.cfg.zfar))
        self.seg_map = {self.static_node: (0, 0, 0)}
        for aid, node in self.actor_nodes.items():
            self.seg_map[node] = tuple(int(c) for c in encode_ids([aid])[0])
        self.scene = scene
        self._world_key = key

    def _shaded(self, mesh, sun: np.ndarray):
        """A copy of ``mesh`` whose face colours carry ambient + sun * max(0, n . sun)."""
        import trimesh
        normals = np.asarray(mesh.face_normals)
        light = self.cfg.ambient + self.cfg.sun_intensity / 5.0 * np.clip(normals @ sun, 0.0, None)
        albedo = np.asarray(mesh.visual.face_colors, np.float64)
        colors = albedo.copy()
        colors[:, :3] = np.clip(albedo[:, :3] * light[:, None], 0, 255)
        out = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
        out.visual.face_colors = colors.astype(np.uint8)
        return out

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
        ids = list(self.actor_nodes)
        centres = np.array([actor_poses[i][:3, 3] for i in ids]).reshape(-1, 3)
        visible = self._in_view(cam, T_global_from_cam, centres, np.array([self.radius[i] for i in ids]))
        for aid, vis in zip(ids, visible):
            node = self.actor_nodes[aid]
            node.mesh.is_visible = bool(vis)
            if vis:
                self.scene.set_pose(node, actor_poses[aid])
        rgb, depth = self._gl.render(self.scene, flags=pr.RenderFlags.FLAT)
        seg, _ = self._gl.render(self.scene, flags=pr.RenderFlags.SEG, seg_node_map=self.seg_map)
        return np.ascontiguousarray(rgb[..., :3]), depth.astype(np.float32), decode_ids(seg)

    def _in_view(self, cam: Camera, T_global_from_cam, centres, radius) -> np.ndarray:
        """Whether each bounding sphere may touch the view frustum (conservative)."""
        p = (centres - T_global_from_cam[:3, 3]) @ T_global_from_cam[:3, :3]     # camera frame
        W, H = cam.resolution
        K = cam.K
        # Distances to the four side planes of the frustum, through the camera centre.
        planes = []
        for u, v, axis in ((0.0, None, 0), (W, None, 0), (None, 0.0, 1), (None, H, 1)):
            if axis == 0:
                n = np.array([1.0, 0.0, -(u - K[0, 2]) / K[0, 0]])
                n *= 1.0 if u == 0.0 else -1.0
            else:
                n = np.array([0.0, 1.0, -(v - K[1, 2]) / K[1, 1]])
                n *= 1.0 if v == 0.0 else -1.0
            planes.append(n / np.linalg.norm(n))
        inside = (p[:, 2] > -radius) & (p[:, 2] < self.cfg.zfar + radius)
        for n in planes:
            inside &= p @ n > -radius
        return inside


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
