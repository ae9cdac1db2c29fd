"""``motion_blur``: a line of exactly the kernel's length, direction and sum, along each camera's
horizon, applied to what the loader gives."""
from __future__ import annotations

import numpy as np
import pytest
from pyquaternion import Quaternion

from clfbev.config import tiny
from clfbev.corruptions import parse
from clfbev.data import NuScenesDetection
from clfbev.motion_blur import blur_images, blur_vectors, line_kernel

pytestmark = pytest.mark.usefixtures("one_thread")


def _blurred_dot(vector, size=41):
    """The blur of one bright pixel (value 1, channel 0) at the centre of a (1, 3, size, size) image."""
    image = np.zeros((1, 3, size, size), np.float32)
    image[0, 0, size // 2, size // 2] = 1.0
    out = blur_images(image, np.array([vector], float))[0]
    np.testing.assert_array_equal(out[1:], 0.0)
    return out[0]


def _placed(size, cells):
    """A (size, size) image holding ``{(dx, dy): value}`` about its centre."""
    img = np.zeros((size, size))
    for (dx, dy), v in cells.items():
        img[size // 2 + dy, size // 2 + dx] = v
    return img


def test_a_bright_pixel_becomes_the_exact_line():
    # Along an axis: L pixels of 1 / L each.
    np.testing.assert_allclose(_blurred_dot((7, 0)), _placed(41, {(x, 0): 1 / 7 for x in range(-3, 4)}), atol=1e-7)
    np.testing.assert_allclose(_blurred_dot((0, 5)), _placed(41, {(0, y): 1 / 5 for y in range(-2, 3)}), atol=1e-7)
    # At 45 deg the segment from (-2, -2) to (2, 2) crosses five diagonal pixels: the two end ones
    # hold half a pixel's diagonal, the three inner ones a whole one.
    diag = {(-2, -2): 1 / 8, (-1, -1): 1 / 4, (0, 0): 1 / 4, (1, 1): 1 / 4, (2, 2): 1 / 8}
    np.testing.assert_allclose(_blurred_dot((4, 4)), _placed(41, diag), atol=1e-7)


def test_an_oblique_line_keeps_its_length_direction_and_sum():
    v = np.array([9.3, -2.1])
    out = _blurred_dot(v)
    assert out.sum() == pytest.approx(1.0, abs=1e-6)
    np.testing.assert_allclose(out, out[::-1, ::-1], atol=1e-7)            # centred, point symmetric
    rows, cols = np.nonzero(out > 1e-9)
    xy = np.stack([cols - 20, rows - 20], axis=1).astype(float)
    u = v / np.linalg.norm(v)
    along, across = xy @ u, np.abs(xy @ np.array([-u[1], u[0]]))
    assert across.max() <= np.sqrt(0.5) + 1e-9                               # every pixel touches the segment
    assert along.max() == pytest.approx(np.linalg.norm(v) / 2, abs=np.sqrt(0.5))
    # The weights' first moment along the line: the segment's mean |t| is L / 4.
    weights = out[rows, cols]
    assert (weights * np.abs(along)).sum() == pytest.approx(np.linalg.norm(v) / 4, abs=0.1)
    assert line_kernel(v).sum() == pytest.approx(1.0, abs=1e-6)


def _horizon_by_vanishing_points(T_lidar_from_cam, K, up_lidar):
    """(N, 2) unit directions of the horizons, from the vanishing points of two horizontal directions."""
    out = []
    for T, k in zip(T_lidar_from_cam, K):
        axis = T[:3, 2] - (T[:3, 2] @ up_lidar) * up_lidar            # the optical axis, made horizontal
        axis /= np.linalg.norm(axis)
        side = np.cross(up_lidar, axis)
        vps = [k @ T[:3, :3].T @ (axis + a * side) for a in (-0.3, 0.3)]   # R_cam_from_lidar @ direction
        d = vps[1][:2] / vps[1][2] - vps[0][:2] / vps[0][2]
        out.append(d / np.linalg.norm(d))
    return np.array(out)


def test_the_loader_blurs_every_camera_along_its_horizon(tiny_dataset):
    cfg = tiny().data_config()
    clean = NuScenesDetection(tiny_dataset, "v1.0-sim", "sim-val", cfg)
    bad = NuScenesDetection(tiny_dataset, "v1.0-sim", "sim-val", cfg, (parse("motion_blur:21"),))
    s, b = clean[1], bad[1]
    sample = clean.nusc.get("sample", clean.sample_tokens[1])
    calib = clean.nusc.get("calibrated_sensor", clean.nusc.get("sample_data", sample["data"]["LIDAR_TOP"])["calibrated_sensor_token"])
    up_lidar = Quaternion(calib["rotation"]).rotation_matrix.T @ np.array([0.0, 0, 1])
    T, K, A = s.T_lidar_from_cam.astype(float), s.intrinsics.astype(float), s.img_aug.astype(float)
    d = _horizon_by_vanishing_points(T, K, up_lidar)
    vectors = 21.0 * np.einsum("nij,nj->ni", A[:, :2, :2], d)
    # the module's geometry agrees with the vanishing points (up to the line's sign) ...
    mine = blur_vectors(21.0, T, up_lidar, K, A)
    np.testing.assert_allclose(np.abs(np.einsum("ni,ni->n", mine, vectors)), np.einsum("ni,ni->n", vectors, vectors), rtol=1e-9)
    # ... and each camera's image is the clean one blurred along it, nothing else changes.
    np.testing.assert_allclose(b.images, blur_images(s.images, vectors), rtol=0, atol=1e-5)
    assert np.abs(b.images - s.images).max() > 0.5
    for name in ("T_lidar_from_cam", "intrinsics", "img_aug", "points", "gt_boxes"):
        np.testing.assert_array_equal(getattr(b, name), getattr(s, name))
    # The rig's cameras are level: each blur is nearly horizontal, 21 px of the original image long.
    assert (np.abs(d[:, 1]) < 0.05).all()
    np.testing.assert_allclose(np.linalg.norm(vectors, axis=1), 21.0 * A[:, 0, 0], rtol=0.01)
