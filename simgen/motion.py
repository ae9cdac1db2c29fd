"""Motion over time: every moving actor follows its path (straight, or turning at an
intersection: :mod:`simgen.paths`) with car-following.

Each step (the lidar period, 0.05 s) all actors look ahead along their heading through a
corridor as long as their braking distance; the nearest footprint in it limits the speed to one
that can still stop in time (v = sqrt(2 b gap)). When two actors wait for each other (each is in
the other's corridor), the one with the lower priority number goes first: pedestrians, then
cycles, then vehicles, then the ego. Finally a hard constraint keeps the world valid: a proposed
move that would make two footprints overlap is not taken (that actor stands still this step).
So no two objects ever intersect, by construction, and the tests check it independently. A
hitched trailer does not drive: it rides its tractor's straight path a fixed distance behind
it, or, when the path turns, is dragged by its hitch as a kinematic trailer; the two move
together or not at all.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import geometry
from .paths import Routes, hitch_points, pull, trailer_yaw
from .traffic import Plan

# Per class: (comfortable braking b, max acceleration, standstill gap s0, extra look-ahead).
DYNAMICS = {"pedestrian": (2.0, 1.0, 0.3, 0.8), "bicycle": (3.0, 1.5, 1.0, 2.0),
            "motorcycle": (4.0, 2.5, 1.5, 3.0)}
VEHICLE_DYNAMICS = (4.0, 2.5, 2.0, 3.0)
HARD_MARGIN = 0.05   # metres of clearance the hard constraint keeps between footprints


@dataclass(frozen=True)
class Paths:
    """The plans as arrays: n actors on their routes (global frame).

    The state of the world at a step is ``s`` (n,), every actor's arc length on its route, and
    ``axle`` (n, 2), the axle points (= box centres) of the trailers that a turning tractor
    drags (``articulated``); everyone else's pose is a closed form of ``s``."""
    route: Routes             # (n,) routes
    size: np.ndarray          # (n, 3) l, w, h
    length: np.ndarray        # (n,) path length
    v_des: np.ndarray         # (n,) desired speed
    priority: np.ndarray      # (n,) lower goes first
    stop: np.ndarray          # (n, 2) planned stop [t_start, t_end), inf when none
    moving: np.ndarray        # (n,) bool: v_des > 0
    b_comf: np.ndarray        # (n,) comfortable braking (m/s^2)
    a_max: np.ndarray         # (n,) maximum acceleration (m/s^2)
    s0_gap: np.ndarray        # (n,) standstill gap (m)
    extra: np.ndarray         # (n,) look-ahead beyond the braking distance (m)
    tractor: np.ndarray       # (n,) int: a hitched trailer's tractor, -1 for everyone else
    hitch: np.ndarray         # (n,) a trailer's arc length behind its tractor's (m), 0 for the others
    articulated: np.ndarray   # (n,) bool: a trailer whose tractor's path turns

    @classmethod
    def of(cls, plans: list[Plan]) -> "Paths":
        dyn_params = np.array([DYNAMICS.get(p.actor.cls, VEHICLE_DYNAMICS) for p in plans])
        index = {id(p): i for i, p in enumerate(plans)}
        tractor = np.array([index[id(p.tractor)] if p.tractor is not None else -1 for p in plans], dtype=np.int64)
        hitch = np.array([p.tractor.s0 - p.s0 if p.tractor is not None else 0.0 for p in plans])
        route = Routes.of(np.array([p.origin for p in plans]), np.array([p.heading for p in plans]),
                          [p.turn for p in plans])
        return cls(route=route, size=np.array([p.actor.size for p in plans]),
                   length=np.array([p.length for p in plans]),
                   v_des=np.array([p.v_des for p in plans]), priority=np.array([p.priority for p in plans]),
                   stop=np.array([p.stop if p.stop else (np.inf, np.inf) for p in plans]),
                   moving=np.array([p.v_des > 0 for p in plans]), b_comf=dyn_params[:, 0], a_max=dyn_params[:, 1],
                   s0_gap=dyn_params[:, 2], extra=dyn_params[:, 3], tractor=tractor, hitch=hitch,
                   articulated=(tractor >= 0) & route.turns)

    def follow_tractors(self, s: np.ndarray) -> np.ndarray:
        """Arc lengths ``s`` (n,) with every hitched trailer put its hitch distance behind its
        tractor. On a straight path that is the trailer's place (a kinematic trailer dragged
        along a line stays on it); an articulated trailer's place is its axle, but its ``s``
        still tells whether the train moved."""
        towed = self.tractor >= 0
        if not towed.any():
            return s
        s = s.copy()
        s[towed] = s[self.tractor[towed]] - self.hitch[towed]
        return s

    def poses(self, s: np.ndarray, axle: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Box centres (n, 2) and headings (n,) at arc lengths ``s`` (n,), articulated trailers
        at their ``axle`` points (n, 2)."""
        xy, yaw = self.route.at(s)
        k = np.nonzero(self.articulated)[0]
        if len(k):
            hitch = self._hitches(xy, yaw, k)
            xy[k] = axle[k]
            yaw[k] = trailer_yaw(hitch, axle[k], yaw[self.tractor[k]])
        return xy, yaw

    def pull_trailers(self, s_new: np.ndarray, s: np.ndarray, axle: np.ndarray) -> np.ndarray:
        """(n, 2) axle points after the trains moved from ``s`` to ``s_new`` (n,); a train that
        did not move leaves its trailer exactly where it was."""
        k = np.nonzero(self.articulated & (s_new != s))[0]
        if len(k) == 0:
            return axle
        xy, yaw = self.route.at(s_new)
        axle = axle.copy()
        axle[k] = pull(self._hitches(xy, yaw, k), axle[k], self.drawbar[k])
        return axle

    def initial_axles(self, s: np.ndarray) -> np.ndarray:
        """(n, 2) axle points at the start: on the straight before the turn, where the route puts
        the trailer's centre (NaN for everyone but the articulated trailers)."""
        axle = np.full((len(s), 2), np.nan)
        k = np.nonzero(self.articulated)[0]
        axle[k] = self.route.at(s)[0][k]
        return axle

    @property
    def drawbar(self) -> np.ndarray:
        """(n,) hitch (the middle of the tractor's rear face) to a trailer's axle (its box centre)."""
        return self.hitch - self.size[np.maximum(self.tractor, 0), 0] / 2

    def _hitches(self, xy: np.ndarray, yaw: np.ndarray, k: np.ndarray) -> np.ndarray:
        """(m, 2) hitch points of the tractors of trailers ``k`` (m,), from all poses ``xy``, ``yaw``."""
        j = self.tractor[k]
        return hitch_points(xy[j], yaw[j], self.size[j, 0] / 2)

    def boxes(self, xy: np.ndarray, yaw: np.ndarray) -> np.ndarray:
        """(n, 7) footprints of poses ``xy`` (n, 2), ``yaw`` (n,)."""
        return np.concatenate([xy, np.zeros((len(xy), 1)), self.size, yaw[:, None]], 1)


def simulate(plans: list[Plan], static_boxes: np.ndarray,
             times: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Integrate all plans over ``times`` (uniform step).

    Returns
    -------
    xy : (n, K, 2) box centres, global frame.
    yaw : (n, K) headings (rad), continuous over time (never wrapped).
    speed : (n, K) speed (m/s), central differences of the positions: of the arc length along
        the path, or for an articulated trailer of its axle's track.
    """
    paths = Paths.of(plans)
    dt = float(times[1] - times[0])
    s = paths.follow_tractors(np.array([p.s0 for p in plans], dtype=np.float64))
    axle = paths.initial_axles(s)
    v = np.where(paths.moving, paths.v_des, 0.0)
    S = np.zeros((len(plans), len(times)))
    XY = np.zeros((len(plans), len(times), 2))
    YAW = np.zeros((len(plans), len(times)))
    S[:, 0] = s
    XY[:, 0], YAW[:, 0] = paths.poses(s, axle)
    for k in range(len(times) - 1):
        v_new = _next_speed(paths, s, axle, v, float(times[k]), static_boxes, dt)
        s_new = np.minimum(s + v_new * dt, np.maximum(paths.length - paths.size[:, 0] / 2, s))
        s_new, axle = _undo_overlapping_moves(paths, s, paths.follow_tractors(s_new), axle, static_boxes)
        v = (s_new - s) / dt
        s = s_new
        S[:, k + 1] = s
        XY[:, k + 1], YAW[:, k + 1] = paths.poses(s, axle)
    speed = np.gradient(S, dt, axis=1)
    if paths.articulated.any():
        speed[paths.articulated] = np.linalg.norm(np.gradient(XY[paths.articulated], dt, axis=1), axis=-1)
    return XY, YAW, speed


def _next_speed(paths: Paths, s: np.ndarray, axle: np.ndarray, v: np.ndarray, t: float, static_boxes: np.ndarray,
                dt: float) -> np.ndarray:
    """(n,) speeds for the next step: the desired speed (0 during a planned stop), capped by what
    still stops short of the nearest footprint in the corridor ahead (along the current
    heading), within braking and acceleration limits."""
    n = len(s)
    xy, yaw = paths.poses(s, axle)
    size, u = paths.size, np.stack([np.cos(yaw), np.sin(yaw)], 1)
    boxes = paths.boxes(xy, yaw)
    obstacles = np.concatenate([boxes, static_boxes])
    idx_dyn = np.nonzero(paths.moving)[0]
    # Corridor ahead of each moving actor: its braking distance plus a margin.
    D = paths.extra + v * v / (2.0 * paths.b_comf) + v * 0.5
    cor = boxes.copy()
    cor[:, :2] += u * (size[:, :1] / 2 + D[:, None] / 2)
    cor[:, 3] = D
    cor[:, 4] = size[:, 1] + 0.3
    cor = cor[idx_dyn]
    ci, oj = geometry.near_pairs(cor, obstacles)
    ci_g = idx_dyn[ci]
    keep = ci_g != oj
    ci, oj, ci_g = ci[keep], oj[keep], ci_g[keep]
    hit = geometry.bev_overlap_pairwise(cor[ci], obstacles[oj])
    ci, oj, ci_g = ci[hit], oj[hit], ci_g[hit]
    # Mutual waiting: i ignores j when j also sees i and i has the lower priority number.
    pair_key = ci_g * (n + len(static_boxes)) + oj
    rev_key = oj * (n + len(static_boxes)) + ci_g
    mutual = (oj < n) & np.isin(rev_key, pair_key)
    ignore = mutual & (paths.priority[ci_g] < paths.priority[np.minimum(oj, n - 1)])
    ci_g, oj = ci_g[~ignore], oj[~ignore]
    # Gap from i's front to the near side of obstacle j, along i's heading.
    front = boxes[ci_g, :2] + u[ci_g] * size[ci_g, :1] / 2
    ob = obstacles[oj]
    rel = ob[:, 6] - yaw[ci_g]
    half = np.abs(ob[:, 3] / 2 * np.cos(rel)) + np.abs(ob[:, 4] / 2 * np.sin(rel))
    gap_pair = np.einsum("kd,kd->k", ob[:, :2] - front, u[ci_g]) - half
    gap = np.full(n, np.inf)
    np.minimum.at(gap, ci_g, gap_pair)
    target = np.where((t >= paths.stop[:, 0]) & (t < paths.stop[:, 1]), 0.0, paths.v_des)
    v_safe = np.sqrt(2.0 * paths.b_comf * np.maximum(gap - paths.s0_gap, 0.0))
    target = np.minimum(target, v_safe)
    return np.clip(target, v - 2.0 * paths.b_comf * dt, v + paths.a_max * dt).clip(min=0.0)


def _undo_overlapping_moves(paths: Paths, s: np.ndarray, s_new: np.ndarray, axle: np.ndarray,
                            static_boxes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The hard constraint: moves from ``s`` to ``s_new`` (n,) that would make footprints
    overlap are not taken, repeated until no taken move does. A tractor and its trailer move
    together or not at all. Returns the arc lengths taken and the articulated trailers' axle
    points (n, 2) after them."""
    s_new = s_new.copy()
    while True:
        moved = np.nonzero(s_new != s)[0]
        axle_new = paths.pull_trailers(s_new, s, axle)
        if len(moved) == 0:
            return s_new, axle_new
        nb = paths.boxes(*paths.poses(s_new, axle_new))
        all_boxes = np.concatenate([nb, static_boxes])
        mi, oj = geometry.near_pairs(nb[moved], all_boxes, pad=2 * HARD_MARGIN)
        mi_g = moved[mi]
        keep = mi_g != oj
        mi_g, oj = mi_g[keep], oj[keep]
        bad = geometry.bev_overlap_pairwise(nb[mi_g], all_boxes[oj], HARD_MARGIN)
        if not bad.any():
            return s_new, axle_new
        stuck = mi_g[bad]
        stuck = np.concatenate([stuck, paths.tractor[stuck][paths.tractor[stuck] >= 0]])
        s_new[stuck] = s[stuck]
        s_new = paths.follow_tractors(s_new)
