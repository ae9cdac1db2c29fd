"""Labels measured on the sensor data: num_lidar_pts, visibility and attributes.

``num_lidar_pts`` is counted exactly as the devkit counts it on the written files: the float32
points of the key-frame sweep, and the annotation box moved into the sensor frame through the
written ego pose and calibration with the devkit's own ``Box`` and ``points_in_box``.

Visibility is the fraction of an object's camera-facing surface that the six cameras see:
``N_SURFACE`` area-weighted samples on the actor's mesh are projected into every camera; a
sample that faces a camera and lands inside its image counts, and it is visible when the
rendered id at its pixel is the actor's own id. The fraction is binned as nuScenes does
(0-40, 40-60, 60-80, 80-100 %).
"""
from __future__ import annotations

import numpy as np
from pyquaternion import Quaternion

from . import geometry
from .world import CYCLES, Actor

VISIBILITY_BINS = np.array([0.4, 0.6, 0.8])
MOVING_SPEED = {"pedestrian": 0.2}   # m/s above which an actor counts as moving
DEFAULT_MOVING_SPEED = 0.3


def count_points_in_boxes(points_lidar: np.ndarray, anns: list[dict], ego_pose: dict, calib: dict) -> list[int]:
    """Number of (n, >=3) sensor-frame points inside each global annotation box.

    ``anns`` hold nuScenes ``translation``, ``size`` (wlh) and ``rotation``; ``ego_pose`` and
    ``calib`` are the written records of the lidar sample_data. The box is moved exactly as
    ``NuScenes.get_sample_data`` moves it, and tested exactly as ``points_in_box`` tests it: the
    same pyquaternion and numpy operations in the same order as the devkit's ``Box.translate``,
    ``Box.rotate``, ``Box.corners`` and ``points_in_box``, so the float results are the same.
    The devkit itself is not imported here: ``nuscenes.utils`` imports the package, whose
    ``__init__`` loads ``NuScenes`` and scikit-learn, slow to import in every worker process.
    The tests compare every written count with the devkit's own ``points_in_box``.
    """
    from scipy.spatial import cKDTree
    pts = points_lidar[:, :3].T                                  # (3, n), as the devkit holds them
    tree = cKDTree(points_lidar[:, :3].astype(np.float64))       # only to skip far points quickly
    q_pose_inv, q_cal_inv = Quaternion(ego_pose["rotation"]).inverse, Quaternion(calib["rotation"]).inverse
    R_pose_inv, R_cal_inv = q_pose_inv.rotation_matrix, q_cal_inv.rotation_matrix
    counts = []
    for ann in anns:
        center = np.array(ann["translation"])
        center += -np.array(ego_pose["translation"])
        center = np.dot(R_pose_inv, center)
        center += -np.array(calib["translation"])
        center = np.dot(R_cal_inv, center)
        orientation = q_cal_inv * (q_pose_inv * Quaternion(ann["rotation"]))
        w, l, h = np.array(ann["size"])
        signs = geometry.DEVKIT_CORNER_SIGNS
        corners = np.vstack((l / 2 * signs[0], w / 2 * signs[1], h / 2 * signs[2]))
        corners = np.dot(orientation.rotation_matrix, corners)
        for axis in range(3):
            corners[axis, :] = corners[axis, :] + center[axis]
        near = tree.query_ball_point(center, np.linalg.norm([w, l, h]) / 2 + 0.1)
        if not len(near):
            counts.append(0)
            continue
        counts.append(int(geometry.points_in_box(pts[:, np.sort(near)], corners).sum()))
    return counts


def visible_fraction(actors: list[Actor], poses: list[np.ndarray], cams: list, cam_poses: list[np.ndarray],
                     id_images: list[np.ndarray]) -> np.ndarray:
    """Fraction of each actor's camera-facing surface seen in any camera.

    Parameters
    ----------
    actors : the k actors to measure.
    poses : per camera, (k, 4, 4) T_global_from_box of those actors at that camera's time.
    cams : the rig cameras (``K``, ``resolution``).
    cam_poses : per camera, (4, 4) T_global_from_cam.
    id_images : per camera, (H, W) int32 rendered actor ids: an array, or anything that reads
        them as ``id_img[v, u]`` (:class:`simgen.camera.IdImage`).

    Returns
    -------
    (k,) float in [0, 1].
    """
    k = len(actors)
    if k == 0:
        return np.zeros(0)
    m = len(actors[0].surface)
    local = np.stack([a.surface for a in actors])                  # (k, m, 6)
    ids = np.array([a.id for a in actors])
    candidate = np.zeros((k, m), bool)
    seen = np.zeros((k, m), bool)
    for cam, T_box, T_gc, id_img in zip(cams, poses, cam_poses, id_images):
        R_T = np.transpose(T_box[:, :3, :3], (0, 2, 1))              # (k, 3, 3): row vectors @ R^T
        p = local[..., :3] @ R_T + T_box[:, None, :3, 3]
        n = local[..., 3:] @ R_T
        facing = np.einsum("kmi,kmi->km", n, p - T_gc[:3, 3]) < 0
        p_cam = geometry.apply(geometry.invert(T_gc), p.reshape(-1, 3))
        uv, z = geometry.project(cam.K, p_cam)
        W, H = cam.resolution
        with np.errstate(invalid="ignore"):
            inside = (z > 0.1) & (uv[:, 0] >= 0) & (uv[:, 0] < W) & (uv[:, 1] >= 0) & (uv[:, 1] < H)
        inside = inside.reshape(k, m) & facing
        u = np.where(inside.ravel(), uv[:, 0], 0).astype(np.int64)
        v = np.where(inside.ravel(), uv[:, 1], 0).astype(np.int64)
        hit = (id_img[v, u].reshape(k, m) == ids[:, None]) & inside
        candidate |= inside
        seen |= hit
    return seen.sum(1) / np.maximum(candidate.sum(1), 1)


def visibility_token(fraction: float) -> str:
    """nuScenes visibility level "1".."4" for a visible fraction."""
    return str(int(np.searchsorted(VISIBILITY_BINS, fraction, side="right")) + 1)


def attribute(actor: Actor, speed: float) -> str | None:
    """The nuScenes attribute name that follows the actor's state, or None (cones, barriers)."""
    moving = speed > MOVING_SPEED.get(actor.cls, DEFAULT_MOVING_SPEED)
    if actor.cls == "pedestrian":
        return "pedestrian.moving" if moving else "pedestrian.standing"
    if actor.cls in CYCLES:
        return "cycle.with_rider" if actor.rider else "cycle.without_rider"
    if actor.cls in ("car", "truck", "bus"):
        if actor.parked:
            return "vehicle.parked"
        return "vehicle.moving" if moving else "vehicle.stopped"
    return None
