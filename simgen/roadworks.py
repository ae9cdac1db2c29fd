"""Road works: a stretch of a road's curb lane closed by a taper of cones, a row of jersey
barriers along the open lane and one across the far end, with a construction vehicle at work
inside, stopped or parked.

The zone is laid out in its lane's frame: ``s`` along the direction of travel, ``off`` to the
left of it (towards the road's centre, where the traffic still passes). Everything a zone holds
is placed only when the whole zone, curb lane and parking strip, is free; the ego's own lane is
never closed, so the ego is never stuck behind a zone for the whole scene.
"""
from __future__ import annotations

import numpy as np

from .config import SceneConfig
from .layout import Grid
from .placement import ActorMaker, Placer, Plan, lane

ZONE_LENGTH = (16.0, 30.0)   # closed length (m)
TAPER_LENGTH = 8.0           # the cones' diagonal ahead of the closure
TAPER_CONES = 5
BARRIER_GAP = 0.15           # between the ends of neighbouring barriers in a row
EDGE_CLEARANCE = 0.3         # the barrier row's inner face from the open lane's edge
PARKED_MACHINE = 0.5         # share of machines parked for the day (the rest stopped at work)


def place_construction_zones(cfg: SceneConfig, grid: Grid, placer: Placer, new: ActorMaker,
                             rng: np.random.Generator) -> None:
    """``construction_zones_per_km`` zones in curb lanes, each tried at up to 20 places."""
    lay = cfg.layout
    for _ in range(int(round(cfg.actors.construction_zones_per_km * grid.road_km))):
        for _try in range(20):
            origin, heading, length, lateral = lane(grid, rng, lateral=(lay.lanes_per_direction - 0.5) * lay.lane_width)
            L = rng.uniform(*ZONE_LENGTH)
            s0 = rng.uniform(TAPER_LENGTH + 10.0, length - L - 10.0)
            frame = _LaneFrame(origin, heading, lay.lane_width, lay.parking_width)
            if _in_ego_lane(placer.plans[0], frame, s0 + L / 2) or \
                    not placer.free(frame.area(s0 - TAPER_LENGTH, s0 + L), 0.05):
                continue
            _fill_zone(frame, s0, L, placer, new, rng)
            break


class _LaneFrame:
    """A lane's frame: (s, off) -> global xy, ``off`` positive towards the road's centre."""

    def __init__(self, origin: np.ndarray, heading: float, lane_width: float, parking_width: float):
        self.origin, self.heading = origin, heading
        self.d = np.array([np.cos(heading), np.sin(heading)])
        self.left = np.array([-self.d[1], self.d[0]])
        self.lane_width, self.parking_width = lane_width, parking_width

    def at(self, s: float, off: float) -> np.ndarray:
        return self.origin + s * self.d + off * self.left

    def area(self, s_start: float, s_end: float) -> np.ndarray:
        """(7,) footprint of the lane and the parking strip beside it (on the curb side, ``off`` <
        0) from ``s_start`` to ``s_end``, 0.1 m short of both edges: the curb's clutter stands
        just beyond the strip."""
        width = self.lane_width + self.parking_width
        return np.array([*self.at((s_start + s_end) / 2, self.lane_width / 2 - width / 2), 0.0, s_end - s_start,
                         width - 0.2, 1.0, self.heading])


def _in_ego_lane(ego: Plan, frame: _LaneFrame, s: float) -> bool:
    """Whether the zone's lane at arc length ``s`` is the ego's lane (lanes are axis-aligned:
    the same axis and the zone's point within a lane width of the ego's path line)."""
    d = np.array([np.cos(ego.heading), np.sin(ego.heading)])
    rel = frame.at(s, 0.0) - ego.origin
    same_axis = abs(abs(d @ frame.d) - 1.0) < 1e-6
    return bool(same_axis and abs(rel[0] * d[1] - rel[1] * d[0]) < frame.lane_width)


def _fill_zone(frame: _LaneFrame, s0: float, L: float, placer: Placer, new: ActorMaker,
               rng: np.random.Generator) -> None:
    """The taper, the barrier rows and the machine of a zone closing [s0, s0 + L]."""
    hw_lane = frame.lane_width / 2
    # The taper: cones on a diagonal from the curb side to the open lane's edge.
    for k in range(TAPER_CONES):
        f = k / (TAPER_CONES - 1)
        pos = frame.at(s0 - TAPER_LENGTH * (1 - f), -hw_lane + 0.4 + f * (2 * hw_lane - 0.8))
        placer.add(Plan(new("traffic_cone"), pos, frame.heading, 0.0, 0.0, 0.0), 0.05)
    # Jersey barriers end to end along the open lane (their long side, w, along the row).
    s = s0
    while True:
        barrier = new("barrier")
        l_b, w_b, _ = barrier.size
        if s + w_b > s0 + L:
            break
        pos = frame.at(s + w_b / 2, hw_lane - EDGE_CLEARANCE - l_b / 2)
        placer.add(Plan(barrier, pos, frame.heading + np.pi / 2, 0.0, 0.0, 0.0), 0.02)
        s += w_b + BARRIER_GAP
    # One across the far end, then the machine between the row and the curb.
    end = new("barrier")
    placer.add(Plan(end, frame.at(s0 + L + end.size[0] / 2 + 0.3, 0.0), frame.heading, 0.0, 0.0, 0.0), 0.02)
    machine = new("construction_vehicle", parked=bool(rng.random() < PARKED_MACHINE), rider=False)
    l_m, w_m, _ = machine.size
    off = hw_lane - EDGE_CLEARANCE - barrier.size[0] - 0.3 - w_m / 2
    yaw = frame.heading + (np.pi if rng.random() < 0.5 else 0.0)
    s_m = s0 + rng.uniform(l_m / 2 + 0.5, max(l_m / 2 + 0.5, L - l_m / 2 - 1.0))
    placer.add(Plan(machine, frame.at(s_m, off), yaw, 0.0, 0.0, 0.0), 0.05)
