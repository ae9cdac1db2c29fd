"""make(): scenes -> frames -> sensors -> writer, in worker processes, with a progress bar.

Every scene is a pure function of (settings, global seed, scene index): its generator is seeded
with ``SeedSequence([seed, scene_index])``, so the bytes do not depend on ``--workers`` or on
which scenes were already done when a run was resumed.
"""
from __future__ import annotations

import dataclasses
import json
import multiprocessing as mp
import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from . import degrade as D
from . import geometry as geo
from . import labels
from . import rig
from . import writer as W
from .config import ConfigError, SceneConfig
from .layout import Grid
from .lidar import LidarScanner
from .occluders import add_occluders
from .scene import SWEEPS_PER_KEYFRAME, keyframe_times, sample_world, sweep_end_times
from .world import CATEGORY, World

ANNOTATION_RANGE = 80.0
BASE_TIMESTAMP_US = 1_600_000_000_000_000


@dataclass(frozen=True)
class MakeSettings:
    """Everything that determines the bytes of a dataset."""
    cfg: SceneConfig
    n_scenes: int
    seed: int
    samples_per_scene: int
    version: str
    val_fraction: float = 0.2
    gl: str | None = None

    def fingerprint(self) -> dict:
        d = dataclasses.asdict(self.cfg)
        d.pop("source")
        return {"cfg": d, "seed": self.seed, "samples_per_scene": self.samples_per_scene,
                "version": self.version, "val_fraction": self.val_fraction}


def scene_rng(seed: int, idx: int, stream: int) -> np.random.Generator:
    """Independent generators per (seed, scene, stream): 0 = world, 1 = sensors."""
    return np.random.default_rng(np.random.SeedSequence([seed, idx, stream]))


def degrade_sweep(sweep, cfg: SceneConfig, rings: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """The points (n, 5) a degraded LIDAR_TOP delivers for a clean ``sweep``: fog, then the
    dropped rings and the field of view; no points at all if the lidar failed. ``rng`` is the
    scene's degradation stream (the clean sensor stream is left untouched)."""
    d = cfg.degrade
    if rig.LIDAR in d.dropped:
        return np.zeros((0, 5), np.float32)
    pts = sweep.points_lidar
    if d.alpha > 0:
        pts, _ = D.fog_lidar(pts, sweep.rho * sweep.cos_inc, sweep.range, sweep.dir_lidar, d.alpha,
                             cfg.lidar.min_return, cfg.lidar.intensity_ref_range, rng,
                             background_gain=cfg.lidar.fog_background_gain)
    if len(rings):
        pts = D.drop_rings(pts, rings)
    if d.lidar_fov < 360:
        forward_lidar = rig.T_ego_from_lidar()[:3, :3].T @ np.array([1.0, 0.0, 0.0])
        pts = D.keep_sector(pts, forward_lidar, d.lidar_fov)
    return pts


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
        points = degrade_sweep(sweep, cfg, dropped_rings, rng_degrade) if cfg.degrade.active else sweep.points_lidar
        W.write_pointcloud(dataroot / fname, points)
        pose = add_sample_data(rig.LIDAR, sd_tok, float(t_end), k_sample, is_key, fname, 0, 0, "pcd")
        lidar_chain.append(rec["sample_data"][-1])
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


def _worker_init(gl):
    # llvmpipe keeps its default thread count in every worker: measured, 2 workers with 2 render
    # threads each finish sooner here than with 1 each (33.8 s against 36.7 s, 4 scenes).
    if gl:
        os.environ["PYOPENGL_PLATFORM"] = gl


def _task(args):
    s, dataroot, idx, threads = args
    return idx, generate_scene(s, dataroot, idx, threads)


def check_resume(s: MakeSettings, dataroot: Path) -> list[int]:
    """Scenes still to do. Refuses a dataroot that holds parts made with other settings."""
    settings_file = dataroot / W.PARTS_DIR / "settings.json"
    fp = json.loads(W.dump_json(s.fingerprint()))
    if settings_file.exists():
        try:
            old = json.loads(settings_file.read_text())
        except json.JSONDecodeError:
            old = None
        if old is not None and {k: v for k, v in old.items() if k != "n_scenes"} != fp:
            old_flat, new_flat = _flatten(old), _flatten(fp)
            differ = sorted(k for k in old_flat.keys() | new_flat.keys()
                            if k != "n_scenes" and old_flat.get(k) != new_flat.get(k))
            raise ConfigError(f"{dataroot}: holds a dataset made with other settings (differing: "
                              f"{', '.join(differ[:6])}{', ...' if len(differ) > 6 else ''}); "
                              f"use another --out or delete it")
    W.write_atomic(settings_file, W.dump_json(fp))
    return [i for i in range(s.n_scenes) if not W.part_path(dataroot, i).exists()]


def _flatten(d: dict, prefix: str = "") -> dict:
    """Nested dicts -> {"a.b.c": leaf}."""
    out = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_flatten(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


def write_degradation_record(s: MakeSettings, dataroot: Path) -> None:
    """``<version>/degradation.json``: every degradation setting, the derived fog extinction and
    visibility, the dropped rings per scene, and the pairing contract. Written for clean sets
    too (all off), so that a set always says what it is."""
    d = s.cfg.degrade
    rings = {f"scene-{i:04d}": [int(r) for r in D.choose_rings(d.beam_drop, scene_rng(s.seed, i, 2))]
             for i in range(s.n_scenes)} if d.beam_drop else {}
    record = {
        "settings": dataclasses.asdict(d),
        "fog_alpha_per_m": d.alpha,
        "fog_visibility_m": D.visibility_of(d.alpha) if d.alpha > 0 else None,
        "failed_sensors": list(d.dropped),
        "dropped_rings": rings,
        "preset": s.cfg.name,
        "seed": s.seed,
        "labels": ("clean world: sample_annotation, instance, sample and ego_pose equal those of the "
                   "undegraded run with the same preset, seed and scene count"
                   if d.occlusion == "none" else
                   "occluders are part of the world: the same objects, tracks and poses as the clean run, but "
                   "sample_annotation visibility and num_lidar_pts reflect the occluders"),
    }
    W.write_atomic(dataroot / s.version / "degradation.json", W.dump_json(record))


def make(s: MakeSettings, dataroot: Path, workers: int, progress: bool = True) -> dict:
    """Generate (or finish) a dataset. Returns a summary with timings and table sizes."""
    from tqdm import tqdm
    dataroot = Path(dataroot)
    todo = check_resume(s, dataroot)
    start = time.perf_counter()
    done_samples = 0
    bar = tqdm(total=s.n_scenes, initial=s.n_scenes - len(todo), unit="scene", disable=not progress,
               desc="simgen make", dynamic_ncols=True)
    n_proc = max(1, min(workers, len(todo)))
    # The cores left to each worker process cast its lidar rays in parallel.
    threads = max(1, len(os.sched_getaffinity(0)) // n_proc)
    tasks = [(s, dataroot, i, threads) for i in todo]
    if n_proc == 1:
        results = map(_task, tasks)
        pool = None
    else:
        ctx = mp.get_context("spawn")
        pool = ctx.Pool(n_proc, initializer=_worker_init, initargs=(s.gl,))
        results = pool.imap_unordered(_task, tasks)
    try:
        for _idx, n in results:
            done_samples += n
            bar.update(1)
            bar.set_postfix(samples_per_s=f"{done_samples / (time.perf_counter() - start):.2f}")
    finally:
        if pool is not None:
            pool.close()
            pool.join()
        bar.close()
    counts = W.merge(dataroot, s.version, s.n_scenes, s.val_fraction)
    write_degradation_record(s, dataroot)
    return {"scenes": s.n_scenes, "generated_scenes": len(todo), "samples": counts["sample"],
            "seconds": time.perf_counter() - start, "tables": counts}
