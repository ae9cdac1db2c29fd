"""Labels measured on the sensor data: num_lidar_pts, visibility, attributes and the dense
per-pixel labels.

``num_lidar_pts`` is counted exactly as the devkit counts it on the written files: the float32
points of the key-frame sweep, and the annotation box moved into the sensor frame through the
written ego pose and calibration with the devkit's own ``Box`` and ``points_in_box``.

Visibility is the fraction of an object's camera-facing surface that the six cameras see:
``N_SURFACE`` area-weighted samples on the actor's mesh are projected into every camera; a
sample that faces a camera and lands inside its image counts, and it is visible when the
rendered id at its pixel is the actor's own id. The fraction is binned as nuScenes does
(0-40, 40-60, 60-80, 80-100 %).

Dense labels (``simgen make --dense-labels``) are two images per camera image: the z-depth of
the first surface at each pixel, in KITTI's uint16 convention, and its nuScenes-lidarseg class,
given by the function that labels the lidar points (:func:`simgen.lidarseg.classes`).
"""
from __future__ import annotations

import numpy as np
from pyquaternion import Quaternion

from . import geometry
from . import lidarseg
from .face_meshes import STATIC_TILE, static_tiles
from .world import CYCLES, VEHICLES, Actor, World

VISIBILITY_BINS = np.array([0.4, 0.6, 0.8])
MOVING_SPEED = {"pedestrian": 0.2}   # m/s above which an actor counts as moving
DEFAULT_MOVING_SPEED = 0.3
DEPTH_SCALE = 256.0                  # KITTI depth maps: uint16 = metres x 256


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
    if actor.cls in VEHICLES:
        if actor.parked:
            return "vehicle.parked"
        return "vehicle.moving" if moving else "vehicle.stopped"
    return None


# ---- dense labels ------------------------------------------------------------------------------

def depth_image(depth: np.ndarray) -> np.ndarray:
    """(H, W) float32 camera-frame z (m), 0 where nothing was hit -> (H, W) uint16 z x 256,
    rounded; 0 where nothing was hit or where z x 256 passes the uint16 range (beyond 255.99 m),
    as in KITTI's depth maps, whose readers take 0 for "no depth"."""
    scaled = np.rint(depth.astype(np.float32, copy=False) * np.float32(DEPTH_SCALE))
    return np.where(scaled <= np.iinfo(np.uint16).max, scaled, 0).astype(np.uint16)


def face_classes(world: World, face_owner: np.ndarray) -> np.ndarray:
    """The lidarseg class of every face the camera renderer draws (:class:`simgen.camera.Renderer`
    after ``set_world(world)``), indexed as its id pass indexes them: (F,) uint8, 0 for the sky.

    The renderer's face table is the sky, then the static world (its static mesh and the actors
    that never move) in tiles of ``STATIC_TILE`` metres, then each moving actor; it keeps the
    actor id of each face (``face_owner``, (F,) int, 0 for the sky and the static mesh) but not
    the static mesh's surface classes, so the static part's order is rebuilt here the way the
    renderer builds it, and checked against ``face_owner``.
    """
    static_class, static_owner, triangles = _static_faces(world)
    order = np.concatenate(static_tiles(triangles, STATIC_TILE))
    n_static = len(order)
    if len(face_owner) < 1 + n_static or np.any(face_owner[1:1 + n_static] != static_owner[order]):
        raise RuntimeError("the camera renderer's face table is not in the order labels.face_classes rebuilds")
    surface = np.zeros(len(face_owner), np.uint8)                 # sky and moving actors: read by id
    surface[1:1 + n_static] = static_class[order]
    return lidarseg.classes(np.asarray(face_owner), surface, lidarseg.class_of_id(world))


def _static_faces(world: World) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The static world as the renderer merges it: the static mesh's faces, then those of each
    annotated actor that never moves, posed at t = 0. Returns per face its surface class (F,)
    uint8 (0 for the actors: they are labelled by id), its actor id (F,) int32 (0 for the static
    mesh) and its (F, 3, 3) global triangle."""
    sm = world.static_mesh
    classes = [np.asarray(sm.metadata["lidarseg"], np.uint8)]
    owners = [np.zeros(len(sm.faces), np.int32)]
    triangles = [np.asarray(sm.triangles)]
    moving = world.speed.max(axis=1) > 0
    boxes = world.boxes_at(0.0)
    for i, a in enumerate(world.actors):
        if a.annotate and not moving[i]:
            T_global_from_box = geometry.pose_2d(boxes[i, 0], boxes[i, 1], boxes[i, 6], boxes[i, 2])
            triangles.append(np.asarray(a.mesh.triangles) @ T_global_from_box[:3, :3].T + T_global_from_box[:3, 3])
            classes.append(np.zeros(len(a.mesh.faces), np.uint8))
            owners.append(np.full(len(a.mesh.faces), a.id, np.int32))
    return np.concatenate(classes), np.concatenate(owners), np.concatenate(triangles)


def seg_image(face: np.ndarray, face_class: np.ndarray) -> np.ndarray:
    """(H, W) rendered face indices (:class:`simgen.camera.IdImage` ``.face``) -> (H, W) uint8
    lidarseg class per pixel, 0 (void) where the sky is."""
    return np.take(face_class, face)
