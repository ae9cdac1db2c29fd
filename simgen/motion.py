"""Motion over time: every moving actor follows its straight path with car-following.

Each step (the lidar period, 0.05 s) all actors look ahead along their path through a corridor
as long as their braking distance; the nearest footprint in it limits the speed to one that can
still stop in time (v = sqrt(2 b gap)). When two actors wait for each other (each is in the
other's corridor), the one with the lower priority number goes first: pedestrians, then cycles,
then vehicles, then the ego. Finally a hard constraint keeps the world valid: a proposed move
that would make two footprints overlap is not taken (that actor stands still this step). So no
two objects ever intersect, by construction, and the tests check it independently.
"""
from __future__ import annotations

import numpy as np

from . import geometry as geo
from .traffic import Plan

# Per class: (comfortable braking b, max acceleration, standstill gap s0, extra look-ahead).
DYNAMICS = {"pedestrian": (2.0, 1.0, 0.3, 0.8), "bicycle": (3.0, 1.5, 1.0, 2.0),
            "motorcycle": (4.0, 2.5, 1.5, 3.0)}
VEHICLE_DYNAMICS = (4.0, 2.5, 2.0, 3.0)
HARD_MARGIN = 0.05   # metres of clearance the hard constraint keeps between footprints


def simulate(plans: list[Plan], static_boxes: np.ndarray, times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Integrate all plans over ``times`` (uniform step).

    Returns
    -------
    xy : (n, K, 2) box centres, global frame.
    speed : (n, K) speed along the path (m/s), central differences of the positions.
    """
    n, K = len(plans), len(times)
    dt = float(times[1] - times[0])
    origin = np.array([p.origin for p in plans])
    yaw = np.array([p.heading for p in plans])
    u = np.stack([np.cos(yaw), np.sin(yaw)], 1)
    size = np.array([p.actor.size for p in plans])
    length = np.array([p.length for p in plans])
    v_des = np.array([p.v_des for p in plans])
    prio = np.array([p.priority for p in plans])
    stop = np.array([p.stop if p.stop else (np.inf, np.inf) for p in plans])
    dyn = np.array([p.v_des > 0 for p in plans])
    dyn_params = np.array([DYNAMICS.get(p.actor.cls, VEHICLE_DYNAMICS) for p in plans])
    b_comf, a_max, s0_gap, extra = dyn_params.T

    s = np.array([p.s0 for p in plans], dtype=np.float64)
    v = np.where(dyn, v_des, 0.0)
    S = np.zeros((n, K))
    S[:, 0] = s
    idx_dyn = np.nonzero(dyn)[0]

    def boxes_for(s_arr):
        pos = origin + s_arr[:, None] * u
        return np.concatenate([pos, np.zeros((n, 1)), size, yaw[:, None]], 1)

    for k in range(K - 1):
        t = times[k]
        boxes = boxes_for(s)
        obstacles = np.concatenate([boxes, static_boxes])
        # Corridor ahead of each moving actor: its braking distance plus a margin.
        D = extra + v * v / (2.0 * b_comf) + v * 0.5
        cor = boxes.copy()
        cor[:, :2] += u * (size[:, :1] / 2 + D[:, None] / 2)
        cor[:, 3] = D
        cor[:, 4] = size[:, 1] + 0.3
        cor = cor[idx_dyn]
        ci, oj = geo.near_pairs(cor, obstacles)
        ci_g = idx_dyn[ci]
        keep = ci_g != oj
        ci, oj, ci_g = ci[keep], oj[keep], ci_g[keep]
        hit = geo.bev_overlap_pairwise(cor[ci], obstacles[oj])
        ci, oj, ci_g = ci[hit], oj[hit], ci_g[hit]
        # Mutual waiting: i ignores j when j also sees i and i has the lower priority number.
        pair_key = ci_g * (n + len(static_boxes)) + oj
        rev_key = oj * (n + len(static_boxes)) + ci_g
        mutual = (oj < n) & np.isin(rev_key, pair_key)
        ignore = mutual & (prio[ci_g] < prio[np.minimum(oj, n - 1)])
        ci_g, oj = ci_g[~ignore], oj[~ignore]
        # Gap from i's front to the near side of obstacle j, along i's heading.
        front = boxes[ci_g, :2] + u[ci_g] * size[ci_g, :1] / 2
        ob = obstacles[oj]
        rel = ob[:, 6] - yaw[ci_g]
        half = np.abs(ob[:, 3] / 2 * np.cos(rel)) + np.abs(ob[:, 4] / 2 * np.sin(rel))
        gap_pair = np.einsum("kd,kd->k", ob[:, :2] - front, u[ci_g]) - half
        gap = np.full(n, np.inf)
        np.minimum.at(gap, ci_g, gap_pair)
        target = np.where((t >= stop[:, 0]) & (t < stop[:, 1]), 0.0, v_des)
        v_safe = np.sqrt(2.0 * b_comf * np.maximum(gap - s0_gap, 0.0))
        target = np.minimum(target, v_safe)
        v_new = np.clip(target, v - 2.0 * b_comf * dt, v + a_max * dt).clip(min=0.0)
        s_new = np.minimum(s + v_new * dt, np.maximum(length - size[:, 0] / 2, s))
        # Hard constraint: undo moves that would overlap anything (repeat until consistent).
        while True:
            moved = np.nonzero(s_new != s)[0]
            if len(moved) == 0:
                break
            nb = boxes_for(s_new)
            all_boxes = np.concatenate([nb, static_boxes])
            mi, oj = geo.near_pairs(nb[moved], all_boxes, pad=2 * HARD_MARGIN)
            mi_g = moved[mi]
            keep = mi_g != oj
            mi_g, oj = mi_g[keep], oj[keep]
            bad = geo.bev_overlap_pairwise(nb[mi_g], all_boxes[oj], HARD_MARGIN)
            if not bad.any():
                break
            s_new[mi_g[bad]] = s[mi_g[bad]]
        v = (s_new - s) / dt
        s = s_new
        S[:, k + 1] = s
    xy = origin[:, None, :] + S[..., None] * u[:, None, :]
    speed = np.gradient(S, dt, axis=1)
    return xy, speed
