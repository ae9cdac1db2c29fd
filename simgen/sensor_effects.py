"""What the weather and the degradation make of a clean sensor reading: the sweep a degraded
LIDAR_TOP delivers and the image a degraded camera delivers, each the composition, in a fixed
order, of the pure functions of simgen.degrade and simgen.weather on the clean data, each drawing
from its own stream (simgen.settings), so the clean data and the labels stay the same bytes.
"""
from __future__ import annotations

import numpy as np

from . import degrade
from . import lidarseg
from . import rig
from .config import SceneConfig
from .lidar import Sweep
from .settings import WeatherStreams, scene_rng
from .weather import lidar_sweep, rain_lidar, snow_lidar


def degrade_sweep(sweep: Sweep, cfg: SceneConfig, rings: np.ndarray, rng: np.random.Generator,
                  weather: WeatherStreams) -> tuple[np.ndarray, np.ndarray]:
    """The points (n, 5) a degraded LIDAR_TOP delivers for a clean ``sweep``, and their lidarseg
    labels (n,) uint8: fog, rain and snowfall (their clutter returns are labelled noise), then the
    dropped rings and the field of view; no points at all if the lidar failed. ``rng`` is the
    scene's degradation stream and ``weather`` its weather streams (the clean sensor stream is
    left untouched)."""
    d = cfg.degrade
    if rig.LIDAR in d.dropped:
        return np.zeros((0, 5), np.float32), np.zeros(0, np.uint8)
    # The label rides along as a sixth column, and each row's ray as a seventh (for the rain and
    # snow): the degradation steps keep or drop whole rows and carry the columns after the ring
    # unchanged (their contract in simgen.degrade).
    pts = lidar_sweep.with_ray_column(np.concatenate([sweep.points_lidar, sweep.label[:, None].astype(np.float32)],
                                                     axis=1))
    if d.alpha > 0:
        pts, is_fog = degrade.fog_lidar(pts, sweep.rho * sweep.cos_inc, sweep.range, sweep.dir_lidar, d.alpha,
                                        cfg.lidar.min_return, cfg.lidar.intensity_ref_range, rng)
        pts[is_fog, 5] = lidarseg.NOISE
    # Rain, then snowfall: each a pure function of the points and its own stream.
    if cfg.weather.particles:
        rays = lidar_sweep.sweep_rays(pts, sweep, cfg.lidar.min_return, d.alpha)
        pts, rays = rain_lidar.rain_sweep(pts, rays, cfg.weather.rain, cfg.lidar, weather.rain_lidar)
        pts, rays = snow_lidar.snow_sweep(pts, rays, cfg.weather.snow, cfg.lidar, weather.snow_lidar)
    if len(rings):
        pts = degrade.drop_rings(pts, rings)
    if d.lidar_fov < 360:
        forward_lidar = rig.T_ego_from_lidar()[:3, :3].T @ np.array([1.0, 0.0, 0.0])
        pts = degrade.keep_sector(pts, forward_lidar, d.lidar_fov)
    return np.ascontiguousarray(pts[:, :5]), pts[:, 5].astype(np.uint8)


def degrade_image(rgb: np.ndarray, depth: np.ndarray, cam: rig.Camera, cfg: SceneConfig, s, idx: int,
                  cam_index: int, weather: WeatherStreams, t_cam: float, paved: np.ndarray | None = None,
                  v_cam: np.ndarray | None = None) -> np.ndarray:
    """The image a degraded camera delivers at scene time ``t_cam``: fog on the rendered range,
    then rain and snowfall, then lens dirt (the same blobs in every frame of a scene: their rng is
    keyed on the scene and the camera), then the night's sensor noise; black if the camera
    failed. ``weather`` holds the scene's weather streams; ``paved`` (H, W) bool the pixels the
    rain wets (None: no wet road), ``v_cam`` (3,) the camera's velocity in its frame (m/s; None:
    at rest), which slants the rain's streaks."""
    from .camera import depth_to_range
    from .weather import veil
    d = cfg.degrade
    if cam.channel in d.dropped:
        return np.zeros_like(rgb)
    if d.alpha > 0 and cfg.camera.renderer == "pyrender":   # Mitsuba renders fog as a medium
        # The fog scatters the light there is: daylight's airlight, or at night the night sky's.
        airlight = veil.rendered_sky(True) if cfg.weather.night else degrade.AIRLIGHT
        rgb = degrade.fog_image(rgb, depth_to_range(depth, cam.K), d.alpha, airlight)
    # Rain, then snowfall, on the rendered range.
    if cfg.weather.particles:
        from .weather import rain_camera, snow_camera
        down_cam = cam.T_ego_from_cam[:3, :3].T @ np.array([0.0, 0.0, -1.0])    # the ego stays level
        v = np.zeros(3) if v_cam is None else v_cam
        sky = veil.sky_colour(rgb, depth, veil.rendered_sky(cfg.weather.night))
        rgb = rain_camera.rain_image(rgb, depth, cam.K, cfg.weather.rain, weather.rain_camera, down_cam, v, paved, sky)
        rgb = snow_camera.snow_image(rgb, depth, cam.K, cfg.weather.snow, weather.snow_camera, down_cam, v, sky)
    if d.lens_occlusion:
        rgb = degrade.lens_dirt(rgb, d.lens_occlusion, scene_rng(s.seed, idx, 100 + cam_index))
    # The night's sensor noise, last: it is the camera's own.
    if cfg.weather.night:
        from .weather import night_sensor
        rgb = night_sensor.add_noise(rgb, night_sensor.binning(cam.resolution), weather.night_camera)
    return rgb
