"""A scene's timeline and world: ``sample_world(cfg, rng, n_samples)`` is the whole recipe.

Timeline (seconds from the scene start): the lidar spins at 20 Hz and sweep j ends at
``j * LIDAR_PERIOD``; key frames (samples) are the sweeps ending at 0.5 s, 1.0 s, ... (2 Hz),
so the first sample has 10 earlier sweeps. The world is simulated on the lidar period until
half a second after the last key frame.
"""
from __future__ import annotations

import numpy as np

from .config import SceneConfig
from .layout import Grid, build_static, drivable_mask
from .motion import simulate
from .traffic import place_actors
from .world import World

LIDAR_PERIOD = 0.05
KEYFRAME_PERIOD = 0.5
SWEEPS_PER_KEYFRAME = int(round(KEYFRAME_PERIOD / LIDAR_PERIOD))


def keyframe_times(n_samples: int) -> np.ndarray:
    """(S,) key-frame times: the end of every tenth sweep, from 0.5 s."""
    return KEYFRAME_PERIOD * (1 + np.arange(n_samples))


def sweep_end_times(n_samples: int) -> np.ndarray:
    """(S * 10,) end times of all lidar sweeps up to the last key frame."""
    return LIDAR_PERIOD * (1 + np.arange(n_samples * SWEEPS_PER_KEYFRAME))


def sample_world(cfg: SceneConfig, rng: np.random.Generator, n_samples: int) -> World:
    """Procedural world for one scene with ``n_samples`` key frames."""
    duration = float(keyframe_times(n_samples)[-1] + KEYFRAME_PERIOD)
    times = LIDAR_PERIOD * np.arange(int(round(duration / LIDAR_PERIOD)) + 1)
    grid = Grid(cfg.layout)
    static_mesh, clutter = build_static(grid, rng)
    plans = place_actors(cfg, grid, clutter, duration, rng)
    xy, yaw, speed = simulate(plans, clutter, times)
    size = np.array([p.actor.size for p in plans])
    z = grid.ground_z(xy) + size[:, 2:3] / 2
    z[0] = 0.0  # the ego's track is its ego_pose, whose z is 0 by nuScenes convention
    return World(
        extent=grid.extent, static_mesh=static_mesh, static_boxes=clutter,
        actors=[p.actor for p in plans], times=times, xy=xy, z=z,
        yaw=yaw, speed=speed,
        drivable=drivable_mask(grid),
        description=cfg.description,
    )
