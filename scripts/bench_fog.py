"""Fog's benchmarks: its share of a 1600x900 sample's time, and what it does to one clean urban
sweep per severity (the lidar_fog_* keys; see scripts/bench.py and docs/fog.md)."""
from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np

from bench_common import median_ms, run_make

# Bands of the clean range (m); the kept ratios leave out the first.
FOG_BANDS = ((0.0, 10.0), (10.0, 30.0), (30.0, 50.0), (50.0, np.inf))


def bench_fog(quick: bool) -> dict:
    """Fog's share of a 1600x900 sample: the degradation functions on one sample's data (6 camera
    images with their depth, 10 sweeps), timed alone, over the same sample made without fog."""
    from simgen import rig
    from simgen.config import load_preset, with_degradation
    from simgen.lidar import LidarScanner
    from simgen.mitsuba_camera import actor_poses_at
    from simgen.pipeline import _renderer, build_world
    from simgen.sensor_effects import degrade_image, degrade_sweep
    from simgen.settings import MakeSettings, weather_streams
    cfg = with_degradation(load_preset("urban"), fog=5)
    s = MakeSettings(cfg, 1, 0, 1, "v1.0-sim")
    world = build_world(s, 0)
    r = _renderer(cfg, None)
    r.set_world(world, key="bench-fog")
    cams = rig.cameras(cfg.camera.resolution)
    poses = actor_poses_at(world, 0.5)
    frames = []
    for cam in cams:
        rgb, depth, _ = r.render(cam, world.ego_pose(0.5) @ cam.T_ego_from_cam, poses)
        frames.append((cam, rgb, depth))
    scanner = LidarScanner(cfg.lidar, world)
    sweeps = [scanner.scan(0.05 * (k + 1), np.random.default_rng(k)) for k in range(10)]

    weather = weather_streams(s, 0)

    def fog_one_sample():
        for i, (cam, rgb, depth) in enumerate(frames):
            degrade_image(rgb, depth, cam, cfg, s, 0, i, weather, 0.5)
        for sw in sweeps:
            degrade_sweep(sw, cfg, np.zeros(0, int), np.random.default_rng(0), weather)

    ms = median_ms(fog_one_sample, 3 if quick else 7)
    sample_s = render_sample_s(quick)
    return {"fog_ms_per_sample_1600x900": ms, "fog_overhead_pct": 100 * ms / 1000 / sample_s,
            **lidar_fog_figures(sweeps[0], cfg.lidar)}


def render_sample_s(quick: bool) -> float:
    """Seconds per 1600x900 sample (one worker), as sample_s_1600x900."""
    with tempfile.TemporaryDirectory() as tmp:
        samples = 2 if quick else 4
        secs = run_make(Path(tmp) / "d", 1, samples, 1, "1600x900")
        return secs / samples


def lidar_fog_figures(sw, lidar) -> dict:
    """What fog does to one clean sweep ``sw``, severity 0..5 (see the lidar_fog_* keys)."""
    from simgen import degrade
    rho_cos = sw.rho * sw.cos_inc
    band = np.digitize(sw.range, [b[1] for b in FOG_BANDS[:-1]])          # (n,) band index by clean range

    def per_band(mask: np.ndarray) -> list[int]:
        return [int((mask & (band == b)).sum()) for b in range(len(FOG_BANDS))]

    out = {k: [] for k in ("points", "returns", "returns_by_band", "silent", "equation", "kept", "won",
                           "intensity_0", "iqr")}
    for alpha in degrade.FOG_ALPHA:
        pts, is_fog = degrade.fog_lidar(sw.points_lidar, rho_cos, sw.range, sw.dir_lidar, alpha, lidar.min_return,
                                        lidar.intensity_ref_range, np.random.default_rng(0))
        out["points"].append(len(pts))
        out["returns"].append(int(is_fog.sum()))
        if alpha == 0:
            out["returns_by_band"].append([0] * len(FOG_BANDS))
            out["silent"].append(0)
            continue
        out["iqr"].append(fog_range_iqr(sw, rho_cos, pts, is_fog, alpha, lidar.min_return))
        f = degrade.fog_returns(rho_cos, sw.range, alpha, lidar.min_return)
        if int(f.kept.sum()) != len(pts) or int((f.kept & f.fog_wins).sum()) != int(is_fog.sum()):
            raise RuntimeError("degrade.fog_returns and degrade.fog_lidar disagree on the same sweep")
        expected = f.p_hard >= lidar.min_return                            # the lidar equation alone
        hard = f.kept & ~f.fog_wins
        out["returns_by_band"].append(per_band(f.kept & f.fog_wins))
        out["silent"].append(int((expected & ~f.kept).sum()))
        eq, kept, won = per_band(expected)[1:], per_band(hard)[1:], per_band(expected & f.fog_wins)[1:]
        out["equation"].append(eq)
        out["kept"].append([round(k / e, 4) if e else None for k, e in zip(kept, eq)])
        out["won"].append([round(w / e, 4) if e else None for w, e in zip(won, eq)])
        out["intensity_0"].append(intensity_ratio_fog_count(sw.points_lidar, alpha))
    return {"lidar_fog_points_by_severity": out["points"], "lidar_fog_returns_by_severity": out["returns"],
            "lidar_fog_returns_by_band": out["returns_by_band"], "lidar_fog_silent_rays_by_severity": out["silent"],
            "lidar_fog_equation_by_band": out["equation"], "lidar_fog_kept_ratio_by_band": out["kept"],
            "lidar_fog_won_share_by_band": out["won"], "lidar_fog_intensity_0_by_severity": out["intensity_0"],
            "lidar_fog_range_iqr_by_severity": out["iqr"], "lidar_fog_haze_returns": haze_returns(sw, rho_cos, lidar)}


def fog_range_iqr(sw, rho_cos: np.ndarray, pts: np.ndarray, is_fog: np.ndarray, alpha: float,
                  min_return: float) -> list[float] | None:
    """Interquartile ranges (m) of the fog returns' distances [along their rays (from each ray's
    origin), from the sensor at the sweep's end (which adds the ego's motion during the sweep)]."""
    from simgen import degrade
    if not is_fog.any():
        return None
    kept = degrade.fog_returns(rho_cos, sw.range, alpha, min_return).kept
    ray = np.nonzero(kept)[0][is_fog]
    origin = sw.points_lidar[ray, :3] - sw.dir_lidar[ray] * sw.range[ray, None]

    def iqr(x: np.ndarray) -> float:
        q1, q3 = np.percentile(x, [25, 75])
        return round(float(q3 - q1), 3)

    return [iqr(np.linalg.norm(pts[is_fog, :3] - origin, axis=1)), iqr(np.linalg.norm(pts[is_fog, :3], axis=1))]


def haze_returns(sw, rho_cos: np.ndarray, lidar, visibility: float = 2000.0) -> list[int]:
    """[fog returns, rays] of the sweep in haze of ``visibility`` metres."""
    from simgen import degrade
    alpha = degrade.alpha_of_visibility(visibility)
    _, is_fog = degrade.fog_lidar(sw.points_lidar, rho_cos, sw.range, sw.dir_lidar, alpha, lidar.min_return,
                                  lidar.intensity_ref_range, np.random.default_rng(0))
    return [int(is_fog.sum()), len(sw.range)]


def intensity_ratio_fog_count(points_lidar: np.ndarray, alpha: float) -> int:
    """Clean returns (n, 5) whose attenuated 8-bit intensity round(i exp(-2 alpha R)) is 0, R
    ranged by the points themselves, as a procedure that sees only the point cloud does."""
    r0 = np.linalg.norm(points_lidar[:, :3], axis=1)
    i_att = np.round(points_lidar[:, 3] * np.exp(-2 * alpha * r0))
    return int(((i_att == 0) & (points_lidar[:, 3] > 0)).sum())
