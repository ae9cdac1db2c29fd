"""Routes as closed forms of arc length, and the kinematic trailer that follows a tractor.

A route starts at ``origin`` along ``heading``. A straight route stays on that line. A turning
route leaves it at arc length ``Turn.s`` on a circular arc of ``Turn.radius`` through
``Turn.angle`` (positive: left, counter-clockwise) and goes on straight along its new heading.
Position and heading are continuous in arc length, and the heading is never wrapped, so a
track of headings over time has no 2 pi jumps.

A hitched trailer is a centre-axle trailer: its axle sits under the middle of its box and its
drawbar pivots at a hitch point on its tractor's rear (the middle of the tractor's rear face).
Its axle is dragged towards the hitch keeping its distance (the tractrix), so through a turn
its heading lags the tractor's and afterwards comes back to it.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import geometry


@dataclass(frozen=True)
class Turn:
    """Where and how a route turns."""
    s: float        # arc length at which the arc begins
    radius: float   # m
    angle: float    # rad, signed: positive turns left

    @property
    def end(self) -> float:
        """Arc length at which the arc ends."""
        return self.s + self.radius * abs(self.angle)


@dataclass(frozen=True)
class Routes:
    """n routes as arrays (global frame); ``s_turn`` is inf on a straight route."""
    origin: np.ndarray      # (n, 2)
    yaw: np.ndarray         # (n,) heading at the origin
    s_turn: np.ndarray      # (n,) arc length where the arc begins, inf when straight
    radius: np.ndarray      # (n,) arc radius (1 on straight routes: never used)
    angle: np.ndarray       # (n,) signed turning angle (0 on straight routes)

    @classmethod
    def of(cls, origin: np.ndarray, yaw: np.ndarray, turns: list[Turn | None]) -> "Routes":
        """Routes from (n, 2) origins, (n,) headings and n turns (None: straight)."""
        return cls(origin=np.asarray(origin, np.float64).reshape(-1, 2), yaw=np.asarray(yaw, np.float64),
                   s_turn=np.array([t.s if t else np.inf for t in turns]),
                   radius=np.array([t.radius if t else 1.0 for t in turns]),
                   angle=np.array([t.angle if t else 0.0 for t in turns]))

    @property
    def turns(self) -> np.ndarray:
        """(n,) bool: the route has an arc."""
        return np.isfinite(self.s_turn)

    def at(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Positions (n, ..., 2) and headings (n, ...) at arc lengths ``s`` (n, ...).

        Before its arc (and on a straight route) a position is ``origin + s u`` with the
        heading at the origin, bit for bit; on the arc the heading grows linearly with s about
        the arc's centre; after it the route goes on straight along the final heading.
        """
        s = np.asarray(s, np.float64)
        col = lambda a: a.reshape(a.shape + (1,) * (s.ndim - 1))   # noqa: E731  (n,) -> (n, 1, ...)
        yaw0 = col(self.yaw)
        u0 = np.stack([np.cos(self.yaw), np.sin(self.yaw)], -1)
        straight_xy = col(self.origin[:, 0]) + s * col(u0[:, 0]), col(self.origin[:, 1]) + s * col(u0[:, 1])
        before = ~col(self.turns) | (s <= col(np.where(self.turns, self.s_turn, 0.0)))
        if before.all():
            return np.stack(straight_xy, -1), np.broadcast_to(yaw0, s.shape).copy()
        # The arc's centre lies radius to the side it turns to, abreast of where it begins.
        s_a = np.where(self.turns, self.s_turn, 0.0)
        side = np.sign(self.angle)
        centre = self.origin + s_a[:, None] * u0 + (side * self.radius)[:, None] * np.stack([-u0[:, 1], u0[:, 0]], -1)
        turned = np.clip((s - col(s_a)) / col(self.radius), 0.0, col(np.abs(self.angle)))
        yaw = yaw0 + col(side) * turned
        r = col(side * self.radius)
        after = np.maximum(s - col(s_a) - col(self.radius * np.abs(self.angle)), 0.0)
        arc_x = col(centre[:, 0]) + r * np.sin(yaw) + after * np.cos(yaw)
        arc_y = col(centre[:, 1]) - r * np.cos(yaw) + after * np.sin(yaw)
        x = np.where(before, straight_xy[0], arc_x)
        y = np.where(before, straight_xy[1], arc_y)
        return np.stack([x, y], -1), np.where(before, yaw0, yaw)


def hitch_points(xy: np.ndarray, yaw: np.ndarray, back: np.ndarray) -> np.ndarray:
    """(m, 2) hitch points ``back`` (m,) metres behind box centres ``xy`` (m, 2) of heading ``yaw`` (m,)."""
    return xy - back[:, None] * np.stack([np.cos(yaw), np.sin(yaw)], -1)


def pull(hitch: np.ndarray, axle: np.ndarray, drawbar: np.ndarray) -> np.ndarray:
    """One step of the kinematic trailer: (m, 2) axle points moved towards the (m, 2) new hitch
    points, keeping their distance ``drawbar`` (m,) to them: A = H - L unit(H - A_old)."""
    d = hitch - axle
    return hitch - drawbar[:, None] * d / np.linalg.norm(d, axis=-1, keepdims=True)


def trailer_yaw(hitch: np.ndarray, axle: np.ndarray, tractor_yaw: np.ndarray) -> np.ndarray:
    """(m,) trailer headings (axle towards hitch), taken within pi of the tractor's (m,) so that,
    like the tractor's, they carry no 2 pi jumps."""
    d = hitch - axle
    bearing = np.arctan2(d[:, 1], d[:, 0])
    return tractor_yaw - geometry.wrap_angle(tractor_yaw - bearing)

