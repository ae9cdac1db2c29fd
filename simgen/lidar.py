"""The HDL-32E LIDAR_TOP: beam pattern, Embree ray casting, intensity, noise and per-point time.

A sweep lasts one rotation (0.05 s at 20 Hz) and ends at its timestamp. The head turns clockwise
seen from above and starts and ends facing backwards, so ray i fires at
``t_end - 0.05 + frac_i * 0.05`` with ego azimuth ``pi - 2 pi frac_i``. Each ray leaves from where
the sensor is at that instant (the ego moves during the sweep); the returns are then expressed in
the sensor frame at ``t_end``, as nuScenes does. Actors are posed at ``t_end``.

Intensity follows ``rho cos(incidence) / R^2``: returns below ``min_return`` are lost, and the
value is scaled so that 255 is reached at ``intensity_ref_range`` for rho cos = 1.
"""
from __future__ import annotations

import functools
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
import trimesh

from . import geometry
from . import lidar_kernels
from . import lidarseg
from .config import LidarConfig
from .rig import T_ego_from_lidar
from .world import CATEGORY, World

N_BEAMS = 32
ELEVATIONS_DEG = np.linspace(-30.67, 10.67, N_BEAMS)   # 1.33 deg apart; ring 0 is the lowest
SWEEP_PERIOD = 0.05
ATLAS_SPACING = 500.0   # metres between actor copies in the atlas: far beyond any candidate ray's reach

# A sweep's work is split over threads only when each gets at least this many rays.
MIN_RAYS_PER_THREAD = 4096

try:
    import embreex  # noqa: F401
    _HAS_EMBREE = True
except ImportError:  # trimesh's pure-Python engine is the fallback
    _HAS_EMBREE = False


@dataclass
class Sweep:
    """One lidar sweep after ray casting, before any degradation.

    points_lidar : (n, 5) float32 x, y, z (sensor frame at the sweep end), intensity 0..255, ring.
    time : (n,) float64 firing time (s, scene clock).  actor_id : (n,) int32, 0 = static world.
    rho : (n,) surface reflectivity.  cos_inc : (n,) cosine of the incidence angle.
    range : (n,) measured range (m).  dir_lidar : (n, 3) unit ray directions, sensor frame at t_end.
    label : (n,) uint8 nuScenes-lidarseg class index (:mod:`simgen.lidarseg`).

    The k rays that returned nothing (no surface, or one out of range or below the detection
    threshold), for the weather, whose particles can echo in them (None unless the scan was asked
    for them: ``scan(..., missed_rays=True)``): ``miss_origin``, ``miss_dir`` (k, 3) each ray's
    origin and unit direction (sensor frame at t_end), ``miss_ring`` (k,), ``miss_time`` (k,)
    firing time (s) and ``miss_range`` (k,) the distance (m) to the surface it met, inf for none.
    """
    points_lidar: np.ndarray
    time: np.ndarray
    actor_id: np.ndarray
    rho: np.ndarray
    cos_inc: np.ndarray
    range: np.ndarray
    dir_lidar: np.ndarray
    label: np.ndarray
    miss_origin: np.ndarray | None = None
    miss_dir: np.ndarray | None = None
    miss_ring: np.ndarray | None = None
    miss_time: np.ndarray | None = None
    miss_range: np.ndarray | None = None


def ray_pattern(cfg: LidarConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The rays of one sweep: firing fraction (m,), ring (m,), unit direction in the ego frame (m, 3)."""
    n_az = int(round(360.0 / cfg.azimuth_step_deg))
    frac = (np.arange(n_az) + 0.5) / n_az
    az = np.pi - 2.0 * np.pi * frac
    el = np.deg2rad(ELEVATIONS_DEG)
    AZ, EL = np.meshgrid(az, el, indexing="ij")            # (n_az, 32): column by column, in firing order
    d = np.stack([np.cos(EL) * np.cos(AZ), np.cos(EL) * np.sin(AZ), np.sin(EL)], -1).reshape(-1, 3)
    ring = np.tile(np.arange(N_BEAMS), n_az)
    return np.repeat(frac, N_BEAMS), ring, d


@functools.lru_cache(maxsize=None)
def _thread_pool(k: int) -> ThreadPoolExecutor:
    """One pool of ``k`` threads per process, made on first use."""
    return ThreadPoolExecutor(k, thread_name_prefix="lidar")


class RayTarget:
    """A mesh ready for first-hit queries: the ray engine plus plain per-face arrays.

    Embree (embreex) when present, else trimesh's pure-Python engine (exact, only slower). Embree
    is called directly rather than through trimesh: for the many small per-actor queries of a
    sweep, trimesh's per-call work (re-normalising directions, re-validating caches) costs more
    than the ray casting. Coordinates are taken relative to the mesh's lower corner so that
    float32 keeps millimetre precision anywhere in the world.
    """

    def __init__(self, mesh: trimesh.Trimesh, reflectivity: np.ndarray, engine: str = "auto"):
        vertices, faces = np.array(mesh.vertices, np.float64), np.array(mesh.faces, np.int64)
        if engine == "auto":
            engine = "embree" if _HAS_EMBREE else "triangle"
        self.engine = engine
        self.origin = vertices.min(axis=0) if len(vertices) else np.zeros(3)
        if engine == "embree":
            from embreex import rtcore_scene
            from embreex.mesh_construction import TriangleMesh
            self._scene = rtcore_scene.EmbreeScene()
            TriangleMesh(scene=self._scene, vertices=(vertices - self.origin).astype(np.float32),
                         indices=faces.astype(np.int32))
        else:
            from trimesh.ray.ray_triangle import RayMeshIntersector
            self._scene = RayMeshIntersector(mesh)
        self.normals = np.array(mesh.face_normals)                                # (f, 3)
        self.plane = np.einsum("fd,fd->f", self.normals, vertices[faces[:, 0]])   # (f,) n . v0
        self.reflectivity = np.asarray(reflectivity, np.float32)

    def first_triangles(self, origins: np.ndarray, dirs: np.ndarray, tfar: np.ndarray | None = None) -> np.ndarray:
        """(m,) index of the first triangle each ray hits, -1 for a miss. ``tfar`` (m,), optional,
        only lets Embree stop early: a hit beyond it may or may not be reported (``first_hits``
        applies it exactly)."""
        if len(origins) == 0:
            return np.zeros(0, np.int64)
        if self.engine != "embree":
            return np.asarray(self._scene.intersects_first(origins, dirs), dtype=np.int64)
        return np.asarray(self._scene.run((origins - self.origin).astype(np.float32), dirs.astype(np.float32),
                                          dists=None if tfar is None else tfar.astype(np.float32)), dtype=np.int64)

    def first_hits(self, origins: np.ndarray, dirs: np.ndarray, tfar: np.ndarray | None = None
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(m, 3) rays with unit directions -> (m,) hit distance (inf for a miss), triangle (-1)
        and |cos| of the incidence angle (the ray against the face normal).

        The distance is the exact (float64) ray-plane distance to the triangle the engine reports.
        With ``tfar`` (m,), a hit farther than it counts as a miss.
        """
        tri = self.first_triangles(origins, dirs, tfar)
        dist, cos = lidar_kernels.plane_hits(tri, origins, dirs, self.normals, self.plane,
                                 np.zeros(0) if tfar is None else tfar)
        return dist, tri, cos


class ActorMeshes:
    """All actor meshes concatenated in their box frames, posed together with one vectorised step."""

    def __init__(self, actors):
        verts, faces, owner, refl, off = [], [], [], [], 0
        for i, a in enumerate(actors):
            verts.append(a.mesh.vertices)
            faces.append(a.mesh.faces + off)
            owner.append(np.full(len(a.mesh.vertices), i))
            refl.append(a.mesh.metadata["reflectivity"])
            off += len(a.mesh.vertices)
        self.ids = np.array([a.id for a in actors], dtype=np.int32)
        self.verts = np.concatenate(verts) if verts else np.zeros((0, 3))
        self.faces = np.concatenate(faces) if faces else np.zeros((0, 3), np.int64)
        self.vert_owner = np.concatenate(owner) if owner else np.zeros(0, np.int64)
        self.face_owner = self.vert_owner[self.faces[:, 0]] if len(self.faces) else np.zeros(0, np.int64)
        self.refl = np.concatenate(refl) if refl else np.zeros(0, np.float32)

    def posed(self, poses: np.ndarray) -> trimesh.Trimesh:
        """(k, 4, 4) T_global_from_box per actor -> one global mesh."""
        P = poses[self.vert_owner]
        v = np.einsum("nij,nj->ni", P[:, :3, :3], self.verts) + P[:, :3, 3]
        return trimesh.Trimesh(v, self.faces, process=False)


class LidarScanner:
    """Ray-casts sweeps of one world.

    The static world and the actors that never move share one BVH, built once. The moving
    actors share a second BVH, also built once: an "atlas" holding each actor's mesh in its own
    box frame, the copies ``ATLAS_SPACING`` apart. Per sweep, the rays whose azimuth comes near an
    actor are moved into that actor's box frame (plus its atlas offset) and all of them are cast
    in one call; a hit counts only on the intended actor's copy. Rebuilding a BVH of the posed
    actors for every sweep would cost several times more than the casting itself.

    ``threads``: each stage of a sweep (static hits, actor hits, the points) works on contiguous
    chunks of rays in this many threads; embreex and the compiled kernels release the GIL. The
    rays are independent and the chunks are joined in order, so the bytes do not depend on it.
    """

    def __init__(self, cfg: LidarConfig, world: World, threads: int = 1):
        self.cfg, self.world = cfg, world
        self.frac, self.ring, d = ray_pattern(cfg)
        self.n_az = len(self.frac) // N_BEAMS
        self.T_ego_from_lidar = T_ego_from_lidar()
        # The lasers are fixed in the sensor, which is mounted tilted by about 1.4 deg: take the
        # pattern's azimuths relative to the mount's yaw, then apply the whole mount rotation.
        R = self.T_ego_from_lidar[:3, :3]
        Rz = geometry.pose_2d(0.0, 0.0, np.arctan2(R[1, 0], R[0, 0]))[:3, :3]
        self.dir_ego = d @ (R @ Rz.T).T
        moving = world.speed.max(axis=1) > 0
        annotated = np.array([a.annotate for a in world.actors])
        self.static_idx = np.nonzero(~moving & annotated)[0]
        self.moving_idx = np.nonzero(moving & annotated)[0]
        statics = ActorMeshes([world.actors[i] for i in self.static_idx])
        sm = world.static_mesh
        verts, faces = [sm.vertices], [sm.faces]
        if len(self.static_idx):
            posed = statics.posed(self._poses(self.static_idx, 0.0))
            verts.append(posed.vertices)
            faces.append(posed.faces + len(sm.vertices))
        self.static = RayTarget(trimesh.Trimesh(np.concatenate(verts), np.concatenate(faces), process=False),
                                np.concatenate([sm.metadata["reflectivity"], statics.refl]))
        self.static_ids = np.concatenate([np.zeros(len(sm.faces), np.int32), statics.ids[statics.face_owner]])
        # lidarseg class per static face (the merged actors' faces are overridden by their id's
        # class, below) and per actor id.
        self.static_label = np.concatenate([sm.metadata["lidarseg"], np.zeros(len(statics.faces), np.uint8)])
        self.label_of_id = np.zeros(1 + max(a.id for a in world.actors), np.uint8)
        for a in world.actors:
            self.label_of_id[a.id] = lidarseg.INDEX[CATEGORY[a.cls]]
        self.sensor_height = float(self.T_ego_from_lidar[2, 3])
        self.ring_elevation = np.deg2rad(ELEVATIONS_DEG)
        self.mover_ids = np.array([world.actors[i].id for i in self.moving_idx], np.int32)
        self.threads = max(1, int(threads))
        self._build_atlas()

    def _column_poses(self, t_end: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per column of 32 lasers (they fire together): firing time (n_az,), sensor origin
        (n_az, 3) and ego yaw (n_az,) in the global frame. The ego pose is planar (ego_pose z is
        0, rotation about z only)."""
        t_col = t_end - SWEEP_PERIOD + self.frac[::N_BEAMS] * SWEEP_PERIOD
        x, y, yaw = self.world.ego_xy_yaw(t_col)
        c, s = np.cos(yaw), np.sin(yaw)
        p = self.T_ego_from_lidar[:3, 3]
        origin = np.stack([x + c * p[0] - s * p[1], y + s * p[0] + c * p[1], np.full_like(x, p[2])], 1)
        return t_col, origin, yaw

    def sweep_rays(self, t_end: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The rays of the sweep ending at ``t_end``: firing times (m,), and origins and unit
        directions (m, 3) in the global frame."""
        t_col, origin_col, yaw = self._column_poses(t_end)
        return (np.repeat(t_col, N_BEAMS),) + lidar_kernels.sweep_rays(origin_col, yaw, self.dir_ego, N_BEAMS)

    def _map(self, fn, n: int) -> list:
        """``fn(slice)`` over contiguous chunks of ``range(n)``, in threads; results in order."""
        k = self.threads if n >= MIN_RAYS_PER_THREAD * self.threads else 1
        cut = np.linspace(0, n, k + 1).astype(np.int64)
        chunks = [slice(int(a), int(b)) for a, b in zip(cut[:-1], cut[1:])]
        return [fn(chunks[0])] if k == 1 else list(_thread_pool(k).map(fn, chunks))

    def _poses(self, idx: np.ndarray, t: float) -> np.ndarray:
        b = self.world.boxes_at(t)[idx]
        return geometry.poses_2d(b[:, 0], b[:, 1], b[:, 6], b[:, 2])

    def _build_atlas(self) -> None:
        """One BVH of every moving actor's mesh in its box frame, each at its own offset."""
        k = len(self.moving_idx)
        side = max(1, int(np.ceil(k ** (1 / 3))))
        cell = np.stack(np.unravel_index(np.arange(k), (side, side, side)), 1)
        self.atlas_offset = cell * ATLAS_SPACING                              # (k, 3)
        verts, faces, owner, refl, n = [], [], [], [], 0
        for j, i in enumerate(self.moving_idx):
            mesh = self.world.actors[i].mesh
            verts.append(np.asarray(mesh.vertices) + self.atlas_offset[j])
            faces.append(np.asarray(mesh.faces) + n)
            owner.append(np.full(len(mesh.faces), j))
            refl.append(mesh.metadata["reflectivity"])
            n += len(mesh.vertices)
        if k == 0:
            self.atlas = None
            return
        self.atlas = RayTarget(trimesh.Trimesh(np.concatenate(verts), np.concatenate(faces), process=False),
                               np.concatenate(refl))
        self.atlas_owner = np.concatenate(owner)

    def _cast_movers(self, t_end, origin, dirs, sensor_xy, ego_yaw, dist, rho, ids, cos_inc) -> None:
        """Cast the rays near each moving actor against the atlas; update the hits in place."""
        if self.atlas is None:
            return
        boxes = self.world.boxes_at(t_end)[self.moving_idx]
        near = np.nonzero(np.hypot(*(boxes[:, :2] - sensor_xy).T)
                          <= self.cfg.max_range + np.hypot(boxes[:, 3], boxes[:, 4]))[0]
        # How far the sensor is, at any firing, from where it is at t_end (the ego moves).
        travel = float(np.max(np.hypot(*(origin[::N_BEAMS, :2] - sensor_xy).T)))
        rays, owner = self._candidate_rays(boxes[near], sensor_xy, ego_yaw, dist, travel)
        if len(rays) == 0:
            return
        owner = near[owner]
        c_box, s_box = np.cos(boxes[:, 6]), np.sin(boxes[:, 6])
        centre = np.ascontiguousarray(boxes[:, :3])

        def hits(chunk):
            o_local, d_local = lidar_kernels.into_box_frames(rays[chunk], owner[chunk], origin, dirs, centre, c_box, s_box,
                                                 self.atlas_offset)
            return self.atlas.first_hits(o_local, d_local, tfar=dist[rays[chunk]])

        d_hit, tri, cos = _join(self._map(hits, len(rays)))
        ok = (tri >= 0) & (self.atlas_owner[np.maximum(tri, 0)] == owner) & (d_hit < dist[rays])
        # Several actors may be hit by one ray: write the farthest first so the nearest wins.
        # (|cos| of the incidence does not depend on the frame.)
        sel = np.nonzero(ok)[0]
        sel = sel[np.argsort(-d_hit[sel], kind="stable")]
        r, t = rays[sel], tri[sel]
        dist[r] = d_hit[sel]
        rho[r] = self.atlas.reflectivity[t]
        ids[r] = self.mover_ids[owner[sel]]
        cos_inc[r] = cos[sel]

    def _candidate_rays(self, boxes: np.ndarray, sensor_xy: np.ndarray, ego_yaw: float, dist: np.ndarray,
                        travel: float) -> tuple[np.ndarray, np.ndarray]:
        """The rays that can pass within reach of each of ``boxes`` (k, 7) during the sweep: the
        columns whose azimuth and the rings whose elevation come near its bounding cylinder, less
        the rays whose first static hit (``dist``, per ray) comes before the cylinder's near side.
        The cylinder is widened by ``travel``, the farthest the sensor gets during the sweep from
        ``sensor_xy``, its position at the sweep's end.

        Returns (ray indices, box index of each), box by box, column by column, ring by ring."""
        rel = boxes[:, :2] - sensor_xy
        d = np.hypot(rel[:, 0], rel[:, 1])
        r = np.hypot(boxes[:, 3], boxes[:, 4]) / 2 + travel + 0.05   # + 5 cm of slack
        inside = d <= r
        with np.errstate(invalid="ignore", divide="ignore"):
            half = np.arcsin(np.minimum(r / d, 1.0)) + np.deg2rad(1.0)   # + the mount tilt's effect
        centre = ((np.pi - (np.arctan2(rel[:, 1], rel[:, 0]) - ego_yaw)) / (2 * np.pi)) % 1.0
        c0 = np.floor((centre - half / (2 * np.pi)) * self.n_az).astype(np.int64)
        c1 = np.ceil((centre + half / (2 * np.pi)) * self.n_az).astype(np.int64)
        c0[inside], c1[inside] = 0, self.n_az - 1
        # Elevations under which the cylinder's bottom and top are seen from the sensor height.
        dz_lo = boxes[:, 2] - boxes[:, 5] / 2 - self.sensor_height
        dz_hi = boxes[:, 2] + boxes[:, 5] / 2 - self.sensor_height
        el_lo = np.arctan2(dz_lo, np.where(dz_lo < 0, d - r, d + r))
        el_hi = np.arctan2(dz_hi, np.where(dz_hi > 0, d - r, d + r))
        margin = np.deg2rad(1.6)                                # the mount tilt, and then some
        rings = ((self.ring_elevation >= el_lo[:, None] - margin)
                 & (self.ring_elevation <= el_hi[:, None] + margin))     # (k, 32)
        rings[inside] = True
        # Every (box, column) pair, then its rings.
        n_cols = c1 - c0 + 1
        box_of_col = np.repeat(np.arange(len(boxes)), n_cols)
        col = (np.arange(len(box_of_col)) - np.repeat(np.cumsum(n_cols) - n_cols, n_cols) + c0[box_of_col]) % self.n_az
        col_ring = rings[box_of_col]                                     # (pairs, 32)
        pair, ring = np.nonzero(col_ring)
        rays, owner = col[pair] * N_BEAMS + ring, box_of_col[pair]
        # A ray travels at least as far along itself as across the ground.
        reach = dist[rays] >= (d - r)[owner]
        return rays[reach], owner[reach]

    def scan(self, t_end: float, rng: np.random.Generator, missed_rays: bool = False) -> Sweep:
        """Cast one sweep ending at ``t_end`` (s). ``rng`` draws the range noise. ``missed_rays``:
        also keep the rays that returned nothing (``Sweep.miss_*``, which only rain and snow read;
        a clear sweep skips their bookkeeping, 8 % of its time)."""
        cfg = self.cfg
        t_col, origin_col, yaw = self._column_poses(t_end)
        origin, dirs = lidar_kernels.sweep_rays(origin_col, yaw, self.dir_ego, N_BEAMS)
        dist, tri, cos_inc = _join(self._map(lambda c: self.static.first_hits(origin[c], dirs[c]), len(dirs)))
        face = np.maximum(tri, 0)             # a miss reads face 0; its infinite distance drops it
        rho = np.take(self.static.reflectivity, face)
        ids = np.take(self.static_ids, face)
        T_end = self.world.ego_pose(t_end)
        T_lidar = T_end @ self.T_ego_from_lidar                          # T_global_from_lidar at t_end
        ego_yaw = float(np.arctan2(T_end[1, 0], T_end[0, 0]))
        self._cast_movers(t_end, origin, dirs, T_lidar[:2, 3], ego_yaw, dist, rho, ids, cos_inc)
        noise = cfg.range_noise_sigma * rng.standard_normal(len(dist))
        label = np.where(ids > 0, np.take(self.label_of_id, ids), np.take(self.static_label, face))
        # Into the lidar frame at t_end: p = R (origin - t) + (R dir) meas, R = R_lidar_from_global;
        # the first term once per column.
        R_lidar_from_global = np.ascontiguousarray(T_lidar[:3, :3].T)
        origin_lidar = (origin_col - T_lidar[:3, 3]) @ R_lidar_from_global.T

        def points(chunk):
            return lidar_kernels.returns(chunk.start, dist[chunk], noise[chunk], rho[chunk], cos_inc[chunk], ids[chunk],
                             label[chunk], dirs, self.ring, t_col, origin_lidar, R_lidar_from_global, cfg.min_range,
                             cfg.max_range, cfg.min_return, cfg.intensity_ref_range, N_BEAMS)

        sweep = Sweep(*_join(self._map(points, len(dist))))
        if missed_rays:
            _add_missed_rays(sweep, dist, dirs, self.ring, t_col, origin_lidar, R_lidar_from_global)
        return sweep


def _add_missed_rays(sweep: Sweep, dist: np.ndarray, dirs: np.ndarray, ring: np.ndarray, t_col: np.ndarray,
                     origin_lidar: np.ndarray, R_lidar_from_global: np.ndarray) -> None:
    """Fill the sweep's ``miss_*`` fields from the sweep's rays (m,) in firing order: a return's ray
    is its column (its firing time is its column's, which is unique) times N_BEAMS plus its ring."""
    col = np.searchsorted(t_col, sweep.time)
    returned = np.zeros(len(dist), bool)
    returned[col * N_BEAMS + sweep.points_lidar[:, 4].astype(np.int64)] = True
    miss = np.flatnonzero(~returned)
    sweep.miss_origin = origin_lidar[miss // N_BEAMS]
    sweep.miss_dir = dirs[miss] @ R_lidar_from_global.T
    sweep.miss_ring = ring[miss]
    sweep.miss_time = t_col[miss // N_BEAMS]
    sweep.miss_range = dist[miss]


def _join(parts: list[tuple]) -> tuple:
    """Per-chunk tuples of arrays -> one tuple of the arrays joined in chunk order."""
    return parts[0] if len(parts) == 1 else tuple(np.concatenate(a) for a in zip(*parts))
