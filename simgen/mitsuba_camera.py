"""Optional path-traced cameras with Mitsuba 3: the same world meshes, face colours, rig and sun as
the pyrender cameras, with fog as a homogeneous participating medium of the lidar's extinction.

Mitsuba's camera frame looks along +z with +y up and +x to the LEFT; the nuScenes camera frame
looks along +z with y down and x right, so ``T_mitsuba_from_cv = diag(-1, -1, 1)`` (a half turn
about z). The off-centre principal point is Mitsuba's ``principal_point_offset_x/y`` (in units
of the film size, with the opposite sign to ``cx - W/2``). Per-face colours are written as a face attribute
(``face_color``), read by a diffuse BSDF through a ``mesh_attribute`` texture, with flat face normals.
A second pass, in which every shape emits its
actor id and nothing else is lit, gives the per-pixel actor id, used to check that both renderers
agree geometrically.

Variant: ``llvm_ad_rgb`` when libLLVM 19 can be loaded, else ``scalar_rgb``, which works out of
the box (Mitsuba 3 documentation, "Variants": the ``llvm_*`` variants compile their kernels
through Dr.Jit's LLVM backend, which loads a libLLVM shared library at run time). It costs
seconds per image, so it is an option for small photoreal sets.

Why a face attribute and not vertex colours: the worlds hold sliver triangles (the 1 cm sides of
the lane markings and road boxes, 66 m long). Mitsuba interpolates a vertex attribute from
barycentric coordinates it recomputes in float32 from the hit point, through a Gram determinant
``|e1|^2 |e2|^2 - (e1 . e2)^2`` that cancels to zero on such a sliver (66^4 against 66^2 * 1e-4),
so the colour, hence the sample, is NaN there: black pixels. A face attribute is looked up by
the primitive index alone.

Mitsuba's log goes to stderr (:func:`_log_to_stderr`), so that a caller's stdout stays its own
(``scripts/bench.py --json`` prints JSON there).
"""
from __future__ import annotations

import ctypes.util
import sys
import tempfile
from pathlib import Path

import numpy as np
import trimesh

from . import geometry
from .config import CameraConfig
from .rig import Camera
from .sun import sun_direction
from .world import World

T_MI_FROM_CV = np.diag([-1.0, -1.0, 1.0, 1.0])
SKY_RADIANCE = (0.55, 0.7, 0.95)
FOG_ALBEDO = 0.9
FOG_TOP = 40.0          # metres: the fog layer's height


def choose_variant() -> str:
    """``llvm_ad_rgb`` if libLLVM 19 can be found, else ``scalar_rgb``."""
    import mitsuba as mi
    found = ctypes.util.find_library("LLVM-19") or ctypes.util.find_library("LLVM.so.19")
    if found and "llvm_ad_rgb" in mi.variants():
        return "llvm_ad_rgb"
    return "scalar_rgb"


def _ply(mesh: trimesh.Trimesh, path: Path) -> None:
    """Write ``mesh`` as a binary PLY: its vertices, and per face the vertex indices and the face
    colour as float linear RGB in [0, 1] (Mitsuba loads the face properties red, green, blue as
    the ``face_color`` attribute; trimesh's export writes 4 uchar channels)."""
    faces = np.asarray(mesh.faces, dtype=np.int32)
    xyz = np.ascontiguousarray(mesh.vertices, dtype="<f4")
    # Reflectance in [0, 1], linear: the face colours are sRGB-encoded.
    rgb = (np.asarray(mesh.visual.face_colors)[:, :3] / 255.0) ** 2.2
    face = np.empty(len(faces), dtype=[("n", "u1"), ("v", "<i4", (3,)),
                                       ("red", "<f4"), ("green", "<f4"), ("blue", "<f4")])
    face["n"], face["v"] = 3, faces
    face["red"], face["green"], face["blue"] = rgb[:, 0], rgb[:, 1], rgb[:, 2]
    header = ("ply\nformat binary_little_endian 1.0\n"
              f"element vertex {len(xyz)}\nproperty float x\nproperty float y\nproperty float z\n"
              f"element face {len(faces)}\nproperty list uchar int vertex_indices\n"
              "property float red\nproperty float green\nproperty float blue\nend_header\n")
    path.write_bytes(header.encode() + xyz.tobytes() + face.tobytes())


def _log_to_stderr(mi) -> None:
    """Send Mitsuba's log (its warnings included) to stderr instead of stdout."""
    class StderrAppender(mi.Appender):
        def append(self, level, text):
            sys.stderr.write(text + "\n")

        def log_progress(self, progress, name, formatted, eta, ptr=None):
            pass

    logger = mi.logger() if hasattr(mi, "logger") else mi.Thread.thread().logger()
    logger.clear_appenders()
    logger.add_appender(StderrAppender())


class MitsubaRenderer:
    """Renders one camera of one frame of a world. ``spp`` samples per pixel for the rgb pass."""

    def __init__(self, cfg: CameraConfig, spp: int = 16, variant: str | None = None) -> None:
        import mitsuba as mi
        self.variant = variant or choose_variant()
        mi.set_variant(self.variant)
        _log_to_stderr(mi)
        self.mi, self.cfg, self.spp = mi, cfg, spp
        self._tmp = tempfile.TemporaryDirectory(prefix="simgen-mitsuba-")
        self._static_key = None
        self.last_linear: np.ndarray | None = None

    def close(self) -> None:
        self._tmp.cleanup()

    def _shapes(self, world: World, actor_poses: dict[int, np.ndarray]) -> tuple[dict, list[int]]:
        """Scene dict entries for the static world and the posed actors, and the actor id of
        each shape in order (0 = static world)."""
        root = Path(self._tmp.name)
        key = id(world)
        if self._static_key != key:
            _ply(world.static_mesh, root / "static.ply")
            self._static_key = key
        bsdf = {"type": "diffuse", "reflectance": {"type": "mesh_attribute", "name": "face_color"}}
        shapes = {"s0000": {"type": "ply", "filename": str(root / "static.ply"), "bsdf": bsdf, "face_normals": True}}
        owners = [0]
        for a in world.actors:
            if not a.annotate or a.id not in actor_poses:
                continue
            m = a.mesh.copy()
            m.apply_transform(actor_poses[a.id])
            path = root / f"actor{a.id}.ply"
            _ply(m, path)
            shapes[f"s{len(owners):04d}"] = {"type": "ply", "filename": str(path), "bsdf": bsdf, "face_normals": True}
            owners.append(a.id)
        return shapes, owners

    def _sensor(self, cam: Camera, T_global_from_cam: np.ndarray, spp: int, medium=None, scale: int = 1) -> dict:
        """Mitsuba sensor of ``cam``; ``scale`` multiplies the film size (same view)."""
        mi = self.mi
        W, H = self.cfg.resolution
        K = cam.K
        sensor = {
            "type": "perspective",
            "fov_axis": "x",
            "fov": float(np.degrees(2 * np.arctan(W / (2 * K[0, 0])))),
            # Mitsuba measures the offset the other way round (the image content moves opposite to
            # the principal point): without the minus, +cx shifts objects left by 2 cx.
            "principal_point_offset_x": float((W / 2 - K[0, 2]) / W),
            "principal_point_offset_y": float((H / 2 - K[1, 2]) / H),
            "near_clip": 0.1,
            "far_clip": float(self.cfg.zfar),
            "to_world": mi.ScalarTransform4f((T_global_from_cam @ T_MI_FROM_CV).tolist()),
            "film": {"type": "hdrfilm", "width": W * scale, "height": H * scale, "rfilter": {"type": "box"},
                     "pixel_format": "rgb", "component_format": "float32"},
            "sampler": {"type": "independent", "sample_count": spp},
        }
        if medium is not None:
            sensor["medium"] = medium
        return sensor

    def render(self, world: World, cam: Camera, T_global_from_cam: np.ndarray, actor_poses: dict[int, np.ndarray],
               fog_alpha: float = 0.0, with_ids: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
        """rgb (H, W, 3) uint8 and ids (H, W) int32 (actor id per pixel, 0 = static world / sky;
        None unless ``with_ids``). The rgb pass's linear float image stays in ``self.last_linear``."""
        mi = self.mi
        shapes, owners = self._shapes(world, actor_poses)
        emitters = sun_and_sky(world.meta, self.cfg)
        medium = None
        if fog_alpha > 0:
            medium = {"type": "homogeneous", "sigma_t": float(fog_alpha),
                      "albedo": {"type": "rgb", "value": [FOG_ALBEDO] * 3}}
            # A fog layer FOG_TOP metres deep over the whole view: sun and sky light enter it from
            # above, as in ground fog, instead of crossing hundreds of metres of it.
            c = T_global_from_cam[:3, 3]
            shapes["fogbox"] = {"type": "cube", "bsdf": {"type": "null"}, "interior": medium,
                                "to_world": mi.ScalarTransform4f().translate([float(c[0]), float(c[1]), FOG_TOP / 2 - 5.0])
                                .scale([self.cfg.zfar, self.cfg.zfar, FOG_TOP / 2 + 5.0])}
        integrator = ({"type": "volpath", "max_depth": 8} if fog_alpha > 0 else {"type": "path", "max_depth": 3})
        scene = mi.load_dict({"type": "scene", "integrator": integrator, **shapes, **emitters,
                              "sensor": self._sensor(cam, T_global_from_cam, self.spp, medium)})
        self.last_linear = np.asarray(mi.render(scene, spp=self.spp))[..., :3]   # (H, W, 3) float32, linear
        # nan_to_num only as a guard: no sample is NaN since the face colours (module docstring).
        rgb = np.round(255 * np.clip(np.nan_to_num(self.last_linear), 0, 1) ** (1 / 2.2)).astype(np.uint8)
        if not with_ids:
            return rgb, None

        # Geometry pass: every shape emits its actor id as radiance (black BSDF, no other light);
        # one sample per pixel and a box filter, so each pixel holds exactly one shape's id. The
        # sample lies anywhere in its pixel, while a rasteriser samples the pixel centre: the film
        # is 3x finer and the central sub-pixel of each 3x3 block is kept (within 1/6 px).
        id_shapes = {}
        for (name, shape), owner in zip(((k, v) for k, v in shapes.items() if k != "fogbox"), owners):
            id_shapes[name] = {**shape, "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.0}},
                               "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [float(owner), 0.0, 0.0]}}}
        geo_scene = mi.load_dict({"type": "scene", "integrator": {"type": "path", "max_depth": 1},
                                  **id_shapes, "sensor": self._sensor(cam, T_global_from_cam, 1, scale=3)})
        ids = np.round(np.asarray(mi.render(geo_scene, spp=1))[1::3, 1::3, 0]).astype(np.int32)
        return rgb, ids


def sun_and_sky(meta: dict, cfg: CameraConfig) -> dict:
    """Scene dict entries of the light: the sun of the pyrender cameras (simgen/sun.py), a
    directional emitter shining along -sun_direction, and the sky's ambient."""
    sun = sun_direction(meta)
    return {
        "sun": {"type": "directional", "direction": (-sun).tolist(),
                "irradiance": {"type": "rgb", "value": [cfg.sun_intensity] * 3}},
        "sky": {"type": "constant", "radiance": {"type": "rgb", "value": [cfg.ambient * c for c in SKY_RADIANCE]}},
    }


def actor_poses_at(world: World, t: float) -> dict[int, np.ndarray]:
    """actor id -> (4, 4) T_global_from_box at time ``t`` (annotated actors)."""
    b = world.boxes_at(t)
    poses = geometry.poses_2d(b[:, 0], b[:, 1], b[:, 6], b[:, 2])
    return {a.id: poses[i] for i, a in enumerate(world.actors) if a.annotate}
