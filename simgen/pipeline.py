"""One scene: world -> frames -> sensors -> labels -> its part file (``generate_scene``).

Every scene is a pure function of (settings, global seed, scene index): its generator is seeded
with ``SeedSequence([seed, scene_index])``, so the bytes do not depend on ``--workers`` or on
which scenes were already done when a run was resumed. :mod:`simgen.make` runs the scenes in
worker processes.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from . import degrade as D
from . import geometry as geo
from . import labels
from . import lidarseg as LS
from . import rig
from . import writer as W
from .config import SceneConfig
from .layout import Grid
from .lidar import LidarScanner
from .occluders import add_occluders
from .scene import SWEEPS_PER_KEYFRAME, keyframe_times, sample_world, sweep_end_times
from .settings import MakeSettings, scene_rng
from .world import CATEGORY, World

ANNOTATION_RANGE = 80.0
BASE_TIMESTAMP_US = 1_600_000_000_000_000


def degrade_sweep(sweep, cfg: SceneConfig, rings: np.ndarray,
                  rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """The points (n, 5) a degraded LIDAR_TOP delivers for a clean ``sweep``, and their lidarseg
    labels (n,) uint8: fog (its returns are labelled noise), then the dropped rings and the field
    of view; no points at all if the lidar failed. ``rng`` is the scene's degradation stream (the
    clean sensor stream is left untouched)."""
    d = cfg.degrade
    if rig.LIDAR in d.dropped:
        return np.zeros((0, 5), np.float32), np.zeros(0, np.uint8)
    # The label rides along as a sixth column: the degradation steps keep or drop whole rows and
    # carry the columns after the ring unchanged (their contract in simgen.degrade).
    pts = np.concatenate([sweep.points_lidar, sweep.label[:, None].astype(np.float32)], axis=1)
    if d.alpha > 0:
        pts, is_fog = D.fog_lidar(pts, sweep.rho * sweep.cos_inc, sweep.range, sweep.dir_lidar, d.alpha,
                                  cfg.lidar.min_return, cfg.lidar.intensity_ref_range, rng)
        pts[is_fog, 5] = LS.NOISE
    if len(rings):
        pts = D.drop_rings(pts, rings)
    if d.lidar_fov < 360:
        forward_lidar = rig.T_ego_from_lidar()[:3, :3].T @ np.array([1.0, 0.0, 0.0])
        pts = D.keep_sector(pts, forward_lidar, d.lidar_fov)
    return np.ascontiguousarray(pts[:, :5]), pts[:, 5].astype(np.uint8)


def degrade_image(rgb: np.ndarray, depth: np.ndarray, cam: rig.Camera, cfg: SceneConfig, s, idx: int,
                  cam_index: int) -> np.ndarray:
    """The image a degraded camera delivers: fog on the rendered range, then lens dirt (the same
    blobs in every frame of a scene: their rng is keyed on the scene and the camera); black if
    the camera failed."""
    from .camera import depth_to_range
    d = cfg.degrade
    if cam.channel in d.dropped:
        return np.zeros_like(rgb)
    if d.alpha > 0 and cfg.camera.renderer == "pyrender":   # Mitsuba renders fog as a medium
        rgb = D.fog_image(rgb, depth_to_range(depth, cam.K), d.alpha)
    if d.lens_occlusion:
        rgb = D.lens_dirt(rgb, d.lens_occlusion, scene_rng(s.seed, idx, 100 + cam_index))
    return rgb


def camera_time(t_end: float, cam: rig.Camera) -> float:
    """A camera fires when the lidar sweep ending at ``t_end`` crosses its optical axis."""
    frac = ((np.pi - cam.center_azimuth) / (2 * np.pi)) % 1.0
    return t_end - 0.05 + frac * 0.05


_RENDERER = None


def _renderer(cfg: SceneConfig, gl: str | None):
    """The process's one renderer (re-created only if the resolution changes)."""
    global _RENDERER
    from .camera import Renderer
    if _RENDERER is None or _RENDERER.cfg.resolution != cfg.camera.resolution:
        if _RENDERER is not None:
            _RENDERER.close()
        _RENDERER = Renderer(cfg.camera, gl)
    _RENDERER.cfg = cfg.camera
    return _RENDERER


_MITSUBA = None


def _mitsuba(cfg: SceneConfig):
    """The process's one Mitsuba renderer."""
    global _MITSUBA
    from .mitsuba_camera import MitsubaRenderer
    if _MITSUBA is None:
        _MITSUBA = MitsubaRenderer(cfg.camera, cfg.camera.spp)
    _MITSUBA.cfg, _MITSUBA.spp = cfg.camera, cfg.camera.spp
    return _MITSUBA


def build_world(s: MakeSettings, idx: int) -> World:
    """The world of scene ``idx``: a pure function of the settings, the seed and the index."""
    rng_world = scene_rng(s.seed, idx, 0)
    world = sample_world(s.cfg, rng_world, s.samples_per_scene)
    world.meta.update(sun_azimuth=float(rng_world.uniform(-np.pi, np.pi)),
                      sun_elevation=float(rng_world.uniform(0.5, 1.2)))
    if s.cfg.degrade.occlusion != "none":
        # Own stream, after the world is complete: the clean world's content is untouched.
        world = add_occluders(world, Grid(s.cfg.layout), s.cfg.degrade.occlusion, scene_rng(s.seed, idx, 3))
    return world


def generate_scene(s: MakeSettings, dataroot: Path, idx: int, threads: int = 1) -> int:
    """Render, scan, label and write one scene. Returns its number of samples.

    ``threads``: the lidar's ray casting is split over this many threads (the bytes do not depend
    on it). numpy's BLAS is held to one thread meanwhile: the products here are (n, 3) @ (3, 3),
    which gain nothing from threads, and its idle threads spin (sched_yield) after each one:
    measured on an 800x450 scene, 2.4 s of system time against 0.1 s, for the same wall time.
    """
    from threadpoolctl import threadpool_limits
    with threadpool_limits(limits=1, user_api="blas"):
        return _generate_scene(s, dataroot, idx, threads)


def _generate_scene(s: MakeSettings, dataroot: Path, idx: int, threads: int) -> int:
    cfg = s.cfg
    world = build_world(s, idx)
    rng_sensor = scene_rng(s.seed, idx, 1)
    renderer = _renderer(cfg, s.gl)
    renderer.set_world(world, key=(s.seed, idx, id(world)))
    scanner = LidarScanner(cfg.lidar, world, threads=threads)
    cams = rig.cameras(cfg.camera.resolution)
    # Degradation draws from its own stream, so the clean sensor data (and the labels counted
    # on them) are the same bytes with or without it: paired datasets.
    rng_degrade = scene_rng(s.seed, idx, 2)
    dropped_rings = D.choose_rings(cfg.degrade.beam_drop, rng_degrade) if cfg.degrade.beam_drop else np.zeros(0, int)

    scene_name = f"scene-{idx:04d}"
    log_name = f"simgen-{s.seed}-{idx:04d}"
    tok = lambda *p: W.token(s.seed, idx, *p)  # noqa: E731
    t0_us = BASE_TIMESTAMP_US + idx * 1_000_000_000
    us = lambda t: int(t0_us + round(t * 1e6))  # noqa: E731
    rec = {name: [] for name in W.PER_SCENE_TABLES}

    log_tok, map_tok, scene_tok = tok("log"), tok("map"), tok("scene")
    map_file = f"maps/{map_tok}.png"
    W.write_png(dataroot / map_file, world.drivable)
    rec["log"].append({"token": log_tok, "logfile": log_name, "vehicle": "simgen-ego",
                       "date_captured": "2020-09-13", "location": f"simgen-{cfg.name}"})
    rec["map"].append({"token": map_tok, "log_tokens": [log_tok], "category": "semantic_prior", "filename": map_file})

    calib = {}
    for cam in cams:
        calib[cam.channel] = {"token": tok("calib", cam.channel), "sensor_token": W.token("sensor", cam.channel),
                              "translation": list(cam.translation), "rotation": list(cam.rotation),
                              "camera_intrinsic": cam.K.tolist()}
    calib[rig.LIDAR] = {"token": tok("calib", rig.LIDAR), "sensor_token": W.token("sensor", rig.LIDAR),
                        "translation": list(rig.LIDAR_TRANSLATION), "rotation": list(rig.lidar_rotation()),
                        "camera_intrinsic": []}
    rec["calibrated_sensor"] = list(calib.values())

    key_times = keyframe_times(s.samples_per_scene)
    sample_toks = [tok("sample", k) for k in range(len(key_times))]
    for k, t in enumerate(key_times):
        rec["sample"].append({"token": sample_toks[k], "timestamp": us(t), "scene_token": scene_tok,
                              "prev": sample_toks[k - 1] if k else "",
                              "next": sample_toks[k + 1] if k + 1 < len(key_times) else ""})
    rec["scene"].append({"token": scene_tok, "log_token": log_tok, "nbr_samples": len(key_times),
                         "first_sample_token": sample_toks[0], "last_sample_token": sample_toks[-1],
                         "name": scene_name,
                         "description": " ".join(filter(None, [
                             f"simgen preset {cfg.name}, seed {s.seed}, scene {idx}. {world.description}",
                             cfg.degrade.describe()]))})

    def add_sample_data(channel, sd_tok, t, k_sample, is_key, filename, width, height, fmt):
        T = world.ego_pose(t)
        rec["ego_pose"].append({"token": sd_tok, "timestamp": us(t), "translation": [float(T[0, 3]), float(T[1, 3]), 0.0],
                                "rotation": [float(v) for v in geo.matrix_to_quat_wxyz(T[:3, :3])]})
        rec["sample_data"].append({"token": sd_tok, "sample_token": sample_toks[k_sample], "ego_pose_token": sd_tok,
                                   "calibrated_sensor_token": calib[channel]["token"], "timestamp": us(t),
                                   "fileformat": fmt, "is_key_frame": is_key, "height": height, "width": width,
                                   "filename": filename, "prev": "", "next": ""})
        return rec["ego_pose"][-1]

    # Lidar: every sweep; key frames go to samples/, the others to sweeps/ (next sample's token).
    instance_anns: dict[int, list[dict]] = {}
    lidar_chain, cam_chains = [], {c.channel: [] for c in cams}
    for j, t_end in enumerate(sweep_end_times(s.samples_per_scene)):
        is_key = (j + 1) % SWEEPS_PER_KEYFRAME == 0
        k_sample = min(j // SWEEPS_PER_KEYFRAME, len(key_times) - 1)
        sweep = scanner.scan(float(t_end), rng_sensor)
        sd_tok = tok("sd", rig.LIDAR, j)
        fname = f"{'samples' if is_key else 'sweeps'}/{rig.LIDAR}/{log_name}__{rig.LIDAR}__{us(t_end)}.pcd.bin"
        points, point_labels = (degrade_sweep(sweep, cfg, dropped_rings, rng_degrade) if cfg.degrade.active
                                else (sweep.points_lidar, sweep.label))
        W.write_pointcloud(dataroot / fname, points)
        pose = add_sample_data(rig.LIDAR, sd_tok, float(t_end), k_sample, is_key, fname, 0, 0, "pcd")
        lidar_chain.append(rec["sample_data"][-1])
        if is_key and len(points):
            # nuScenes-lidarseg labels the key frames' points (a failed lidar has none to label).
            seg_file = f"lidarseg/{s.version}/{sd_tok}_lidarseg.bin"
            W.write_atomic(dataroot / seg_file, point_labels.tobytes())
            rec["lidarseg"].append({"token": sd_tok, "sample_data_token": sd_tok, "filename": seg_file})
        if is_key:
            _key_frame(s, idx, world, renderer, cams, calib, rec, add_sample_data, cam_chains, instance_anns, sweep,
                       pose, float(t_end), k_sample, sample_toks[k_sample], dataroot, log_name, tok, us)
    for chain in [lidar_chain, *cam_chains.values()]:
        for a, b in zip(chain[:-1], chain[1:]):
            a["next"], b["prev"] = b["token"], a["token"]
    for aid, anns in instance_anns.items():
        for a, b in zip(anns[:-1], anns[1:]):
            a["next"], b["prev"] = b["token"], a["token"]
        actor = world.actors[aid]
        rec["instance"].append({"token": anns[0]["instance_token"], "category_token": W.token("category", CATEGORY[actor.cls]),
                                "nbr_annotations": len(anns), "first_annotation_token": anns[0]["token"],
                                "last_annotation_token": anns[-1]["token"]})
    W.write_part(dataroot, idx, rec)
    return len(key_times)


def _key_frame(s, idx: int, world: World, renderer, cams, calib, rec, add_sample_data, cam_chains, instance_anns, sweep,
               lidar_pose, t_key, k_sample, sample_tok, dataroot, log_name, tok, us):
    """Cameras, annotations and labels of one key frame."""
    cfg = s.cfg
    Wd, Ht = cfg.camera.resolution
    T_key = world.ego_pose(t_key)
    boxes_key = world.boxes_at(t_key)
    speed_key = world.speed_at(t_key)
    near = [i for i, a in enumerate(world.actors)
            if a.annotate and np.hypot(*(boxes_key[i, :2] - T_key[:2, 3])) <= ANNOTATION_RANGE]
    id_images, cam_poses, actor_poses = [], [], []
    for cam_index, cam in enumerate(cams):
        t_cam = camera_time(t_key, cam)
        T_gc = world.ego_pose(t_cam) @ cam.T_ego_from_cam
        b = world.boxes_at(t_cam)
        poses = geo.poses_2d(b[:, 0], b[:, 1], b[:, 6], b[:, 2])
        pose_of = {a.id: poses[i] for i, a in enumerate(world.actors) if a.annotate}
        rgb, depth, ids = renderer.render(cam, T_gc, pose_of, with_depth=cfg.degrade.alpha > 0, lazy_ids=True)
        if cfg.camera.renderer == "mitsuba":
            # Path-traced rgb; the labels keep the rasterised id pass, so they do not depend on
            # the renderer (the two agree geometrically: tests/simgen/test_mitsuba.py).
            rgb, _ = _mitsuba(cfg).render(world, cam, T_gc, pose_of, cfg.degrade.alpha, with_ids=False)
        if cfg.degrade.active:
            rgb = degrade_image(rgb, depth, cam, cfg, s, idx, cam_index)
        fname = f"samples/{cam.channel}/{log_name}__{cam.channel}__{us(t_cam)}.jpg"
        W.write_jpeg(dataroot / fname, rgb, cfg.camera.jpeg_quality)
        add_sample_data(cam.channel, tok("sd", cam.channel, k_sample), t_cam, k_sample, True, fname, Wd, Ht, "jpg")
        cam_chains[cam.channel].append(rec["sample_data"][-1])
        id_images.append(ids)
        cam_poses.append(T_gc)
        actor_poses.append(poses[near])
    actors = [world.actors[i] for i in near]
    vis = labels.visible_fraction(actors, actor_poses, cams, cam_poses, id_images)
    anns = []
    for n, i in enumerate(near):
        actor = world.actors[i]
        translation, size, rotation = geo.box_to_nuscenes(boxes_key[i])
        attr = labels.attribute(actor, float(speed_key[i]))
        anns.append({"token": tok("ann", actor.id, k_sample), "sample_token": sample_tok,
                     "instance_token": tok("instance", actor.id),
                     "visibility_token": labels.visibility_token(vis[n]),
                     "attribute_tokens": [W.token("attribute", attr)] if attr else [],
                     "translation": translation, "size": size, "rotation": rotation,
                     "prev": "", "next": "", "num_lidar_pts": 0, "num_radar_pts": 0})
    counts = labels.count_points_in_boxes(sweep.points_lidar, anns, lidar_pose, calib[rig.LIDAR])
    for ann, c, i in zip(anns, counts, near):
        ann["num_lidar_pts"] = c
        instance_anns.setdefault(i, []).append(ann)
    rec["sample_annotation"].extend(anns)
