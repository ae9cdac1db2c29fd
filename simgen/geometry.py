"""Pure numpy geometry: rigid transforms, quaternions, boxes and pinhole projection.

Conventions
-----------
- Transforms are 4x4 homogeneous matrices named by their frames, ``T_ego_from_lidar``, so
  chains cancel visibly: ``T_global_from_lidar = T_global_from_ego @ T_ego_from_lidar``.
- Quaternions are (w, x, y, z), as in nuScenes.
- Boxes are (x, y, z, l, w, h, yaw): centre, length along the heading, width, height, and the
  yaw about +z from +x. nuScenes stores ``size = (w, l, h)``; convert only with
  :func:`box_to_nuscenes` / :func:`box_from_nuscenes`.
- Points are (n, 3) or (n, C); the devkit's (3, n) layout appears only at the devkit boundary.
"""
from __future__ import annotations

import numpy as np

# scipy.spatial is imported where it is used: the process that only coordinates `simgen make`
# workers imports this module but never needs it.


def quat_wxyz_to_matrix(q) -> np.ndarray:
    """(4,) wxyz quaternion -> (3, 3) rotation matrix."""
    from scipy.spatial.transform import Rotation
    w, x, y, z = np.asarray(q, dtype=np.float64)
    return Rotation.from_quat([x, y, z, w]).as_matrix()


def matrix_to_quat_wxyz(R: np.ndarray) -> np.ndarray:
    """(3, 3) rotation matrix -> (4,) wxyz quaternion with w >= 0."""
    from scipy.spatial.transform import Rotation
    x, y, z, w = Rotation.from_matrix(R).as_quat()
    q = np.array([w, x, y, z])
    return q if q[0] >= 0 else -q


def yaw_to_quat_wxyz(yaw: float) -> np.ndarray:
    """Rotation about +z by ``yaw`` radians -> (4,) wxyz quaternion."""
    return np.array([np.cos(yaw / 2.0), 0.0, 0.0, np.sin(yaw / 2.0)])


def quat_wxyz_to_yaw(q) -> float:
    """Yaw (about +z, from +x) of a wxyz quaternion, in (-pi, pi]."""
    R = quat_wxyz_to_matrix(q)
    return float(np.arctan2(R[1, 0], R[0, 0]))


def make_transform(R: np.ndarray, t) -> np.ndarray:
    """(3, 3) rotation and (3,) translation -> (4, 4) transform."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def transform_from_quat(t, q_wxyz) -> np.ndarray:
    """nuScenes (translation, rotation wxyz) record -> (4, 4) transform."""
    return make_transform(quat_wxyz_to_matrix(q_wxyz), t)


def pose_2d(x, y, yaw, z=0.0) -> np.ndarray:
    """Planar pose -> (4, 4) transform (rotation about +z, then translation)."""
    c, s = np.cos(yaw), np.sin(yaw)
    T = np.eye(4)
    T[:2, :2] = [[c, -s], [s, c]]
    T[:3, 3] = (x, y, z)
    return T


def poses_2d(x: np.ndarray, y: np.ndarray, yaw: np.ndarray, z=0.0) -> np.ndarray:
    """Vectorised :func:`pose_2d`: (n,) arrays -> (n, 4, 4)."""
    n = len(x)
    T = np.zeros((n, 4, 4))
    c, s = np.cos(yaw), np.sin(yaw)
    T[:, 0, 0], T[:, 0, 1], T[:, 1, 0], T[:, 1, 1] = c, -s, s, c
    T[:, 2, 2] = T[:, 3, 3] = 1.0
    T[:, 0, 3], T[:, 1, 3], T[:, 2, 3] = x, y, z
    return T


def invert(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid (..., 4, 4) transform."""
    R = T[..., :3, :3]
    t = T[..., :3, 3]
    Ti = np.zeros_like(T)
    Rt = np.swapaxes(R, -1, -2)
    Ti[..., :3, :3] = Rt
    Ti[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, t)
    Ti[..., 3, 3] = 1.0
    return Ti


def apply(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a (4, 4) transform to (n, 3) points -> (n, 3)."""
    return points @ T[:3, :3].T + T[:3, 3]


def wrap_angle(a):
    """Wrap angles to (-pi, pi]."""
    return np.pi - np.mod(np.pi - np.asarray(a), 2.0 * np.pi)


def box_corners(box) -> np.ndarray:
    """(7,) box (x, y, z, l, w, h, yaw) -> (8, 3) corners in the box's parent frame.

    Order: the bottom corners front-left, front-right, rear-right, rear-left (clockwise seen
    from above), then the top corners in the same order.
    """
    x, y, z, l, w, h, yaw = np.asarray(box, dtype=np.float64)
    sx = np.array([1, 1, -1, -1, 1, 1, -1, -1]) * l / 2
    sy = np.array([1, -1, -1, 1, 1, -1, -1, 1]) * w / 2
    sz = np.array([-1, -1, -1, -1, 1, 1, 1, 1]) * h / 2
    c, s = np.cos(yaw), np.sin(yaw)
    return np.stack([x + c * sx - s * sy, y + s * sx + c * sy, z + sz], axis=1)


def bev_corners(boxes: np.ndarray) -> np.ndarray:
    """(n, >=7) boxes -> (n, 4, 2) BEV footprint corners, counter-clockwise."""
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, boxes.shape[-1])
    sx = np.array([1, -1, -1, 1]) * 0.5
    sy = np.array([1, 1, -1, -1]) * 0.5
    dx = sx[None] * boxes[:, 3:4]
    dy = sy[None] * boxes[:, 4:5]
    c, s = np.cos(boxes[:, 6:7]), np.sin(boxes[:, 6:7])
    return np.stack([boxes[:, 0:1] + c * dx - s * dy, boxes[:, 1:2] + s * dx + c * dy], axis=-1)


def bev_overlap_pairwise(a: np.ndarray, b: np.ndarray, margin: float = 0.0) -> np.ndarray:
    """Whether the BEV footprints of boxes ``a[k]`` and ``b[k]`` intersect (separating axes).

    Parameters
    ----------
    a, b : (k, >=7) boxes, compared row by row.
    margin : grow every box by this much on each side before testing (metres).

    Returns
    -------
    (k,) bool; touching counts as overlapping.
    """
    a = np.asarray(a, dtype=np.float64).reshape(-1, np.shape(a)[-1])[:, :7].copy()
    b = np.asarray(b, dtype=np.float64).reshape(-1, np.shape(b)[-1])[:, :7].copy()
    a[:, 3:5] += 2 * margin
    b[:, 3:5] += 2 * margin
    ca, cb = bev_corners(a), bev_corners(b)                       # (k, 4, 2)
    sep = np.zeros(len(a), dtype=bool)
    for box in (a, b):
        c, s = np.cos(box[:, 6]), np.sin(box[:, 6])
        for ax in (np.stack([c, s], -1), np.stack([-s, c], -1)):  # the box's two edge normals
            pa = np.einsum("kcd,kd->kc", ca, ax)
            pb = np.einsum("kcd,kd->kc", cb, ax)
            sep |= (pa.max(-1) < pb.min(-1)) | (pb.max(-1) < pa.min(-1))
    return ~sep


def bev_overlap(a: np.ndarray, b: np.ndarray, margin: float = 0.0) -> np.ndarray:
    """(n, >=7) and (m, >=7) boxes -> (n, m) bool: whether their BEV footprints intersect."""
    n, m = len(a), len(b)
    ia, ib = np.meshgrid(np.arange(n), np.arange(m), indexing="ij")
    return bev_overlap_pairwise(np.asarray(a)[ia.ravel()], np.asarray(b)[ib.ravel()], margin).reshape(n, m)


def near_pairs(a: np.ndarray, b: np.ndarray, pad: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs (i, j) whose BEV bounding circles (plus ``pad``) meet: a cheap pre-filter."""
    from scipy.spatial import cKDTree
    if len(a) == 0 or len(b) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    ra = np.hypot(a[:, 3], a[:, 4]) / 2
    rb = np.hypot(b[:, 3], b[:, 4]) / 2
    reach = ra.max() + rb.max() + pad
    m = cKDTree(a[:, :2]).sparse_distance_matrix(cKDTree(b[:, :2]), reach, output_type="ndarray")
    i, j, d = m["i"].astype(np.int64), m["j"].astype(np.int64), m["v"]
    keep = d <= ra[i] + rb[j] + pad
    order = np.lexsort((j[keep], i[keep]))
    return i[keep][order], j[keep][order]


# Corner signs of the devkit's Box.corners, (x forward, y left, z up) in units of half the box:
# corners 0-3 are the front face, and 4, 1 and 3 lie along the box's x, y and z edges from 0.
DEVKIT_CORNER_SIGNS = (np.array([1, 1, 1, 1, -1, -1, -1, -1]), np.array([1, -1, -1, 1, 1, -1, -1, 1]),
                       np.array([1, 1, -1, -1, 1, 1, -1, -1]))


def points_in_box(points: np.ndarray, corners: np.ndarray) -> np.ndarray:
    """The points-in-box test: (3, n) points and a box's (3, 8) corners in the devkit's order
    (:data:`DEVKIT_CORNER_SIGNS`), in the same frame -> (n,) bool, boundary inclusive.

    The operations of the devkit's ``points_in_box`` in its order, on its (3, n) layout, so that
    a count equals the devkit's on the same floats (labels' ``num_lidar_pts`` relies on it).
    """
    p1 = corners[:, 0]
    v = points - p1.reshape((-1, 1))
    inside = np.ones(v.shape[1], bool)
    for corner in (4, 1, 3):                                 # the box's x, y and z edges from p1
        e = corners[:, corner] - p1
        ev = np.dot(e, v)
        inside &= (0 <= ev) & (ev <= np.dot(e, e))
    return inside


def points_in_box_mask(points: np.ndarray, box) -> np.ndarray:
    """(n, >=3) points and one (7,) box in the same frame -> (n,) bool, boundary inclusive."""
    x, y, z, l, w, h, yaw = (float(v) for v in box)
    sx, sy, sz = (sign * half for sign, half in zip(DEVKIT_CORNER_SIGNS, (l / 2, w / 2, h / 2)))
    c, s = np.cos(yaw), np.sin(yaw)
    corners = np.stack([x + c * sx - s * sy, y + s * sx + c * sy, z + sz])      # (3, 8)
    return points_in_box(np.asarray(points, dtype=np.float64)[:, :3].T, corners)


def box_to_nuscenes(box) -> tuple[list[float], list[float], list[float]]:
    """(7,) box -> nuScenes (translation xyz, size wlh, rotation wxyz)."""
    x, y, z, l, w, h, yaw = (float(v) for v in box)
    return [x, y, z], [w, l, h], [float(v) for v in yaw_to_quat_wxyz(yaw)]


def box_from_nuscenes(translation, size_wlh, rotation_wxyz) -> np.ndarray:
    """nuScenes (translation, size wlh, rotation wxyz) -> (7,) box."""
    w, l, h = size_wlh
    return np.array([*translation, l, w, h, quat_wxyz_to_yaw(rotation_wxyz)])


def scale_intrinsics(K: np.ndarray, sx: float, sy: float) -> np.ndarray:
    """Intrinsics for an image resized by (sx, sy) (pixel-edge convention)."""
    K = np.array(K, dtype=np.float64)
    K[0] *= sx
    K[1] *= sy
    return K


def project(K_cam: np.ndarray, points_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pinhole projection of (n, 3) camera-frame points (x right, y down, z forward).

    Returns (n, 2) pixels (u right, v down) and (n,) depth z. Points with z <= 0 get NaN pixels.
    """
    z = points_cam[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = (points_cam @ K_cam.T)[:, :2] / z[:, None]
    uv[z <= 0] = np.nan
    return uv, z
