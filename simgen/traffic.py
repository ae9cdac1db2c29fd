"""Actor placement: the ego, moving and parked vehicles, cycles, pedestrians, cones and barriers.

Every actor gets a path (origin, heading; some moving vehicles turn at an intersection ahead,
:mod:`simgen.turns`) and a desired speed; static actors get speed 0. Placement is
rejection-sampled so that no two footprints overlap at the start; the motion model
(:mod:`simgen.motion`) keeps it that way. The shared machinery is in :mod:`simgen.placement`,
road works in :mod:`simgen.roadworks`, bus stops and trailers in :mod:`simgen.curbside`.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from . import assets
from .config import ActorsConfig, SceneConfig
from .curbside import HITCH_GAP, hitch, place_bus_stops, place_parked_trailers, place_train
from .layout import CURB_HEIGHT, MAP_PAD, Grid
# SIZE_MEAN and make_actor are read from here by callers that build single actors.
from .placement import (EGO_SIZE, SIZE_MEAN, SPEED, ActorMaker, Placer, Plan, make_actor, lane,  # noqa: F401
                        sidewalk_line)
from .paths import Routes
from .roadworks import place_construction_zones
from .turns import path_clear, turn_ahead
from .world import Actor

# Standing pedestrians: the shares of those facing along the sidewalk (either way), towards the
# road and towards the buildings; how close to a curb one waits to cross; the largest turn away
# from the way faced (rad); how close people stand to talk to each other (m).
STANDING_WAYS = np.array([0.35, 0.35, 0.2, 0.1])
WAIT_AT_CURB = 4.0
TURN = 0.3
GROUP_RADIUS = 2.5


def place_actors(cfg: SceneConfig, grid: Grid, static: np.ndarray, duration: float,
                 rng: np.random.Generator) -> list[Plan]:
    """All actors of a scene: the ego first (id 0), then everyone else, section by section (each
    draws from ``rng`` in turn, so their order is part of the scene's recipe)."""
    placer = Placer(static)
    new = ActorMaker(rng)
    _place_ego(cfg, grid, placer, duration, rng)
    place_construction_zones(cfg, grid, placer, new, rng)
    place_bus_stops(cfg, grid, placer, new, rng)
    place_parked_trailers(cfg, grid, placer, new, rng)
    _place_parking_strips(cfg.actors, grid, placer, new, rng)
    _place_moving_vehicles(cfg.actors, grid, placer, new, duration, rng)
    _place_moving_bicycles(cfg, grid, placer, new, rng)
    _place_parked_bicycles(cfg, grid, placer, new, rng)
    _place_pedestrians(cfg, grid, placer, new, rng)
    _face_groups(placer.plans)
    return placer.plans


def _place_ego(cfg: SceneConfig, grid: Grid, placer: Placer, duration: float, rng: np.random.Generator) -> None:
    """The ego: in a lane, starting near the world centre, not annotated."""
    W, H = grid.extent
    for _ in range(1000):
        origin, heading, length, _ = lane(grid, rng)
        v = rng.uniform(*cfg.ego.speed)
        centre = MAP_PAD + np.array([W, H]) / 2
        d = np.array([np.cos(heading), np.sin(heading)])
        s_mid = float(np.dot(centre - origin, d))
        s0 = s_mid - v * duration / 2 + rng.uniform(-cfg.layout.block_pitch / 4, cfg.layout.block_pitch / 4)
        ego_mesh = assets.car(*EGO_SIZE, (200, 200, 200))
        ego = Actor(0, "car", EGO_SIZE, ego_mesh, np.zeros((0, 6)), annotate=False)
        plan = Plan(ego, origin, heading, float(np.clip(s0, 10, length - 10)), length, v, priority=10**6)
        if placer.add(plan, 0.5):
            return


def _place_parking_strips(a: ActorsConfig, grid: Grid, placer: Placer, new: ActorMaker,
                          rng: np.random.Generator) -> None:
    """Parked vehicles, cone groups and barrier rows in the parking strips, slot by slot."""
    lay = grid.cfg
    hw, sw = grid.road_half_width, lay.sidewalk_width
    W, H = grid.extent
    slot = 6.5
    spans_x, spans_y = grid.intervals(grid.xs, W), grid.intervals(grid.ys, H)
    cone_p = a.cones_per_km / 4.0 / max(1e-6, 1000.0 / slot)      # a group holds about 4 cones
    barrier_p = a.barriers_per_km / 3.0 / max(1e-6, 1000.0 / slot)
    for horizontal, centres, spans in ((True, grid.ys, spans_x), (False, grid.xs, spans_y)):
        for c in centres:
            for side in (-1, 1):
                lat = side * (hw - lay.parking_width / 2)
                for u0, u1 in spans:
                    for u in np.arange(u0 + sw + 1.0, u1 - sw - slot, slot):
                        heading = (0.0 if side < 0 else np.pi) if horizontal else (np.pi / 2 if side > 0 else -np.pi / 2)
                        pos = np.array([u + slot / 2, c + lat]) if horizontal else np.array([c + lat, u + slot / 2])
                        _fill_slot(a, placer, new, rng, pos, heading, cone_p, barrier_p)


def _fill_slot(a: ActorsConfig, placer: Placer, new: ActorMaker, rng: np.random.Generator, pos: np.ndarray,
               heading: float, cone_p: float, barrier_p: float) -> None:
    """One parking slot at ``pos`` (2,): a cone group, a barrier row, a parked vehicle or nothing."""
    moto_p, truck_p = a.parked_motorcycle_fraction, a.parked_truck_fraction
    d = np.array([np.cos(heading), np.sin(heading)])
    r = rng.random()
    if r < cone_p:
        n = int(rng.integers(3, 6))
        for k in range(n):
            placer.add(Plan(new("traffic_cone"), pos + (k - n / 2) * 1.3 * d, heading, 0.0, 0.0, 0.0), 0.1)
    elif r < cone_p + barrier_p:
        for k in range(int(rng.integers(2, 4))):
            placer.add(Plan(new("barrier"), pos + (k - 1) * 2.6 * d, heading + np.pi / 2, 0.0, 0.0, 0.0), 0.05)
    elif r < cone_p + barrier_p + a.parked_fraction:
        q = rng.random()
        cls = "motorcycle" if q < moto_p else ("truck" if q < moto_p + truck_p else "car")
        jitter = rng.uniform(-0.4, 0.4)
        placer.add(Plan(new(cls, parked=True, rider=False), pos + jitter, heading, 0.0, 0.0, 0.0), 0.3)


def _place_moving_vehicles(a: ActorsConfig, grid: Grid, placer: Placer, new: ActorMaker, duration: float,
                           rng: np.random.Generator) -> None:
    """Moving vehicles in lanes, with an occasional planned stop; some trucks tow a trailer, and
    ``turning_fraction`` of them turn left or right (evenly) at the next intersection."""
    mix = list(a.vehicle_mix)
    weights = np.array([a.vehicle_mix[k] for k in mix])
    for _ in range(int(round(a.vehicles_per_km * grid.road_km))):
        cls = mix[rng.choice(len(mix), p=weights / weights.sum())]
        actor = new(cls, rider=True)
        towed = cls == "truck" and a.hitched_trailer_fraction > 0 and rng.random() < a.hitched_trailer_fraction
        trailer = new("trailer") if towed else None
        turning = a.turning_fraction > 0 and rng.random() < a.turning_fraction
        left = turning and rng.random() < 0.5
        for _try in range(20):
            origin, heading, length, lateral = lane(grid, rng)
            stop = ()
            if rng.random() < a.stop_probability:
                t0 = rng.uniform(0, duration)
                stop = (t0, t0 + rng.uniform(1.5, 4.0))
            plan = Plan(actor, origin, heading, rng.uniform(5, length - 5), length,
                        rng.uniform(*SPEED[cls]), stop=stop, priority=2000 + actor.id)
            if turning:
                plan = _with_turn(grid, plan, lateral, left, trailer)
            if place_train(placer, plan, hitch(trailer, plan) if towed else None, 1.0):
                break


def _with_turn(grid: Grid, plan: Plan, lateral: float, left: bool, trailer: Actor | None) -> Plan:
    """``plan`` turning at the next intersection ahead (see :mod:`simgen.turns`), or ``plan`` as
    it is when no intersection lies ahead or the turn would take it, or its ``trailer``, off the
    road (a train's articulation also has to leave the two boxes apart)."""
    found = turn_ahead(grid, plan.origin, plan.heading, plan.s0, lateral, left)
    if found is None:
        return plan
    turn, length = found
    routes = Routes.of(plan.origin[None], [plan.heading], [turn])
    size = np.array(plan.actor.size)
    if trailer is None:
        clear = path_clear(grid, routes, plan.s0, turn, size)
    else:
        behind = size[0] / 2 + HITCH_GAP + trailer.size[0] / 2
        clear = path_clear(grid, routes, plan.s0, turn, size, np.array(trailer.size), behind)
    return dataclasses.replace(plan, turn=turn, length=length) if clear else plan


def _place_moving_bicycles(cfg: SceneConfig, grid: Grid, placer: Placer, new: ActorMaker,
                           rng: np.random.Generator) -> None:
    """Moving bicycles near the right edge of the outer lane."""
    edge = cfg.layout.lanes_per_direction * cfg.layout.lane_width - 0.55
    for _ in range(int(round(cfg.actors.bicycles_per_km * grid.road_km))):
        actor = new("bicycle", rider=True)
        for _try in range(20):
            origin, heading, length, _ = lane(grid, rng, lateral=edge)
            plan = Plan(actor, origin, heading, rng.uniform(5, length - 5), length,
                        rng.uniform(*SPEED["bicycle"]), priority=1000 + actor.id)
            if placer.add(plan, 0.5):
                break


def _place_parked_bicycles(cfg: SceneConfig, grid: Grid, placer: Placer, new: ActorMaker,
                           rng: np.random.Generator) -> None:
    """Parked bicycles along the building side of the sidewalks, across the walking direction."""
    for _ in range(int(round(cfg.actors.parked_bicycles_per_km * grid.road_km))):
        actor = new("bicycle", parked=True, rider=False)
        for _try in range(20):
            origin, heading, length = sidewalk_line(grid, rng, grid.road_half_width + cfg.layout.sidewalk_width - 1.0)
            s = rng.uniform(5, length - 5)
            plan = Plan(actor, origin + s * np.array([np.cos(heading), np.sin(heading)]),
                        heading + np.pi / 2, 0.0, 0.0, 0.0, z_ground=CURB_HEIGHT)
            if grid.ground_z(plan.xy(0.0)) > 0 and placer.add(plan, 0.1):
                break


def _place_pedestrians(cfg: SceneConfig, grid: Grid, placer: Placer, new: ActorMaker,
                       rng: np.random.Generator) -> None:
    """Pedestrians: standing, walking along sidewalks, or walking towards a crosswalk."""
    hw = grid.road_half_width
    walk_lo, walk_hi = hw + 1.3, hw + cfg.layout.sidewalk_width - 2.0
    for _ in range(int(round(cfg.actors.pedestrians_per_km * grid.road_km))):
        actor = new("pedestrian")
        standing = rng.random() < cfg.actors.standing_fraction
        crossing = not standing and rng.random() < cfg.actors.crossing_fraction
        for _try in range(30):
            origin, heading, length = sidewalk_line(grid, rng, rng.uniform(walk_lo, walk_hi))
            if crossing:
                s = _before_crossing(grid, origin, heading, length, rng)
                if s is None:
                    continue
            else:
                s = rng.uniform(5, length - 5)
            v = 0.0 if standing else rng.uniform(*SPEED["pedestrian"])
            way = rng.random() if standing else 0.0
            if standing:
                # Placed with a footprint turned by 2 pi way, as it always was, so that the draws
                # that follow and every other actor stay where they were; then turned to face.
                plan = Plan(actor, origin + s * np.array([np.cos(heading), np.sin(heading)]),
                            2 * np.pi * way - np.pi, 0.0, 0.0, 0.0, z_ground=CURB_HEIGHT)
            else:
                plan = Plan(actor, origin, heading, s, length, v, priority=actor.id)
            if grid.ground_z(plan.xy(plan.s0)) > 0 and placer.add(plan, 0.2):
                if standing:
                    plan.heading = _standing_heading(grid, origin, heading, s, way)
                break


def _standing_heading(grid: Grid, origin: np.ndarray, heading: float, s: float, way: float) -> float:
    """Which way a pedestrian standing at arc length ``s`` of a sidewalk line faces, from one
    uniform variate ``way`` in [0, 1): across the road ahead or behind when it waits at a corner
    (within ``WAIT_AT_CURB`` of the curb), otherwise along the sidewalk either way, sometimes
    towards the road or the buildings. The variate picks the way; what is left of it turns the
    person a little (up to ``TURN`` either side). The road the line runs along is to its left."""
    d_curb = _curb_distances(grid, origin, heading, s)
    if np.abs(d_curb).min() <= WAIT_AT_CURB:
        base = np.array([heading if d_curb[np.abs(d_curb).argmin()] > 0 else heading + np.pi])
        k, rest = 0, way
    else:
        base = heading + np.array([0.0, np.pi, np.pi / 2, -np.pi / 2])
        edges = np.cumsum(STANDING_WAYS)
        k = int(np.searchsorted(edges, way, side="right"))
        rest = (way - (edges[k] - STANDING_WAYS[k])) / STANDING_WAYS[k]
    yaw = base[k] + TURN * (2 * rest - 1)
    return float(np.arctan2(np.sin(yaw), np.cos(yaw)))


def _curb_distances(grid: Grid, origin: np.ndarray, heading: float, s: float) -> np.ndarray:
    """Signed distances (m) along a sidewalk line from arc length ``s`` to the near curb of every
    road the line crosses: positive ahead, negative behind."""
    rel = _crossings(grid, origin, heading) - s
    return np.where(rel > 0, rel - grid.road_half_width, rel + grid.road_half_width)


def _crossings(grid: Grid, origin: np.ndarray, heading: float) -> np.ndarray:
    """(k,) arc lengths at which a sidewalk line from ``origin`` along ``heading`` (axis-aligned)
    crosses the centreline of each road across it."""
    along_x = abs(np.cos(heading)) > 0.5
    crosses = grid.xs if along_x else grid.ys
    o, sgn = (origin[0], np.sign(np.cos(heading))) if along_x else (origin[1], np.sign(np.sin(heading)))
    return (crosses - o) * sgn


def _face_groups(plans: list[Plan]) -> None:
    """Standing pedestrians within ``GROUP_RADIUS`` of one another turn to face the middle of the
    others: people chatting, not a queue."""
    still = [p for p in plans if p.actor.cls == "pedestrian" and p.v_des == 0.0]
    if len(still) < 2:
        return
    xy = np.array([p.xy(p.s0) for p in still])                       # (k, 2)
    near = np.hypot(*(xy[:, None] - xy[None]).transpose(2, 0, 1)) <= GROUP_RADIUS
    np.fill_diagonal(near, False)
    count = near.sum(1)
    centre = (near @ xy) / np.maximum(count, 1)[:, None]              # (k, 2) the others' middle
    for p, n, c, own in zip(still, count, centre, xy):
        if n:
            p.heading = float(np.arctan2(c[1] - own[1], c[0] - own[0]))


def _before_crossing(grid: Grid, origin: np.ndarray, heading: float, length: float,
                     rng: np.random.Generator) -> float | None:
    """Arc length a few metres before the curb of a road that the sidewalk line crosses, or None
    if it crosses none far enough from its ends."""
    hw = grid.road_half_width
    s_cross = _crossings(grid, origin, heading)
    s_cross = s_cross[(s_cross > hw + 8) & (s_cross < length - hw - 8)]
    if len(s_cross) == 0:
        return None
    return float(rng.choice(s_cross)) - hw - rng.uniform(0.5, 6.0)
