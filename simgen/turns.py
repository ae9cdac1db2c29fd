"""Turns at intersections: where a vehicle in a lane turns onto a crossing road, and whether its
swept path (and its trailer's) stays on the road.

A turn goes from a lane at ``lateral`` right of its road's centreline onto the lane at the
same ``lateral`` of the crossing road (right-hand traffic), on the circle centred on the curb
corner it turns around: radius ``hw - lateral`` to the right, ``hw + lateral`` to the left (hw:
the road's half width, parking strips included). That is the widest arc that stays inside the
intersection, so a rigid box on it never leaves the road: its inner side keeps to its lane up
to the corner and turns about the corner itself. A vehicle turns only where the arc is no
tighter than its own turning circle, and a trailer cuts inside its tractor's path, so a train's
sweep is checked explicitly (:func:`path_clear`).
"""
from __future__ import annotations

import numpy as np

from . import geometry
from .layout import MAP_PAD, Grid
from .paths import Routes, Turn, hitch_points, pull, trailer_yaw

# A vehicle's tightest turn: front wheels at lock (about 35 degrees), wheelbase about 0.6 of the
# body (2.7 m of a 4.6 m car, 4 m of a 6.7 m truck), the box centre about half a wheelbase ahead
# of the rear axle. The outer front wheel then runs on a circle of 5.5 m radius for the mean car
# and 12.7 m for the mean bus: cars' kerb-to-kerb turning circles are about 11 m, and EU type
# approval (directive 97/27/EC) asks a bus to turn within 12.5 m.
MAX_STEER = np.radians(35.0)
WHEELBASE_SHARE = 0.6
SWEEP_STEP = 0.25       # m of tractor travel per step of the checked sweep
EDGE_STEP = 0.5         # m between the points checked along a box's outline
CLEARANCE = 0.2         # m a tractor and its trailer keep apart through a checked turn


def turn_ahead(grid: Grid, origin: np.ndarray, heading: float, s0: float, lateral: float,
               left: bool) -> tuple[Turn, float] | None:
    """The turn at the first intersection ahead of arc length ``s0`` on the lane from ``origin``
    along the axis-aligned ``heading``, and the whole route's length; None if no intersection
    lies ahead."""
    u = np.array([np.cos(heading), np.sin(heading)])
    along_x = abs(u[0]) > 0.5
    crossing = grid.xs if along_x else grid.ys
    s_cross = (crossing - origin[0 if along_x else 1]) * np.sign(u[0 if along_x else 1])
    hw = grid.road_half_width
    radius = hw + lateral if left else hw - lateral
    # The arc ends on the crossing road's lane: lateral beyond its centreline to the left,
    # lateral before it to the right; a quarter circle advances one radius along the road.
    s_arc = s_cross + (lateral if left else -lateral) - radius
    ahead = s_arc[s_arc >= s0]
    if len(ahead) == 0:
        return None
    turn = Turn(float(ahead.min()), float(radius), np.pi / 2 if left else -np.pi / 2)
    end_xy, end_yaw = Routes.of(origin[None], [heading], [turn]).at(np.array([turn.end]))
    return turn, turn.end + _to_city_edge(grid, end_xy[0], float(end_yaw[0]))


def _to_city_edge(grid: Grid, xy: np.ndarray, heading: float) -> float:
    """Distance from ``xy`` along the axis-aligned ``heading`` to the edge of the city."""
    W, H = grid.extent
    u = np.round([np.cos(heading), np.sin(heading)])
    lo, hi = np.array([MAP_PAD, MAP_PAD]), np.array([MAP_PAD + W, MAP_PAD + H])
    axis = 0 if u[0] != 0 else 1
    return float(hi[axis] - xy[axis] if u[axis] > 0 else xy[axis] - lo[axis])


def on_road(grid: Grid, xy: np.ndarray) -> np.ndarray:
    """(..., 2) global points -> (...) bool: on a road (within its half width of a centreline,
    parking strips included), as the drivable map draws it."""
    hw = grid.road_half_width
    near_x = (np.abs(xy[..., 0, None] - grid.xs) <= hw).any(-1)
    near_y = (np.abs(xy[..., 1, None] - grid.ys) <= hw).any(-1)
    return near_x | near_y


def outline(boxes: np.ndarray) -> np.ndarray:
    """(m, 7) boxes -> (m, p, 2) points along their BEV outlines, at most ``EDGE_STEP`` apart."""
    l, w = boxes[:, 3].max(), boxes[:, 4].max()
    k = int(np.ceil(max(l, w) / EDGE_STEP))
    t = np.linspace(-0.5, 0.5, k + 1)
    # Unit-square outline, then scaled, turned and moved per box.
    edge = np.concatenate([np.stack([t, np.full_like(t, s)], 1) for s in (-0.5, 0.5)]
                          + [np.stack([np.full_like(t, s), t], 1) for s in (-0.5, 0.5)])
    local = edge[None] * boxes[:, None, 3:5]
    c, s = np.cos(boxes[:, 6])[:, None], np.sin(boxes[:, 6])[:, None]
    turned = np.stack([c * local[..., 0] - s * local[..., 1], s * local[..., 0] + c * local[..., 1]], -1)
    return turned + boxes[:, None, :2]


def sweep(routes: Routes, s: np.ndarray, size: np.ndarray) -> np.ndarray:
    """(m, 7) boxes of the single route in ``routes`` at arc lengths ``s`` (m,), footprint size (3,)."""
    xy, yaw = routes.at(np.asarray(s)[None])
    return np.concatenate([xy[0], np.zeros((len(s), 1)), np.broadcast_to(size, (len(s), 3)), yaw[0][:, None]], 1)


def train_sweep(routes: Routes, s0: float, size: np.ndarray, trailer_size: np.ndarray, behind: float,
                s_end: float) -> tuple[np.ndarray, np.ndarray]:
    """The tractor's and its trailer's boxes (m, 7) each, the tractor driving its single route
    from ``s0`` to ``s_end`` in steps of ``SWEEP_STEP``; the trailer's centre starts ``behind``
    metres back on the route and follows by :func:`simgen.paths.pull`."""
    s = np.arange(s0, s_end, SWEEP_STEP)
    tractor = sweep(routes, s, size)
    hitch = hitch_points(tractor[:, :2], tractor[:, 6], np.full(len(s), size[0] / 2))
    drawbar = np.array([behind - size[0] / 2])
    axle = [routes.at(np.array([[s0 - behind]]))[0][0, 0]]
    for h in hitch[1:]:                  # sequential by nature: each step pulls the last axle
        axle.append(pull(h[None], axle[-1][None], drawbar)[0])
    axle = np.array(axle)
    trailer = np.concatenate([axle, np.zeros((len(s), 1)), np.broadcast_to(trailer_size, (len(s), 3)),
                              trailer_yaw(hitch, axle, tractor[:, 6])[:, None]], 1)
    return tractor, trailer


def min_turn_radius(length: float) -> float:
    """Radius (m) of the circle a vehicle ``length`` long drives its box centre on at full lock."""
    wheelbase = WHEELBASE_SHARE * length
    return float(np.hypot(wheelbase / np.tan(MAX_STEER), wheelbase / 2))


def path_clear(grid: Grid, routes: Routes, s0: float, turn: Turn, size: np.ndarray,
               trailer_size: np.ndarray | None = None, behind: float = 0.0) -> bool:
    """Whether a vehicle of ``size`` (3,) starting at ``s0`` on the single route of ``routes``
    can steer through ``turn`` and stays on the road, and with a trailer of ``trailer_size`` (its
    centre ``behind`` metres back) both boxes on the road and ``CLEARANCE`` apart. The sweep
    runs until the vehicle, or its trailer, has come out of the turn and straightened up."""
    if turn.radius < min_turn_radius(size[0]):
        return False
    if trailer_size is None:
        boxes = sweep(routes, np.arange(s0, turn.end + size[0], SWEEP_STEP), size)
        return bool(on_road(grid, outline(boxes)).all())
    settle = 4 * (behind - size[0] / 2) + behind      # the tractrix decays by e^-4 over 4 drawbars
    tractor, trailer = train_sweep(routes, s0, size, trailer_size, behind, turn.end + settle)
    return bool(on_road(grid, outline(np.concatenate([tractor, trailer]))).all()
                and not geometry.bev_overlap_pairwise(tractor, trailer, CLEARANCE).any())
