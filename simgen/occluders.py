"""Extra static occluders along the ego's route (``--occlusion light|heavy``): parked vans and
hedges in the parking strips, trees and poles at the curb, between the ego and the traffic.

They are added to the world AFTER it is simulated, from their own random stream, so the actors,
their tracks and the ego's route are exactly those of the clean world. An occluder that would
touch any actor's footprint at any time (with a margin), or the existing clutter, is not
placed; intersections are left free. Being part of the world, occluders are seen consistently by
the cameras and the lidar (they join the static mesh), and they change the annotations only
through ``visibility`` and ``num_lidar_pts``: every clean object still exists.
"""
from __future__ import annotations

import dataclasses

import numpy as np
import trimesh

from . import geometry
from . import lidarseg
from .assets import Parts
from .layout import CURB_HEIGHT, Grid
from .world import World

SPACING = {"light": 18.0, "heavy": 6.0}       # metres of route per occluder, each side
MARGIN = 0.4                                   # clearance to any actor footprint, at any time
ROUTE_EXTRA = (20.0, 50.0)                     # route extended backwards / forwards (m)


def _kinds(p: Parts, kind: int, x: float, y: float, yaw: float, rng: np.random.Generator) -> tuple:
    """Add one occluder's mesh to ``p``; returns its (7,) footprint box."""
    if kind == 0:    # a van: tall box with a darker windscreen band
        l, w, h = rng.uniform(5.0, 6.0), rng.uniform(2.0, 2.2), rng.uniform(2.3, 2.7)
        color = tuple(int(c) for c in rng.integers(150, 240, 3))
        p.box((l, w, h - 0.35), (x, y, 0.35 + (h - 0.35) / 2), color, 0.5, yaw, label=lidarseg.CAR)
        p.box((0.1, w * 0.9, 0.6), (x + np.cos(yaw) * l / 2, y + np.sin(yaw) * l / 2, h - 0.6), (30, 35, 40), 0.1, yaw,
              label=lidarseg.CAR)
        return (x, y, h / 2, l, w, h, yaw)
    if kind == 1:    # a hedge
        l, w, h = rng.uniform(4.0, 7.0), rng.uniform(0.8, 1.2), rng.uniform(1.2, 1.8)
        p.box((l, w, h), (x, y, CURB_HEIGHT + h / 2), (50, int(rng.integers(90, 130)), 45), 0.35, yaw,
              label=lidarseg.VEGETATION)
        return (x, y, CURB_HEIGHT + h / 2, l, w, h, yaw)
    if kind == 2:    # a tree with a low, wide canopy
        hgt, r = rng.uniform(1.4, 2.0), rng.uniform(1.6, 2.4)
        p.cylinder((x, y, CURB_HEIGHT), (x, y, CURB_HEIGHT + hgt), 0.2, (95, 70, 50), 0.3, label=lidarseg.VEGETATION)
        p.sphere((x, y, CURB_HEIGHT + hgt + r * 0.7), r, (45, int(rng.integers(100, 140)), 50), 0.4,
                 label=lidarseg.VEGETATION)
        return (x, y, CURB_HEIGHT + hgt / 2, 0.5, 0.5, hgt, 0.0)
    # a thick pole / pillar
    hgt = rng.uniform(3.0, 5.0)
    p.cylinder((x, y, CURB_HEIGHT), (x, y, CURB_HEIGHT + hgt), 0.35, (120, 120, 125), 0.45, label=lidarseg.MANMADE)
    return (x, y, CURB_HEIGHT + hgt / 2, 0.8, 0.8, hgt, 0.0)


def add_occluders(world: World, grid: Grid, level: str, rng: np.random.Generator) -> World:
    """A copy of ``world`` with ``level`` ('none', 'light', 'heavy') occluders along the ego route."""
    if level == "none":
        return world
    ego = world.xy[0]                                          # (K, 2)
    yaw = float(world.yaw[0, 0])                              # the ego's path is straight
    heading = np.array([np.cos(yaw), np.sin(yaw)])
    horizontal = abs(heading[0]) > abs(heading[1])             # the route runs along x
    centres = grid.ys if horizontal else grid.xs
    cross = grid.xs if horizontal else grid.ys
    road_c = centres[np.argmin(np.abs(centres - (ego[0, 1] if horizontal else ego[0, 0])))]
    hw, pw = grid.road_half_width, grid.cfg.parking_width
    s0 = float(ego[0] @ heading) - ROUTE_EXTRA[0]
    s1 = float(ego[-1] @ heading) + ROUTE_EXTRA[1]
    spacing = SPACING[level]

    # Candidates: per side, one every `spacing` metres (jittered), off the intersections.
    cand = []
    for side in (-1.0, 1.0):
        for s in np.arange(s0, s1, spacing):
            s = s + rng.uniform(-0.3, 0.3) * spacing
            kind = int(rng.choice(4, p=[0.35, 0.25, 0.25, 0.15]))
            lateral = (hw - pw / 2) if kind == 0 else (hw + rng.uniform(0.6, 1.4))
            pos_axis = s * (heading[0] if horizontal else heading[1])   # the coordinate along the road
            if np.min(np.abs(cross - pos_axis)) < hw + 4.0:
                continue
            base = np.array([pos_axis, road_c + side * lateral]) if horizontal else np.array([road_c + side * lateral, pos_axis])
            cand.append((kind, base, yaw if kind in (0, 1) else 0.0))

    parts, boxes = Parts(), []
    for kind, (x, y), oyaw in cand:
        trial = Parts()
        box = np.array(_kinds(trial, kind, float(x), float(y), oyaw, rng))
        if _collides(box, world, boxes):
            continue
        parts.extend(trial)
        boxes.append(box)
    if not boxes:
        return world
    extra = parts.build()
    mesh = trimesh.util.concatenate([world.static_mesh, extra])
    for key in ("reflectivity", "lidarseg"):
        mesh.metadata[key] = np.concatenate([world.static_mesh.metadata[key], extra.metadata[key]])
    return dataclasses.replace(world, static_mesh=mesh, static_boxes=np.concatenate([world.static_boxes, boxes]),
                               meta={**world.meta, "occluders": len(boxes), "occlusion": level})


def _collides(box: np.ndarray, world: World, placed: list[np.ndarray]) -> bool:
    """Whether ``box`` comes within MARGIN of any actor at any time, the clutter, or ``placed``."""
    n, K = world.xy.shape[:2]
    sizes = np.array([a.size for a in world.actors])                          # (n, 3) l, w, h
    near = np.linalg.norm(world.xy - box[None, None, :2], axis=2).min(axis=1) < (
        np.hypot(sizes[:, 0], sizes[:, 1]) / 2 + np.hypot(box[3], box[4]) / 2 + MARGIN)
    if near.any():
        idx = np.flatnonzero(near)
        xy = world.xy[idx].reshape(-1, 2)
        b = np.zeros((len(xy), 7))
        b[:, :2] = xy
        b[:, 3:5] = np.repeat(sizes[idx, :2], K, axis=0)
        b[:, 6] = world.yaw[idx].reshape(-1)
        if geometry.bev_overlap_pairwise(np.repeat(box[None], len(b), 0), b, margin=MARGIN).any():
            return True
    others = np.concatenate([world.static_boxes, np.array(placed).reshape(-1, 7)])
    if len(others):
        return bool(geometry.bev_overlap_pairwise(np.repeat(box[None], len(others), 0), others, margin=MARGIN).any())
    return False
