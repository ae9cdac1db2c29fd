"""Data only: actors, their tracks, the world they live in, and a frame (poses at one time).

All coordinates are in the scene's global frame (x east, y north, z up, metres), which is also
the frame of the map PNG: pixel (row, col) = (H - y / 0.1, x / 0.1).
"""
from __future__ import annotations

import functools
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from . import geometry

if TYPE_CHECKING:          # only named in annotations; building a world imports it anyway
    import trimesh

# nuScenes category per simgen class, and the detection-class attribute family.
CATEGORY = {
    "car": "vehicle.car",
    "truck": "vehicle.truck",
    "bus": "vehicle.bus.rigid",
    "construction_vehicle": "vehicle.construction",
    "trailer": "vehicle.trailer",
    "motorcycle": "vehicle.motorcycle",
    "bicycle": "vehicle.bicycle",
    "pedestrian": "human.pedestrian.adult",
    "traffic_cone": "movable_object.trafficcone",
    "barrier": "movable_object.barrier",
}
CLASSES = tuple(CATEGORY)
VEHICLES = ("car", "truck", "bus", "construction_vehicle", "trailer")
# The ego frame's origin is the rear axle, this far behind the centre of the ego's box.
EGO_CENTRE_AHEAD_OF_ORIGIN = 1.3
CYCLES = ("motorcycle", "bicycle")


@dataclass
class Actor:
    """One annotated (or, for the ego, unannotated) object.

    ``mesh`` is in the box frame: origin at the box centre, x along the length (heading: the
    actor's front is +x), z up. Its faces carry ``face_colors`` and a per-face ``reflectivity``
    (0..1, for the lidar) in ``mesh.metadata["reflectivity"]``. ``surface`` is (k, 6) points +
    outward normals on the mesh, box frame, used to measure visibility.
    """
    id: int
    cls: str
    size: tuple[float, float, float]  # l, w, h
    mesh: trimesh.Trimesh
    surface: np.ndarray
    parked: bool = False       # a vehicle or cycle that will not move (attribute "parked"/"without_rider")
    rider: bool = True         # cycles: has a rider
    annotate: bool = True      # False for the ego
    towed_by: int = -1         # a hitched trailer: its tractor's actor id (-1: not hitched)


@dataclass
class World:
    """A scene's world for its whole duration.

    Tracks are sampled at ``times`` (seconds from the scene start, uniform step ``dt``):
    ``xy`` (n, K, 2), ``z`` (n, K) box-centre height, ``yaw`` (n, K) heading (rad, continuous
    over time: never wrapped, so a turning actor's track has no 2 pi jumps), ``speed`` (n, K).
    Actor 0 is the ego; its ``z`` is 0 (the ego_pose height) and its path is straight.
    """
    extent: tuple[float, float]
    static_mesh: trimesh.Trimesh
    static_boxes: np.ndarray            # (s, 7) footprints of static clutter, for collision tests
    actors: list[Actor]
    times: np.ndarray                   # (K,)
    xy: np.ndarray                      # (n, K, 2)
    z: np.ndarray                       # (n, K)
    yaw: np.ndarray                     # (n, K)
    speed: np.ndarray                   # (n, K)
    drivable: np.ndarray                # (H, W) uint8 mask at 0.1 m/px, 255 = drivable
    description: str = ""
    meta: dict = field(default_factory=dict)

    @property
    def dt(self) -> float:
        return float(self.times[1] - self.times[0])

    def boxes_at(self, t: float) -> np.ndarray:
        """(n, 7) boxes (x, y, z, l, w, h, yaw) of all actors at time ``t`` (linear interpolation;
        the heading along the shorter way between its samples)."""
        xy = _interp(self.times, self.xy, t)
        z = _interp(self.times, self.z[..., None], t)
        return np.concatenate([xy, z, self.sizes, _interp_angle(self.times, self.yaw, t)[:, None]], axis=1)

    @functools.cached_property
    def sizes(self) -> np.ndarray:
        """(n, 3) l, w, h of all actors."""
        return np.array([a.size for a in self.actors], dtype=np.float64).reshape(-1, 3)

    def speed_at(self, t: float) -> np.ndarray:
        """(n,) speeds (m/s) at time ``t``."""
        return _interp(self.times, self.speed[..., None], t)[:, 0]

    def ego_xy_yaw(self, t) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The ego frame's origin (rear axle) x, y and yaw at times ``t`` ((m,) arrays)."""
        t_arr = np.atleast_1d(np.asarray(t, dtype=np.float64))
        yaw = np.interp(t_arr, self.times, self.yaw[0])
        c, s = np.cos(yaw), np.sin(yaw)
        x = np.interp(t_arr, self.times, self.xy[0, :, 0]) - EGO_CENTRE_AHEAD_OF_ORIGIN * c
        y = np.interp(t_arr, self.times, self.xy[0, :, 1]) - EGO_CENTRE_AHEAD_OF_ORIGIN * s
        return x, y, yaw

    def ego_pose(self, t) -> np.ndarray:
        """T_global_from_ego at time(s) ``t``: (4, 4) for a scalar, (m, 4, 4) for an array."""
        T = geometry.poses_2d(*self.ego_xy_yaw(t))
        return T[0] if np.ndim(t) == 0 else T


def _interp(times: np.ndarray, values: np.ndarray, t: float) -> np.ndarray:
    """Linear interpolation of (n, K, c) samples at scalar time t -> (n, c)."""
    k, a = _bracket(times, t)
    return values[:, k] * (1.0 - a) + values[:, k + 1] * a


def _interp_angle(times: np.ndarray, angles: np.ndarray, t: float) -> np.ndarray:
    """Linear interpolation of (n, K) angles at scalar time t -> (n,), turning the shorter way
    between the two samples (a constant heading comes back exactly)."""
    k, a = _bracket(times, t)
    step = geometry.wrap_angle(angles[:, k + 1] - angles[:, k])
    return angles[:, k] + a * step


def _bracket(times: np.ndarray, t: float) -> tuple[int, float]:
    """The sample k with times[k] <= t < times[k + 1] (clamped) and the fraction of the way."""
    k = int(np.clip(np.searchsorted(times, t, side="right") - 1, 0, len(times) - 2))
    a = (t - times[k]) / (times[k + 1] - times[k])
    return k, float(np.clip(a, 0.0, 1.0))
