"""simgen.geometry and simgen.rig against the nuScenes devkit, pyquaternion, shapely and hand math."""
from __future__ import annotations

import numpy as np
import pytest
from nuscenes.eval.common.utils import quaternion_yaw
from nuscenes.utils.data_classes import Box
from nuscenes.utils.geometry_utils import points_in_box
from pyquaternion import Quaternion
from shapely.geometry import Polygon

from simgen import geometry
from simgen import rig

# The nuScenes v1.0-mini calibration (its calibrated_sensor table): channel -> (translation, rotation wxyz, fx = fy, cx, cy).
RIG_TABLE = {
    "CAM_FRONT": ((1.7008, 0.0159, 1.5110), (.49980, -.50303, .49978, -.49737), 1266.42, 816.27, 491.51),
    "CAM_FRONT_RIGHT": ((1.5508, -0.4934, 1.4957), (.20603, -.20269, .68245, -.67136), 1260.85, 807.97, 495.33),
    "CAM_BACK_RIGHT": ((1.0149, -0.4806, 1.5624), (.12281, -.13240, -.70043, .69050), 1259.51, 807.25, 501.20),
    "CAM_BACK": ((0.0283, 0.0035, 1.5791), (.50379, -.49740, -.49419, .50455), 809.22, 829.22, 481.78),
    "CAM_BACK_LEFT": ((1.0357, 0.4848, 1.5910), (.69242, -.70316, -.11648, .11203), 1256.74, 792.11, 492.78),
    "CAM_FRONT_LEFT": ((1.5239, 0.4946, 1.5093), (.67573, -.67363, .21214, -.21123), 1272.60, 826.62, 479.75),
}
LIDAR_TABLE = ((0.943713, 0.0, 1.84023), (.70780, -.00649, .01065, -.70631))


def random_quats(rng, n):
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return np.where(q[:, :1] < 0, -q, q)           # w >= 0, the form matrix_to_quat_wxyz returns


def random_rigid(rng, n):
    T = np.zeros((n, 4, 4))
    for k, q in enumerate(random_quats(rng, n)):
        T[k] = geometry.transform_from_quat(rng.uniform(-50, 50, 3), q)
    return T


def random_boxes(rng, n, spread=6.0):
    """(n, 7) boxes with centres in a small square, so that about half of random pairs overlap."""
    return np.column_stack([
        rng.uniform(-spread, spread, (n, 2)), rng.uniform(-1, 1, n),
        rng.uniform(0.3, 8.0, n), rng.uniform(0.3, 3.0, n), rng.uniform(0.5, 3.0, n),
        rng.uniform(-np.pi, np.pi, n)])


def footprint(box, margin=0.0):
    return Polygon(geometry.bev_corners(np.asarray(box, float)[None] + np.r_[0, 0, 0, 2 * margin, 2 * margin, 0, 0])[0])


def same_point_set(a, b, tol):
    """True when the (8, 3) point sets a and b are equal up to order (all points distinct)."""
    D = np.linalg.norm(a[:, None] - b[None], axis=-1)
    return bool((D.min(0) < tol).all() and (D.min(1) < tol).all())


# ---------------------------------------------------------------------------------------------
# Quaternions, matrices, yaw

def test_quat_matrix_round_trip_random():
    rng = np.random.default_rng(0)
    for q in random_quats(rng, 200):
        R = geometry.quat_wxyz_to_matrix(q)
        np.testing.assert_allclose(R, Quaternion(q).rotation_matrix, atol=1e-12)   # wxyz, like pyquaternion
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-12)
        q2 = geometry.matrix_to_quat_wxyz(R)
        assert q2[0] >= 0
        np.testing.assert_allclose(q2, q, atol=1e-9)
        np.testing.assert_allclose(geometry.quat_wxyz_to_matrix(q2), R, atol=1e-12)


def test_matrix_to_quat_returns_nonnegative_w_for_sign_flipped_input():
    rng = np.random.default_rng(1)
    for q in random_quats(rng, 50):
        R = geometry.quat_wxyz_to_matrix(-q)                         # -q is the same rotation
        np.testing.assert_allclose(geometry.matrix_to_quat_wxyz(R), q, atol=1e-9)


def test_yaw_round_trip_random():
    rng = np.random.default_rng(2)
    for yaw in rng.uniform(-np.pi, np.pi, 300):
        q = geometry.yaw_to_quat_wxyz(yaw)
        ref = Quaternion(axis=[0, 0, 1], angle=yaw)
        np.testing.assert_allclose(q, ref.elements, atol=1e-12)
        assert geometry.quat_wxyz_to_yaw(q) == pytest.approx(yaw, abs=1e-12)
        assert geometry.quat_wxyz_to_yaw(q) == pytest.approx(quaternion_yaw(ref), abs=1e-12)
        np.testing.assert_allclose(geometry.quat_wxyz_to_matrix(q), geometry.pose_2d(0, 0, yaw)[:3, :3], atol=1e-12)
    # yaw outside (-pi, pi] comes back wrapped
    for yaw in (np.pi, 3 * np.pi / 2, -3.0 * np.pi + 0.1, 7.0):
        back = geometry.quat_wxyz_to_yaw(geometry.yaw_to_quat_wxyz(yaw))
        assert -np.pi - 1e-12 <= back <= np.pi + 1e-12
        assert geometry.wrap_angle(back - yaw) == pytest.approx(0.0, abs=1e-12)


def test_quat_to_yaw_matches_devkit_on_general_rotations():
    rng = np.random.default_rng(3)
    for q in random_quats(rng, 200):
        assert geometry.quat_wxyz_to_yaw(q) == pytest.approx(quaternion_yaw(Quaternion(q)), abs=1e-9)


# ---------------------------------------------------------------------------------------------
# Transforms

def test_invert_matches_numpy_inverse():
    rng = np.random.default_rng(4)
    T = random_rigid(rng, 100)
    Ti = geometry.invert(T)                                       # batched (n, 4, 4)
    np.testing.assert_allclose(Ti, np.linalg.inv(T), atol=1e-10)
    for k in range(5):                                       # single (4, 4)
        np.testing.assert_allclose(geometry.invert(T[k]), np.linalg.inv(T[k]), atol=1e-10)
        np.testing.assert_allclose(geometry.invert(T[k]) @ T[k], np.eye(4), atol=1e-10)


def test_apply_and_pose_2d():
    rng = np.random.default_rng(5)
    T = random_rigid(rng, 1)[0]
    p = rng.normal(size=(20, 3))
    ph = np.c_[p, np.ones(20)] @ T.T
    np.testing.assert_allclose(geometry.apply(T, p), ph[:, :3], atol=1e-12)
    x, y, yaw = rng.normal(size=(3, 10))
    Tb = geometry.poses_2d(x, y, yaw, z=0.5)
    for k in range(10):
        np.testing.assert_allclose(Tb[k], geometry.pose_2d(x[k], y[k], yaw[k], 0.5), atol=1e-12)
        np.testing.assert_allclose(Tb[k][:3, :3], geometry.quat_wxyz_to_matrix(geometry.yaw_to_quat_wxyz(yaw[k])), atol=1e-12)


# ---------------------------------------------------------------------------------------------
# Boxes

def test_box_nuscenes_round_trip_and_size_order():
    rng = np.random.default_rng(6)
    for box in random_boxes(rng, 200):
        t, size, rot = geometry.box_to_nuscenes(box)
        x, y, z, l, w, h, yaw = box
        assert t == pytest.approx([x, y, z], abs=0)
        assert size == pytest.approx([w, l, h], abs=0)           # nuScenes: w, l, h
        np.testing.assert_allclose(rot, Quaternion(axis=[0, 0, 1], angle=yaw).elements, atol=1e-12)
        assert all(isinstance(v, float) for v in [*t, *size, *rot])     # JSON-serialisable
        back = geometry.box_from_nuscenes(t, size, rot)
        np.testing.assert_allclose(back[:6], box[:6], atol=0)
        assert geometry.wrap_angle(back[6] - yaw) == pytest.approx(0.0, abs=1e-12)


def test_box_corners_match_devkit():
    rng = np.random.default_rng(7)
    for box in random_boxes(rng, 100, spread=50.0):
        x, y, z, l, w, h, yaw = box
        ours = geometry.box_corners(box)
        dev = Box([x, y, z], [w, l, h], Quaternion(axis=[0, 0, 1], angle=yaw)).corners().T
        assert ours.shape == (8, 3)
        assert same_point_set(ours, dev, 1e-9)
        # the first four are the bottom face and corners[i + 4] lies right above corners[i]
        np.testing.assert_allclose(ours[:4, 2], z - h / 2, atol=1e-12)
        np.testing.assert_allclose(ours[4:, :2], ours[:4, :2], atol=1e-12)
        np.testing.assert_allclose(ours[4:, 2], z + h / 2, atol=1e-12)
        # the BEV corners are the same footprint
        assert same_point_set(np.c_[geometry.bev_corners(box[None])[0], np.zeros(4)],
                              np.c_[ours[:4, :2], np.zeros(4)], 1e-9)


def test_bev_corners_counter_clockwise():
    rng = np.random.default_rng(8)
    for c in geometry.bev_corners(random_boxes(rng, 50)):
        area = 0.5 * np.sum(c[:, 0] * np.roll(c[:, 1], -1) - np.roll(c[:, 0], -1) * c[:, 1])
        assert area > 0


def test_bev_overlap_matches_shapely_on_random_pairs():
    rng = np.random.default_rng(9)
    a, b = random_boxes(rng, 500, spread=4.0), random_boxes(rng, 500, spread=4.0)
    ours = geometry.bev_overlap_pairwise(a, b)
    ref = np.array([footprint(p).intersects(footprint(q)) for p, q in zip(a, b)])
    assert 0.2 < ref.mean() < 0.8                         # both outcomes are well represented
    np.testing.assert_array_equal(ours, ref)
    # symmetric, and a box always overlaps itself
    np.testing.assert_array_equal(geometry.bev_overlap_pairwise(b, a), ours)
    assert geometry.bev_overlap_pairwise(a, a).all()


def test_bev_overlap_margin_matches_shapely_on_grown_boxes():
    rng = np.random.default_rng(10)
    a, b = random_boxes(rng, 500, spread=8.0), random_boxes(rng, 500, spread=8.0)
    for margin in (0.3, 1.0):
        ours = geometry.bev_overlap_pairwise(a, b, margin)
        ref = np.array([footprint(p, margin).intersects(footprint(q, margin)) for p, q in zip(a, b)])
        np.testing.assert_array_equal(ours, ref)
        assert (ours >= geometry.bev_overlap_pairwise(a, b)).all()      # a margin never removes overlaps


def test_bev_overlap_matrix_matches_pairwise_and_shapely():
    rng = np.random.default_rng(11)
    a, b = random_boxes(rng, 25), random_boxes(rng, 20)
    M = geometry.bev_overlap(a, b)
    assert M.shape == (25, 20)
    ref = np.array([[footprint(p).intersects(footprint(q)) for q in b] for p in a])
    np.testing.assert_array_equal(M, ref)
    # extra columns beyond the 7 box values are ignored
    np.testing.assert_array_equal(geometry.bev_overlap(np.c_[a, np.ones((25, 2))], b), M)


def test_bev_overlap_touching_counts_and_gap_does_not():
    base = np.array([0.0, 0.0, 0.0, 4.0, 2.0, 1.5, 0.0])
    touching = base + [4.0, 0, 0, 0, 0, 0, 0]               # shares the edge x = 2
    apart = base + [4.01, 0, 0, 0, 0, 0, 0]
    assert geometry.bev_overlap_pairwise(base[None], touching[None])[0]
    assert not geometry.bev_overlap_pairwise(base[None], apart[None])[0]
    assert geometry.bev_overlap_pairwise(base[None], apart[None], margin=0.006)[0]
    # a rotated box whose corner region misses, although the bounding circles meet
    rot = np.array([3.2, 2.2, 0.0, 2.0, 1.0, 1.0, np.pi / 4])
    assert not geometry.bev_overlap_pairwise(base[None], rot[None])[0]
    assert not footprint(base).intersects(footprint(rot))


def test_points_in_box_mask_matches_devkit():
    rng = np.random.default_rng(12)
    for box in random_boxes(rng, 50, spread=20.0):
        x, y, z, l, w, h, yaw = box
        pts = np.array([x, y, z]) + rng.uniform(-1, 1, (2000, 3)) * np.array([l, l, h]) * 0.8
        ours = geometry.points_in_box_mask(pts, box)
        dev = points_in_box(Box([x, y, z], [w, l, h], Quaternion(axis=[0, 0, 1], angle=yaw)), pts.T)
        assert ours.any() and not ours.all()
        np.testing.assert_array_equal(ours, dev)
        # extra point columns (intensity, ring) are ignored
        np.testing.assert_array_equal(geometry.points_in_box_mask(np.c_[pts, np.ones((2000, 2))], box), ours)


def test_points_in_box_mask_boundary_inclusive():
    box = np.array([1.0, 2.0, 0.5, 4.0, 2.0, 1.0, 0.0])
    pts = np.array([[3.0, 2.0, 0.5], [1.0, 3.0, 0.5], [1.0, 2.0, 1.0], [3.0 + 1e-9, 2.0, 0.5]])
    np.testing.assert_array_equal(geometry.points_in_box_mask(pts, box), [True, True, True, False])


# ---------------------------------------------------------------------------------------------
# Projection and the rig

def test_project_optical_axis_and_hand_computed_point():
    cam = {c.channel: c for c in rig.cameras()}["CAM_FRONT"]
    K = cam.K
    cx, cy = K[0, 2], K[1, 2]
    uv, z = geometry.project(K, np.array([[0.0, 0.0, 7.5], [0.0, 0.0, 123.0]]))
    np.testing.assert_allclose(uv, [[cx, cy], [cx, cy]], atol=1e-9)
    np.testing.assert_allclose(z, [7.5, 123.0])
    p = np.array([[1.5, -0.8, 12.0], [-4.0, 2.0, 5.0]])
    uv, z = geometry.project(K, p)
    expect = np.array([[1266.42 * 1.5 / 12.0 + 816.27, 1266.42 * -0.8 / 12.0 + 491.51],
                       [1266.42 * -4.0 / 5.0 + 816.27, 1266.42 * 2.0 / 5.0 + 491.51]])
    np.testing.assert_allclose(uv, expect, atol=1e-9)
    np.testing.assert_allclose(z, [12.0, 5.0])
    # behind or on the camera plane: NaN pixels, the depth is still returned
    uv, z = geometry.project(K, np.array([[1.0, 1.0, -3.0], [1.0, 1.0, 0.0], [0.0, 0.0, 2.0]]))
    assert np.isnan(uv[:2]).all() and np.isfinite(uv[2]).all()
    np.testing.assert_allclose(z, [-3.0, 0.0, 2.0])


def test_point_ahead_projects_near_front_centre_and_is_behind_back_camera():
    cams = {c.channel: c for c in rig.cameras()}
    front = cams["CAM_FRONT"]
    p_ego = np.array([[front.translation[0] + 10.0, front.translation[1], front.translation[2]]])
    T_cam_from_ego = geometry.invert(front.T_ego_from_cam)
    p_cam = geometry.apply(T_cam_from_ego, p_ego)
    uv, z = geometry.project(front.K, p_cam)
    assert z[0] == pytest.approx(10.0, abs=0.01)
    # the camera is a fraction of a degree off the ego axes: within 0.5 deg of the principal point
    assert np.hypot(*(uv[0] - front.K[:2, 2])) < 0.5 * np.pi / 180 * front.K[0, 0]
    # ...and exactly where pyquaternion puts it
    R = Quaternion(RIG_TABLE["CAM_FRONT"][1]).normalised.rotation_matrix
    pc = R.T @ (p_ego[0] - np.array(RIG_TABLE["CAM_FRONT"][0]))
    np.testing.assert_allclose(p_cam[0], pc, atol=1e-9)
    np.testing.assert_allclose(uv[0], (front.K @ pc)[:2] / pc[2], atol=1e-6)

    back = cams["CAM_BACK"]
    p_back = geometry.apply(geometry.invert(back.T_ego_from_cam), p_ego)
    assert p_back[0, 2] < -9.0
    uv_b, _ = geometry.project(back.K, p_back)
    assert np.isnan(uv_b).all()
    # and a point 10 m behind CAM_BACK projects near its own principal point
    q_ego = np.array([[back.translation[0] - 10.0, back.translation[1], back.translation[2]]])
    uv_q, z_q = geometry.project(back.K, geometry.apply(geometry.invert(back.T_ego_from_cam), q_ego))
    assert z_q[0] == pytest.approx(10.0, abs=0.01)
    assert np.hypot(*(uv_q[0] - back.K[:2, 2])) < 1.0 * np.pi / 180 * back.K[0, 0]


def test_camera_axes_point_where_the_channel_says():
    azimuth = {"CAM_FRONT": 0, "CAM_FRONT_LEFT": 55, "CAM_BACK_LEFT": 110, "CAM_BACK": 180,
               "CAM_BACK_RIGHT": -110, "CAM_FRONT_RIGHT": -55}
    for cam in rig.cameras():
        az = np.degrees(cam.center_azimuth)
        assert abs(geometry.wrap_angle(np.radians(az - azimuth[cam.channel]))) < np.radians(5), (cam.channel, az)
        R = cam.T_ego_from_cam[:3, :3]
        assert R[2, 1] < -0.99                      # camera y (down) is ego -z
        assert abs(R[2, 2]) < 0.05                  # optical axis near horizontal


def test_rig_matches_reference_calibration():
    cams = rig.cameras()
    assert [c.channel for c in cams] == list(rig.CAMERAS)
    assert set(rig.CAMERAS) == set(RIG_TABLE)
    for cam in cams:
        t, q, f, cx, cy = RIG_TABLE[cam.channel]
        np.testing.assert_allclose(cam.translation, t, atol=0)
        np.testing.assert_allclose(cam.rotation, np.array(q) / np.linalg.norm(q), atol=1e-12)
        np.testing.assert_allclose(cam.K, [[f, 0, cx], [0, f, cy], [0, 0, 1]], atol=1e-9)
        assert cam.resolution == (1600, 900)
        np.testing.assert_allclose(cam.T_ego_from_cam[:3, 3], t, atol=0)
        np.testing.assert_allclose(cam.T_ego_from_cam[:3, :3],
                                   Quaternion(q).normalised.rotation_matrix, atol=1e-12)
    fx = [c.K[0, 0] for c in cams]
    assert len(set(fx)) == 6                         # every camera has its own focal length
    assert {c.channel: c.K[0, 0] for c in cams}["CAM_BACK"] == pytest.approx(809.22)


def test_cameras_scale_intrinsics_exactly():
    full = {c.channel: c for c in rig.cameras()}
    half = {c.channel: c for c in rig.cameras((800, 450))}
    for ch, c in half.items():
        K, Kf = c.K, full[ch].K
        assert c.resolution == (800, 450)
        assert K[0, 0] == 0.5 * Kf[0, 0] and K[1, 1] == 0.5 * Kf[1, 1]
        assert K[0, 2] == 0.5 * Kf[0, 2] and K[1, 2] == 0.5 * Kf[1, 2]
        assert K[0, 1] == 0 and K[1, 0] == 0 and (K[2] == [0, 0, 1]).all()
        np.testing.assert_array_equal(c.T_ego_from_cam, full[ch].T_ego_from_cam)
    # anisotropic scaling scales x and y rows separately
    odd = {c.channel: c for c in rig.cameras((400, 300))}["CAM_FRONT"].K
    np.testing.assert_allclose(odd[0], full["CAM_FRONT"].K[0] * 0.25, atol=1e-12)
    np.testing.assert_allclose(odd[1], full["CAM_FRONT"].K[1] / 3.0, atol=1e-12)


def test_lidar_top_extrinsics():
    T = rig.T_ego_from_lidar()
    np.testing.assert_allclose(T[:3, 3], LIDAR_TABLE[0], atol=0)
    R = T[:3, :3]
    np.testing.assert_allclose(R, Quaternion(LIDAR_TABLE[1]).normalised.rotation_matrix, atol=1e-12)
    # sensor x -> ego -y and sensor y -> ego +x. The real mount is tilted by 1.43 deg, so the ego z
    # components reach 0.024: the in-plane components are checked to 0.02, the whole axes to 0.03.
    np.testing.assert_allclose((R @ [1, 0, 0])[:2], [0, -1], atol=0.02)
    np.testing.assert_allclose((R @ [0, 1, 0])[:2], [1, 0], atol=0.02)
    np.testing.assert_allclose(R @ [1, 0, 0], [0, -1, 0], atol=0.03)
    np.testing.assert_allclose(R @ [0, 1, 0], [1, 0, 0], atol=0.03)
    np.testing.assert_allclose(R @ [0, 0, 1], [0, 0, 1], atol=0.03)
    assert np.degrees(np.arccos(R[2, 2])) == pytest.approx(1.43, abs=0.01)
    np.testing.assert_allclose(rig.lidar_rotation(), np.array(LIDAR_TABLE[1]) / np.linalg.norm(LIDAR_TABLE[1]),
                               atol=1e-12)
