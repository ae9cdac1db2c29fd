"""Offscreen camera rendering with pyrender: rgb, metric depth and a per-pixel actor id.

This is the only module that knows OpenGL camera axes (x right, y up, looking along -z). Every
other module uses the nuScenes camera frame (x right, y down, z forward); the conversion is
``T_gl_from_cv`` below.

Shading is Lambertian (ambient plus a sun), evaluated per face on the CPU; the GPU pass is
pyrender's unlit FLAT pass drawing face indices (see :class:`Renderer`). With ``shadows`` on, a
second, depth-only pass from the sun gives a shadow map, and pixels whose surface the sun cannot
see keep only their face's ambient colour (simgen/sun.py); ids and depth are not affected. On a software
rasteriser (llvmpipe) this is several times faster than pyrender's PBR shader and its separate
segmentation pass, and shows shape just as well.
Actors whose bounding sphere is outside a camera's view are not drawn.

The platform is EGL by default and OSMesa as the fallback (``--gl osmesa`` or the environment
variable ``PYOPENGL_PLATFORM=osmesa``); it must be chosen before OpenGL is imported, so pyrender
is imported lazily. One :class:`Renderer` per process is reused across frames and scenes:
re-creating OffscreenRenderer leaks EGL contexts.
"""
from __future__ import annotations

import functools
import os
import types

import cv2
import numpy as np

from . import geometry, sun as sunlight
from .config import CameraConfig
from .face_meshes import STATIC_TILE, bounding_spheres, coded_mesh, depth_mesh, static_tiles
from .gl_readback import (framebuffers_on_osmesa, read_single_sample_framebuffer, read_window_depth,
                          share_egl_display, single_sample_framebuffers)
from .rig import Camera
from .world import World

# OpenGL camera from the nuScenes (OpenCV) camera frame: flip y and z.
T_CV_FROM_GL = np.diag([1.0, -1.0, -1.0, 1.0])
SKY = (0.62, 0.74, 0.88)
GL_PLATFORMS = ("egl", "osmesa")
CAMERA_ZNEAR = 0.1   # metres
CASTER_MIN_HEIGHT = 0.2   # metres: static faces wholly below this cast no shadow worth drawing


def select_platform(platform: str | None) -> str:
    """Choose the OpenGL platform before anything imports OpenGL."""
    chosen = platform or os.environ.get("PYOPENGL_PLATFORM") or "egl"
    if chosen not in GL_PLATFORMS:
        raise ValueError(f"unknown GL platform {chosen!r} (allowed: {', '.join(GL_PLATFORMS)})")
    os.environ["PYOPENGL_PLATFORM"] = chosen
    return chosen


class Renderer:
    """Holds one OffscreenRenderer and the pyrender scene of the current world.

    One unlit pass per camera draws every face in a colour that encodes its index in the
    world's face table (0 = sky). Looking the indices up gives the shaded rgb image and the
    actor id per pixel at once, both exact: there is no second segmentation pass and no colour
    is ever blended (the framebuffers are single-sample).

    What is drawn per camera: the static world in square tiles of ``STATIC_TILE`` metres and the
    moving actors, each culled by its bounding sphere against the view frustum, drawn near to
    far. (A modest gain: llvmpipe's time goes mostly to filling pixels.) pyrender's own draw
    list (every mesh node, sorted by distance on every frame, then the hidden ones skipped) is
    replaced on this instance by the culled list: opaque, depth-tested geometry needs no sorting.
    """

    def __init__(self, cfg: CameraConfig, platform: str | None = None):
        select_platform(platform)
        import pyrender  # noqa: deferred on purpose, see the module docstring
        import pyrender.renderer
        single_sample_framebuffers(pyrender.renderer)
        self._pr = pyrender
        self.cfg = cfg
        self.width, self.height = cfg.resolution
        self._gl = pyrender.OffscreenRenderer(self.width, self.height)
        gl_renderer = self._gl._renderer
        self._drawn: list = []
        gl_renderer._sorted_mesh_nodes = lambda scene: self._drawn
        framebuffers_on_osmesa(self._gl)      # OSMesa renders and reads back as EGL does
        share_egl_display(self._gl)           # closing one renderer leaves the others working
        self._readers = {d: types.MethodType(functools.partial(read_single_sample_framebuffer, with_depth=d),
                                             gl_renderer) for d in (False, True)}
        self._readers["window"] = types.MethodType(read_window_depth, gl_renderer)
        self.scene = None
        self._world_key = None

    def close(self):
        if self._gl is not None:
            self._gl.delete()
            self._gl = None

    def set_world(self, world: World, key) -> None:
        """Build the pyrender scene and the face tables of ``world`` (skipped when ``key`` is unchanged)."""
        if key == self._world_key:
            return
        pr = self._pr
        sun = self.sun = sunlight.sun_direction(world.meta)
        scene = pr.Scene(ambient_light=np.zeros(3), bg_color=(0.0, 0.0, 0.0, 1.0))   # black = index 0 = sky
        colours, owners = [np.array([[int(255 * c) for c in SKY]], np.uint8)], [np.zeros(1, np.int32)]
        ambient, cos_sun = [colours[0]], [np.zeros(1)]      # the sky is never shadowed
        # Each face's albedo and normal (box frame for a moving actor), kept for the night's shading.
        self._night_faces = [(np.zeros((1, 3), np.uint8), np.zeros((1, 3)))]
        self._night_tables, self.actor_faces = None, {}
        n_faces = 1

        def add(triangles, normals, albedo, sun_local, owner):
            nonlocal n_faces
            self._night_faces.append((albedo, normals))
            colours.append(self._shaded(normals, albedo, sun_local))
            ambient.append(self._shaded(normals, albedo, np.zeros(3)))
            cos_sun.append(normals @ sun_local)
            owners.append(np.broadcast_to(np.asarray(owner, np.int32), (len(triangles),)))
            node = scene.add(coded_mesh(pr, triangles, n_faces))
            n_faces += len(triangles)
            return node

        # Actors that never move join the static world (fewer draw calls); their faces still
        # carry their own ids through the face table.
        moving = world.speed.max(axis=1) > 0
        boxes = world.boxes_at(0.0)
        sm = world.static_mesh
        tris, norms, albedo, owner = ([np.asarray(sm.triangles)], [np.asarray(sm.face_normals)],
                                      [np.asarray(sm.visual.face_colors)[:, :3]], [np.zeros(len(sm.faces), np.int32)])
        for i, a in enumerate(world.actors):
            if a.annotate and not moving[i]:
                T = geometry.pose_2d(boxes[i, 0], boxes[i, 1], boxes[i, 6], boxes[i, 2])
                tris.append(np.asarray(a.mesh.triangles) @ T[:3, :3].T + T[:3, 3])
                norms.append(np.asarray(a.mesh.face_normals) @ T[:3, :3].T)
                albedo.append(np.asarray(a.mesh.visual.face_colors)[:, :3])
                owner.append(np.full(len(a.mesh.faces), a.id, np.int32))
        tris, norms, albedo, owner = (np.concatenate(x) for x in (tris, norms, albedo, owner))
        tiles = static_tiles(tris, STATIC_TILE)
        self.static_nodes = [add(tris[f], norms[f], albedo[f], sun, owner[f]) for f in tiles]
        self.static_centre, self.static_radius = bounding_spheres([tris[f] for f in tiles])
        # The shadow pass draws only what can cast a shadow: the ground, the road and the kerbs
        # shade nothing that stands on them, and leaving them out halves its work.
        casters = tris[tris[:, :, 2].max(axis=1) > CASTER_MIN_HEIGHT]
        caster_tiles = [casters[f] for f in static_tiles(casters, STATIC_TILE)]
        self.caster_nodes = [scene.add(depth_mesh(pr, t)) for t in caster_tiles]
        self.caster_centre, self.caster_radius = bounding_spheres(caster_tiles)
        self.actor_nodes, self.radius, self.turning = {}, {}, {}
        for i, a in enumerate(world.actors):
            # The ego is not rendered (no pixels of the own car); static actors are merged above.
            if a.annotate and moving[i]:
                # Shaded with the sun in the box frame at the start; an actor whose heading
                # changes (it turns) is shaded again for each render (_shade_turning).
                c, s = np.cos(world.yaw[i, 0]), np.sin(world.yaw[i, 0])
                sun_box = np.array([c * sun[0] + s * sun[1], -s * sun[0] + c * sun[1], sun[2]])
                normals, albedo = np.asarray(a.mesh.face_normals), np.asarray(a.mesh.visual.face_colors)[:, :3]
                if np.ptp(world.yaw[i]) > 0:
                    self.turning[a.id] = (n_faces, normals, albedo)
                self.actor_faces[a.id] = (n_faces, normals)
                self.actor_nodes[a.id] = add(np.asarray(a.mesh.triangles), normals, albedo, sun_box, a.id)
                self.radius[a.id] = float(np.linalg.norm(a.size)) / 2
        if n_faces >= 2 ** 24:
            raise ValueError(f"{n_faces} faces do not fit the 24-bit face index of the id pass")
        self.face_rgbx, self.face_ambient_rgbx = _rgbx(np.concatenate(colours)), _rgbx(np.concatenate(ambient))
        self.face_tan = sunlight.slope_tan(np.concatenate(cos_sun))
        self.face_owner = np.concatenate(owners)
        self.cam_node = scene.add(pr.IntrinsicsCamera(1, 1, 0, 0, znear=CAMERA_ZNEAR, zfar=self.cfg.zfar))
        self.scene = scene
        self._world_key = key

    def _shade_turning(self, actor_poses: dict[int, np.ndarray]) -> None:
        """Re-shade the faces of the actors whose heading changes over time with the sun in their
        box frame at this render's poses (actor id -> (4, 4) T_global_from_box)."""
        for aid, (first, normals, albedo) in self.turning.items():
            sun_box = actor_poses[aid][:3, :3].T @ self.sun
            faces = slice(first, first + len(normals))
            self.face_rgbx[faces] = _rgbx(self._shaded(normals, albedo, sun_box))
            self.face_tan[faces] = sunlight.slope_tan(normals @ sun_box)

    def _shaded(self, normals: np.ndarray, albedo: np.ndarray, sun: np.ndarray) -> np.ndarray:
        """(F, 3) uint8 face colours: (F, 3) albedo lit by ambient + sun * max(0, n . sun)."""
        light = self.cfg.ambient + self.cfg.sun_intensity / 5.0 * np.clip(normals @ sun, 0.0, None)
        return np.clip(albedo.astype(np.float64) * light[:, None], 0, 255).astype(np.uint8)

    def render(self, cam: Camera, T_global_from_cam: np.ndarray, actor_poses: dict[int, np.ndarray],
               with_depth: bool = True, lazy_ids: bool = False, night=None):
        """Render one camera.

        Parameters
        ----------
        cam : the camera (intrinsics for this renderer's resolution).
        T_global_from_cam : (4, 4) camera pose, nuScenes camera frame.
        actor_poses : actor id -> (4, 4) T_global_from_box at this camera's time.
        with_depth : return the depth image too (only fog needs it; shadows read it anyway).
        lazy_ids : return the ids as an :class:`IdImage` (looked up where read) instead of an array.
        night : the night's :class:`simgen.weather.night.Lights` at this camera's time, or None by
            day. At night the sun is below the horizon (no sun, no shadow pass) and the image is
            the clean night exposure of the street and vehicle lights (:meth:`_night_rgb`).

        Returns
        -------
        rgb : (H, W, 3) uint8.  depth : (H, W) float32 camera-frame z (m), 0 where nothing was
        hit; None without ``with_depth``.  ids : (H, W) int32 actor id per pixel, 0 for the
        static world and the sky (an :class:`IdImage` with ``lazy_ids``).
        """
        pr = self._pr
        K = cam.K
        self.cam_node.camera = pr.IntrinsicsCamera(K[0, 0], K[1, 1], K[0, 2], K[1, 2], znear=CAMERA_ZNEAR,
                                                   zfar=self.cfg.zfar)
        self.scene.set_pose(self.cam_node, T_global_from_cam @ T_CV_FROM_GL)
        self._shade_turning(actor_poses)
        ids = list(self.actor_nodes)
        centres = np.array([actor_poses[i][:3, 3] for i in ids]).reshape(-1, 3)
        visible = self._in_view(cam, T_global_from_cam, centres, np.array([self.radius[i] for i in ids]))
        # Near to far (actors, then the tiles by distance), so that the depth test rejects more.
        tiles = np.flatnonzero(self._in_view(cam, T_global_from_cam, self.static_centre, self.static_radius))
        tiles = tiles[np.argsort(np.linalg.norm(self.static_centre[tiles] - T_global_from_cam[:3, 3], axis=1),
                                 kind="stable")]
        self._drawn = []
        for aid in np.array(ids)[visible]:
            node = self.actor_nodes[aid]
            self.scene.set_pose(node, actor_poses[aid])
            self._drawn.append(node)
        self._drawn += [self.static_nodes[i] for i in tiles]
        shadows = self.cfg.shadows and night is None
        self._gl._renderer._read_main_framebuffer = self._readers[with_depth or shadows or night is not None]
        coded, depth = self._gl.render(self.scene, flags=pr.RenderFlags.FLAT | pr.RenderFlags.RGBA)
        # RGBA bytes read as one little-endian uint32 per pixel: R | G << 8 | B << 16 | A << 24.
        face = np.ascontiguousarray(coded).view(np.uint32)[..., 0] & 0xFFFFFF
        depth = depth.astype(np.float32, copy=False) if with_depth or shadows or night is not None else None
        if night is not None:
            rgb = self._night_rgb(cam, T_global_from_cam, actor_poses, face, depth, night)
        elif shadows:
            rgb = self._shadowed_rgb(cam, T_global_from_cam, actor_poses, face, depth)
        else:
            # One 4-byte look-up per pixel (np.take on a flat table), then drop the pad byte.
            rgbx = np.take(self.face_rgbx, face).view(np.uint8).reshape(*face.shape, 4)
            rgb = cv2.cvtColor(rgbx, cv2.COLOR_RGBA2RGB)
        ids = IdImage(face, self.face_owner)
        return rgb, depth if with_depth else None, ids if lazy_ids else np.asarray(ids)

    def _night_rgb(self, cam: Camera, T_global_from_cam: np.ndarray, actor_poses: dict[int, np.ndarray],
                   face: np.ndarray, depth: np.ndarray, lights) -> np.ndarray:
        """(H, W, 3) uint8 rgb of the id pass's ``face`` (H, W) and ``depth`` (H, W) at night: each
        pixel's luminance from the ambient and the ``lights`` whose reach meets this view (the
        nearest of them, simgen/weather/night.py), through the camera's clean night exposure
        (simgen/weather/night_sensor.py; the noise is added after the other weather)."""
        from .weather import night, night_sensor, night_shading
        if self._night_tables is None:
            albedo, normals = (np.concatenate(x) for x in zip(*self._night_faces))
            self._night_tables = night.FaceTables(night_sensor.DECODE_8BIT[albedo].astype(np.float32),
                                                  normals.astype(np.float32),
                                                  night.emission(albedo, self.face_owner, lights.lit_ids))
        tables = self._night_tables
        for aid, (first, normals) in self.actor_faces.items():
            tables.normal[first:first + len(normals)] = normals @ actor_poses[aid][:3, :3].T
        seen = self._in_view(cam, T_global_from_cam, lights.pos, lights.reach)
        used = lights.nearest(seen, T_global_from_cam[:3, 3])
        return night_sensor.clean_image(night_shading.shade(face, depth, cam.K, T_global_from_cam, tables, used))

    def _shadowed_rgb(self, cam: Camera, T_global_from_cam: np.ndarray, actor_poses: dict[int, np.ndarray],
                      face: np.ndarray, depth: np.ndarray) -> np.ndarray:
        """(H, W, 3) uint8 rgb of the id pass's ``face`` (H, W) and camera ``depth`` (H, W) with
        the sun's shadows: a shadow map over the receivers, then :func:`sunlight.shade`."""
        K = cam.K
        K4 = np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2]])
        R = sunlight.R_sun_from_global(self.sun, T_global_from_cam[:3, 2])
        R_sun_from_cam, t_sun = R @ T_global_from_cam[:3, :3], R @ T_global_from_cam[:3, 3]
        lo, hi, count = sunlight.receiver_bounds(face, depth, self.face_tan, K4, R_sun_from_cam, t_sun, 2)
        if count == 0:
            sun_map, view = np.ones((1, 1), np.float32), np.array([0.0, 0.0, 1.0, 1.0, 1.0, 0.5, 1.0])
        else:
            sun_map, sun_view = self._shadow_map(R, lo, hi, actor_poses)
            view = sun_view.params((self.width, self.height))
        # The camera depth buffer's step at distance z is about z^2 2^-24 / znear (twice, to be safe).
        depth_step = 2.0 * 2.0 ** -24 / CAMERA_ZNEAR
        return sunlight.shade(face, depth, self.face_rgbx, self.face_ambient_rgbx, self.face_tan, K4,
                              R_sun_from_cam, t_sun, sun_map, view, depth_step)

    def _shadow_map(self, R: np.ndarray, lo: np.ndarray, hi: np.ndarray, actor_poses: dict[int, np.ndarray]):
        """Render the depth seen from the sun over the receivers' sun-frame box ``lo``..``hi`` (3,).

        What may cast a shadow into the box is drawn, highest first: the moving actors and the
        caster tiles whose bounding sphere reaches over its x-y rectangle. Returns the (H, W)
        float32 window depth map, top row first, and its :class:`sunlight.SunView`.
        """
        pr = self._pr
        ids = list(self.actor_nodes)
        actor_centre = np.array([actor_poses[i][:3, 3] for i in ids]).reshape(-1, 3) @ R.T      # sun frame
        actor_radius = np.array([self.radius[i] for i in ids])
        tile_centre = self.caster_centre @ R.T
        actors = sunlight.over_rectangle(actor_centre, actor_radius, lo, hi)
        tiles = sunlight.over_rectangle(tile_centre, self.caster_radius, lo, hi)
        for i in actors:
            self.scene.set_pose(self.actor_nodes[ids[i]], actor_poses[ids[i]])
        nodes = [self.actor_nodes[ids[i]] for i in actors] + [self.caster_nodes[i] for i in tiles]
        tops = np.concatenate([actor_centre[actors, 2] + actor_radius[actors],
                               tile_centre[tiles, 2] + self.caster_radius[tiles]])
        self._drawn = [nodes[i] for i in np.argsort(-tops, kind="stable")]
        view = sunlight.fit_view(R, lo, hi, float(tops.max(initial=-np.inf)), (self.width, self.height))
        self.cam_node.camera = pr.OrthographicCamera(view.xmag, view.ymag, znear=view.znear, zfar=view.zfar)
        self.scene.set_pose(self.cam_node, view.T_global_from_view)
        self._gl._renderer._read_main_framebuffer = self._readers["window"]
        return self._gl.render(self.scene, flags=pr.RenderFlags.DEPTH_ONLY), view

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


def _rgbx(rgb: np.ndarray) -> np.ndarray:
    """(F, 3) uint8 colours -> (F,) uint32, r | g << 8 | b << 16 (little-endian bytes r, g, b, 0)."""
    return np.concatenate([rgb, np.zeros((len(rgb), 1), np.uint8)], 1).view(np.uint32)[:, 0]


class IdImage:
    """(H, W) int32 actor ids, looked up from the rendered face indices only where they are read.

    ``ids[v, u]`` (any numpy index) gives the ids there; ``np.asarray(ids)`` the whole image. The
    visibility labels read a few thousand pixels per camera, so `make` never looks an image up
    in full. Index it or convert it: it has no arithmetic or comparisons of its own.
    """

    def __init__(self, face: np.ndarray, face_owner: np.ndarray):
        self.face, self.face_owner = face, face_owner
        self.shape = face.shape

    def __getitem__(self, index) -> np.ndarray:
        return np.take(self.face_owner, self.face[index])

    def __array__(self, dtype=None, copy=None) -> np.ndarray:
        ids = np.take(self.face_owner, self.face)
        return ids if dtype is None else ids.astype(dtype)


def depth_to_range(depth: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(H, W) camera-frame z -> (H, W) float32 range along each pixel's ray (m); 0 stays 0."""
    return depth.astype(np.float32, copy=False) * _ray_length_per_depth(depth.shape, np.asarray(K, np.float64).tobytes())


@functools.lru_cache(maxsize=16)
def _ray_length_per_depth(shape: tuple[int, int], K_bytes: bytes) -> np.ndarray:
    """(H, W) float32 |ray| / z of each pixel centre: a camera's constant, so computed once (in
    float64) instead of for every frame (a third of the camera fog's time at 1600x900)."""
    K = np.frombuffer(K_bytes, np.float64).reshape(3, 3)
    H, W = shape
    u = (np.arange(W) + 0.5 - K[0, 2]) / K[0, 0]
    v = (np.arange(H) + 0.5 - K[1, 2]) / K[1, 1]
    scale = np.sqrt(1.0 + u[None, :] ** 2 + v[:, None] ** 2).astype(np.float32)
    scale.flags.writeable = False
    return scale
