"""One scene, a pure function of (settings, scene index): world -> frames -> :class:`SceneRecords`.

The scene's random streams are seeded with ``SeedSequence([seed, scene_index, stream])``, so its
bytes do not depend on ``--workers``, on the backend, or on which scenes were already done when
a run was resumed. Nothing is written here: the records hold the tables' rows and every file's
bytes, and :func:`simgen.writer.write_scene` writes them. :mod:`simgen.make` runs the scenes in
worker processes or Ray tasks.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from . import geometry
from . import labels
from . import rig
from . import writer
from .config import SceneConfig
from .layout import Grid
from .lidar import LidarScanner, Sweep
from .sensor_effects import degrade_image, degrade_sweep
from .occluders import add_occluders
from .scene import SWEEPS_PER_KEYFRAME, keyframe_times, sample_world, sweep_end_times
from .settings import MakeSettings, WeatherStreams, degradation_stream, scene_rng, weather_streams
from .world import CATEGORY, World

if TYPE_CHECKING:                  # pyrender is imported by the worker that renders, when it renders
    from .camera import Renderer
    from .weather.night import NightScene

ANNOTATION_RANGE = 80.0
BASE_TIMESTAMP_US = 1_600_000_000_000_000


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


@dataclass(frozen=True)
class SceneContext:
    """What every step of one scene reads: its settings, index, world and cameras, its names and
    clock, and the rows its sensor files refer to."""
    s: MakeSettings
    idx: int
    world: World
    cams: list[rig.Camera]
    calib: dict[str, dict]         # channel -> calibrated_sensor row
    sample_tokens: list[str]       # one per key frame

    @property
    def cfg(self) -> SceneConfig:
        return self.s.cfg

    @property
    def log_name(self) -> str:
        return f"simgen-{self.s.seed}-{self.idx:04d}"

    def token(self, *parts) -> str:
        return writer.token(self.s.seed, self.idx, *parts)

    def us(self, t: float) -> int:
        """Scene seconds -> the scene's timestamp (microseconds); scenes lie 1000 s apart."""
        return int(BASE_TIMESTAMP_US + self.idx * 1_000_000_000 + round(t * 1e6))


@dataclass
class Sensors:
    """The scene's sensors and the random streams they draw from."""
    renderer: Renderer             # holding this scene's world
    scanner: LidarScanner
    rng_sensor: np.random.Generator
    dropped_rings: np.ndarray      # (k,) int, the rings a beam-drop lidar loses
    rng_degrade: np.random.Generator
    weather: WeatherStreams
    face_class: np.ndarray | None  # (F,) uint8 lidarseg class per rendered face; None without dense labels
    night: NightScene | None = None  # the street and vehicle lights; None by day


@dataclass(frozen=True)
class LidarKeyFrame:
    """The key-frame sweep that a key frame's cameras and labels go with."""
    sweep: Sweep
    ego_pose: dict                 # its ego_pose row
    t: float                       # scene seconds
    k_sample: int


def scene_records(s: MakeSettings, idx: int, threads: int = 1) -> writer.SceneRecords:
    """Scene ``idx`` rendered, scanned and labelled, in memory.

    ``threads``: the lidar's ray casting is split over this many threads (the bytes do not depend
    on it). numpy's BLAS is held to one thread meanwhile: the products here are (n, 3) @ (3, 3),
    which gain nothing from threads, and its idle threads would spin after each one.
    """
    from threadpoolctl import threadpool_limits
    with threadpool_limits(limits=1, user_api="blas"):
        return _scene_records(s, idx, threads)


def generate_scene(s: MakeSettings, dataroot: Path, idx: int, threads: int = 1) -> int:
    """Make scene ``idx`` and write it into ``dataroot``. Returns its number of samples."""
    records = scene_records(s, idx, threads)
    writer.write_scene(Path(dataroot), records)
    return records.n_samples


def _scene_records(s: MakeSettings, idx: int, threads: int) -> writer.SceneRecords:
    world = build_world(s, idx)
    rng_sensor = scene_rng(s.seed, idx, 1)
    renderer = _renderer(s.cfg, s.gl)
    renderer.set_world(world, key=(s.seed, idx, id(world)))
    scanner = LidarScanner(s.cfg.lidar, world, threads=threads)
    # Degradation draws from its own stream, so the clean sensor data (and the labels counted
    # on them) are the same bytes with or without it: paired datasets.
    dropped_rings, rng_degrade = degradation_stream(s, idx)
    # The faces' classes serve the dense labels and tell the rain which pixels are paved.
    face_class = labels.face_classes(world, renderer.face_owner) if s.dense_labels or s.cfg.weather.rain > 0 else None
    sensors = Sensors(renderer, scanner, rng_sensor, dropped_rings, rng_degrade, weather_streams(s, idx), face_class,
                      _night_scene(s, world))

    records = writer.SceneRecords(idx)
    scene = _add_scene_rows(s, idx, world, records)
    for j, t_end in enumerate(sweep_end_times(s.samples_per_scene)):
        key_frame = _add_sweep(scene, sensors, records, j, float(t_end))
        if key_frame is not None:
            _add_key_frame(scene, sensors, records, key_frame)
    _link_rows(scene, records)
    return records


def _night_scene(s: MakeSettings, world: World) -> NightScene | None:
    """The night's light sources, a pure function of the world and its layout (no stream drawn:
    the night's world, poses and labels are the day's); None by day."""
    if not s.cfg.weather.night:
        return None
    from .weather.night import night_scene
    return night_scene(world, Grid(s.cfg.layout))


def _add_scene_rows(s: MakeSettings, idx: int, world: World, records: writer.SceneRecords) -> SceneContext:
    """The scene's log, map (and its image), sensor calibrations, key frames and scene rows."""
    cams = rig.cameras(s.cfg.camera.resolution)
    key_times = keyframe_times(s.samples_per_scene)
    calib = {cam.channel: writer.calibrated_sensor_row(writer.token(s.seed, idx, "calib", cam.channel), cam.channel,
                                                       cam.translation, cam.rotation, cam.K) for cam in cams}
    calib[rig.LIDAR] = writer.calibrated_sensor_row(writer.token(s.seed, idx, "calib", rig.LIDAR), rig.LIDAR,
                                                    rig.LIDAR_TRANSLATION, rig.lidar_rotation())
    sample_tokens = [writer.token(s.seed, idx, "sample", k) for k in range(len(key_times))]
    scene = SceneContext(s, idx, world, cams, calib, sample_tokens)

    tok = scene.token
    log_tok, map_tok, scene_tok = tok("log"), tok("map"), tok("scene")
    map_file = f"maps/{map_tok}.png"
    records.files[map_file] = writer.encode_png(world.drivable)
    rows = records.tables
    rows["log"].append(writer.log_row(log_tok, scene.log_name, f"simgen-{s.cfg.name}"))
    rows["map"].append(writer.map_row(map_tok, log_tok, map_file))
    rows["calibrated_sensor"].extend(calib.values())
    rows["sample"].extend(writer.sample_rows(scene.sample_tokens, [scene.us(t) for t in key_times], scene_tok))
    description = " ".join(filter(None, [
        f"simgen preset {s.cfg.name}, seed {s.seed}, scene {idx}. {world.description}", s.cfg.degrade.describe(),
        s.cfg.weather.describe()]))
    rows["scene"].append(writer.scene_row(scene_tok, log_tok, scene.sample_tokens, f"scene-{idx:04d}", description))
    return scene


@dataclass(frozen=True)
class SensorFile:
    """One file a sensor delivers, at scene time ``t``, under key frame ``k_sample``."""
    channel: str
    token: str                     # of its sample_data, and of its ego_pose
    t: float
    k_sample: int
    is_key_frame: bool
    filename: str                  # relative to the dataroot
    data: bytes
    width: int = 0                 # pixels; 0 for the lidar
    height: int = 0


def _add_sensor_file(scene: SceneContext, records: writer.SceneRecords, f: SensorFile) -> dict:
    """A sensor file with its ego_pose and sample_data rows. Returns the ego_pose row."""
    fmt = "pcd" if f.channel == rig.LIDAR else "jpg"
    pose = writer.ego_pose_row(f.token, scene.us(f.t), scene.world.ego_pose(f.t))
    records.tables["ego_pose"].append(pose)
    records.tables["sample_data"].append(writer.sample_data_row(
        f.token, scene.sample_tokens[f.k_sample], scene.calib[f.channel]["token"], scene.us(f.t), fmt,
        f.is_key_frame, f.width, f.height, f.filename))
    records.files[f.filename] = f.data
    return pose


def _add_sweep(scene: SceneContext, sensors: Sensors, records: writer.SceneRecords, j: int,
               t_end: float) -> LidarKeyFrame | None:
    """Lidar sweep ``j``: a key frame's goes to samples/ (with its lidarseg labels), the others
    to sweeps/, under the next sample's token. Returns the key frame it completes, if any."""
    cfg = scene.cfg
    is_key = (j + 1) % SWEEPS_PER_KEYFRAME == 0
    k_sample = min(j // SWEEPS_PER_KEYFRAME, len(scene.sample_tokens) - 1)
    sweep = sensors.scanner.scan(t_end, sensors.rng_sensor, missed_rays=cfg.weather.particles)
    sd_tok = scene.token("sd", rig.LIDAR, j)
    folder = "samples" if is_key else "sweeps"
    filename = f"{folder}/{rig.LIDAR}/{scene.log_name}__{rig.LIDAR}__{scene.us(t_end)}.pcd.bin"
    points, point_labels = (degrade_sweep(sweep, cfg, sensors.dropped_rings, sensors.rng_degrade, sensors.weather)
                            if cfg.degrade.active or cfg.weather.active else (sweep.points_lidar, sweep.label))
    pose = _add_sensor_file(scene, records, SensorFile(rig.LIDAR, sd_tok, t_end, k_sample, is_key, filename,
                                                       writer.encode_pointcloud(points)))
    if not is_key:
        return None
    if len(points):
        # nuScenes-lidarseg labels the key frames' points (a failed lidar has none to label).
        seg_file = f"lidarseg/{scene.s.version}/{sd_tok}_lidarseg.bin"
        records.files[seg_file] = point_labels.tobytes()
        records.tables["lidarseg"].append(writer.lidarseg_row(sd_tok, seg_file))
    return LidarKeyFrame(sweep, pose, t_end, k_sample)


def _add_key_frame(scene: SceneContext, sensors: Sensors, records: writer.SceneRecords,
                   key_frame: LidarKeyFrame) -> None:
    """The six cameras of a key frame, and the annotations of the objects within
    ANNOTATION_RANGE, labelled from the images and the key-frame sweep."""
    world = scene.world
    T_global_from_ego = world.ego_pose(key_frame.t)
    boxes = world.boxes_at(key_frame.t)
    near = [i for i, a in enumerate(world.actors)
            if a.annotate and np.hypot(*(boxes[i, :2] - T_global_from_ego[:2, 3])) <= ANNOTATION_RANGE]
    id_images, cam_poses, actor_poses = _add_cameras(scene, sensors, records, key_frame, near)
    vis = labels.visible_fraction([world.actors[i] for i in near], actor_poses, scene.cams, cam_poses, id_images)
    speed = world.speed_at(key_frame.t)
    anns = []
    for n, i in enumerate(near):
        actor = world.actors[i]
        anns.append(writer.annotation_row(
            scene.token("ann", actor.id, key_frame.k_sample), scene.sample_tokens[key_frame.k_sample],
            scene.token("instance", actor.id), labels.visibility_token(vis[n]),
            labels.attribute(actor, float(speed[i])), boxes[i]))
    counts = labels.count_points_in_boxes(key_frame.sweep.points_lidar, anns, key_frame.ego_pose,
                                          scene.calib[rig.LIDAR])
    for ann, c in zip(anns, counts):
        ann["num_lidar_pts"] = c
    records.tables["sample_annotation"].extend(anns)


def _add_cameras(scene: SceneContext, sensors: Sensors, records: writer.SceneRecords, key_frame: LidarKeyFrame,
                 near: list[int]) -> tuple[list, list[np.ndarray], list[np.ndarray]]:
    """Render the six cameras of a key frame, each at the time the sweep crosses its axis, with
    their dense labels when asked for. Returns per camera its actor-id image, T_global_from_cam
    (4, 4) and the (m, 4, 4) poses of the ``near`` actors at its time."""
    cfg, world = scene.cfg, scene.world
    width, height = cfg.camera.resolution
    id_images, cam_poses, actor_poses = [], [], []
    for cam_index, cam in enumerate(scene.cams):
        t_cam = camera_time(key_frame.t, cam)
        T_global_from_cam = world.ego_pose(t_cam) @ cam.T_ego_from_cam
        b = world.boxes_at(t_cam)
        poses = geometry.poses_2d(b[:, 0], b[:, 1], b[:, 6], b[:, 2])     # (n, 4, 4) T_global_from_box
        pose_of = {a.id: poses[i] for i, a in enumerate(world.actors) if a.annotate}
        with_depth = cfg.degrade.alpha > 0 or cfg.weather.particles or scene.s.dense_labels
        lights = sensors.night.at(poses) if sensors.night is not None else None
        rgb, depth, ids = sensors.renderer.render(cam, T_global_from_cam, pose_of, with_depth=with_depth, lazy_ids=True,
                                                  night=lights)
        if cfg.camera.renderer == "mitsuba":
            # Path-traced rgb; the labels keep the rasterised id pass, so they do not depend on
            # the renderer (the two agree geometrically: tests/simgen/test_mitsuba.py).
            rgb, _ = _mitsuba(cfg).render(world, cam, T_global_from_cam, pose_of, cfg.degrade.alpha, with_ids=False)
        if cfg.degrade.active or cfg.weather.active:
            paved = _paved(ids, sensors.face_class) if cfg.weather.rain > 0 else None
            rgb = degrade_image(rgb, depth, cam, cfg, scene.s, scene.idx, cam_index, sensors.weather, t_cam, paved,
                                _camera_velocity(world, cam, t_cam))
        filename = f"samples/{cam.channel}/{scene.log_name}__{cam.channel}__{scene.us(t_cam)}.jpg"
        sd_tok = scene.token("sd", cam.channel, key_frame.k_sample)
        jpeg = writer.encode_jpeg(rgb, cfg.camera.jpeg_quality)
        _add_sensor_file(scene, records, SensorFile(cam.channel, sd_tok, t_cam, key_frame.k_sample, True, filename,
                                                    jpeg, width, height))
        if scene.s.dense_labels:
            _add_dense_labels(records, filename, depth, ids, sensors.face_class)
        id_images.append(ids)
        cam_poses.append(T_global_from_cam)
        actor_poses.append(poses[near])
    return id_images, cam_poses, actor_poses


def _paved(ids, face_class: np.ndarray) -> np.ndarray:
    """(H, W) bool, the paved pixels of a camera's :class:`~simgen.camera.IdImage` ``ids``."""
    from .weather.rain_camera import paved_pixels
    return paved_pixels(ids.face, face_class)


def _camera_velocity(world: World, cam: rig.Camera, t: float, dt: float = 0.005) -> np.ndarray:
    """(3,) the camera's velocity through the (still) air at scene time t, in its own frame (m/s):
    a central difference of its position over +-dt, the ego's turning included."""
    T_before, T_after = (world.ego_pose(t + e) @ cam.T_ego_from_cam for e in (-dt, dt))
    return T_after[:3, :3].T @ (T_after[:3, 3] - T_before[:3, 3]) / (2 * dt)


def _add_dense_labels(records: writer.SceneRecords, image_file: str, depth: np.ndarray, ids,
                      face_class: np.ndarray) -> None:
    """The dense labels of one camera image, from its clean render (a degraded image keeps the
    labels of the scene it shows): depth (H, W) float32 camera z and ``ids``, its
    :class:`~simgen.camera.IdImage`."""
    depth_file, seg_file = writer.dense_label_files(image_file)
    records.files[depth_file] = writer.encode_png(labels.depth_image(depth), writer.DENSE_PNG_LEVEL)
    records.files[seg_file] = writer.encode_png(labels.seg_image(ids.face, face_class), writer.DENSE_PNG_LEVEL)


def _link_rows(scene: SceneContext, records: writer.SceneRecords) -> None:
    """Chain each sensor's sample_data and each object's annotations in time order, and add an
    instance per annotated object (in the order of their first annotation)."""
    rows = records.tables
    by_sensor: dict[str, list[dict]] = {}
    for row in rows["sample_data"]:
        by_sensor.setdefault(row["calibrated_sensor_token"], []).append(row)
    by_instance: dict[str, list[dict]] = {}
    for ann in rows["sample_annotation"]:
        by_instance.setdefault(ann["instance_token"], []).append(ann)
    for chain in [*by_sensor.values(), *by_instance.values()]:
        writer.link(chain)
    category = {scene.token("instance", a.id): CATEGORY[a.cls] for a in scene.world.actors if a.annotate}
    rows["instance"].extend(writer.instance_row(anns, category[tok]) for tok, anns in by_instance.items())
