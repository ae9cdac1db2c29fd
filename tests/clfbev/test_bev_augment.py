"""BEV-space augmentation (BEVDet's BDA, clfbev.augment.global_transform) with cached image
features: a box and the lifted camera features of the points inside it stay together under
rotation, scale and flip.

A synthetic camera sample with a known object: one camera at the lidar origin looking along +x,
a box 12 m ahead, and camera "features" made by hand: each feature cell whose ray crosses the box
puts all its depth weight on a bin whose frustum point lies inside the box and carries a marker
of 1; every other cell puts its weight on the first bin and carries 0. The features are never
changed (they are cached); only the geometry moves.
"""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
import torch

from clfbev.augment import AugmentConfig, global_matrix, global_transform, random_augment
from clfbev.camera_encoder import CameraEncoder, compress_z, lift_geometry, splat
from clfbev.data import Sample
from clfbev.geometry import CameraGeometry

H, W, STRIDE = 64, 128, 8
h, w = H // STRIDE, W // STRIDE
BINS = (1.0, 31.0, 0.5)
D = 60
PC_RANGE = (-32.0, -32.0, -4.0, 32.0, 32.0, 4.0)
VOXEL = (0.5, 0.5, 8.0)
K = np.array([[256.0, 0, 64], [0, 256.0, 32], [0, 0, 1]])
R_LIDAR_FROM_CAM = np.array([[0.0, 0, 1], [-1, 0, 0], [0, -1, 0]])     # camera z along lidar +x
BOX = np.array([12.0, 0.5, -0.3, 4.5, 3.0, 2.5, 0.3, 2.0, -1.0])        # x y z l w h yaw vx vy
CASES = [(0.4, 1.0, False), (0.0, 1.08, False), (0.0, 1.0, True), (-2.2, 0.93, True)]


def frustum(T_lidar_from_cam: np.ndarray) -> np.ndarray:
    """(D, h, w, 3) lidar-frame point of every bin of every feature cell, computed here: camera
    z = the bin centre depth along the ray through the cell centre."""
    depths = BINS[0] + BINS[2] * (np.arange(D) + 0.5)
    u, v = (np.arange(w) + 0.5) * STRIDE, (np.arange(h) + 0.5) * STRIDE
    vv, uu = np.meshgrid(v, u, indexing="ij")
    rays = np.stack([(uu - K[0, 2]) / K[0, 0], (vv - K[1, 2]) / K[1, 1], np.ones_like(uu)], -1)   # z = 1
    cam = depths[:, None, None, None] * rays[None]
    return cam @ T_lidar_from_cam[:3, :3].T + T_lidar_from_cam[:3, 3]


def inside(points: np.ndarray, box: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Inside mask and signed margin (m) of points (..., 3) in the box (>= 7,)."""
    c, s = math.cos(box[6]), math.sin(box[6])
    d = points - box[:3]
    local = np.stack([c * d[..., 0] + s * d[..., 1], -s * d[..., 0] + c * d[..., 1], d[..., 2]], -1)
    margin = (box[3:6] / 2 - np.abs(local)).min(-1)
    return margin >= 0, margin


def corners(box: np.ndarray) -> np.ndarray:
    """(8, 3) corners of a box (>= 7,)."""
    signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) / 2
    c, s = math.cos(box[6]), math.sin(box[6])
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    return (signs * box[3:6]) @ R.T + box[:3]


@pytest.fixture(scope="module")
def scene() -> tuple[Sample, np.ndarray, np.ndarray]:
    """The synthetic sample, its (D, h, w) one-hot depth and (h, w) marker."""
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R_LIDAR_FROM_CAM, [0.0, 0.0, 0.2]
    hit, margin = inside(frustum(T), BOX)
    hit &= margin > 0.02                                    # clear of the surface, for float32 below
    marker = hit.any(0)
    assert 20 <= marker.sum() < h * w                       # the object covers some cells, not all
    bins = np.where(marker, hit.argmax(0), 0)               # the first bin inside, else the nearest
    depth = (np.arange(D)[:, None, None] == bins).astype(np.float32)
    rng = np.random.default_rng(0)
    object_points = BOX[:3] + (rng.random((50, 3)) - 0.5) * BOX[3:6] * 0.8 @ np.diag([1, 1, 1])
    c, s = math.cos(BOX[6]), math.sin(BOX[6])
    object_points = (object_points - BOX[:3]) @ np.array([[c, s, 0], [-s, c, 0], [0, 0, 1]]) + BOX[:3]
    points = np.zeros((60, 5), np.float32)
    points[:50, :3] = object_points
    points[50:, :3] = rng.uniform(-20, 20, (10, 3)) * [1, 1, 0.1]
    sample = Sample(images=np.zeros((1, 3, 0, 0), np.float32), intrinsics=K[None].astype(np.float32),
                    T_lidar_from_cam=T[None].astype(np.float32), img_aug=np.eye(3, dtype=np.float32)[None],
                    points=points, gt_boxes=BOX[None].astype(np.float32), gt_labels=np.zeros(1, np.int64),
                    T_global_from_lidar=np.eye(4), sample_token="synthetic",
                    image_features=np.zeros((1, 8, h, w), np.float32))
    return sample, depth, marker


def lifted(sample: Sample) -> torch.Tensor:
    cams = CameraGeometry(torch.from_numpy(sample.intrinsics)[None], torch.from_numpy(sample.T_lidar_from_cam)[None],
                          torch.from_numpy(sample.img_aug)[None], (H, W), STRIDE, BINS)
    return lift_geometry(cams)[0, 0]                        # (D, h, w, 3)


def marker_bev(sample: Sample, depth: np.ndarray, marker: np.ndarray) -> np.ndarray:
    """The splat of the marker features with ``sample``'s geometry: (ny, nx)."""
    context = torch.from_numpy(marker.astype(np.float32))[None, None, None]          # (1, 1, 1, h, w)
    bev = splat(torch.from_numpy(depth)[None, None], context, lifted(sample)[None, None], PC_RANGE, VOXEL)
    return compress_z(bev)[0, 0].numpy()


def check_together(sample: Sample, aug: Sample, A: np.ndarray, depth: np.ndarray, marker: np.ndarray) -> None:
    """The augmented box, points and lifted features are the original ones moved by A."""
    box = aug.gt_boxes[0].astype(np.float64)
    # The box: its corners are A times the original's, its velocity the xy block of A times the old one.
    got, want = corners(box), corners(BOX) @ A[:3, :3].T
    assert np.abs(got[:, None] - want[None]).sum(-1).min(1).max() < 1e-4     # the same corners, in any order
    np.testing.assert_allclose(box[7:9], A[:2, :2] @ BOX[7:9], atol=1e-5)
    # The lidar points inside the object stay inside it.
    assert inside(aug.points[:50, :3].astype(np.float64), box)[0].all()
    # The lifted geometry is A applied to the frustum, before the splat ...
    before, after = frustum(sample.T_lidar_from_cam[0].astype(np.float64)), lifted(aug).double().numpy()
    np.testing.assert_allclose(after, before @ A[:3, :3].T + A[:3, 3], atol=2e-4)
    # ... so every frustum point is inside the moved box exactly when it was inside the box (the
    # ones within 1 mm of its surface aside), and the marked features, lifted, lie in it.
    was, m0 = inside(before, BOX)
    now, m1 = inside(after, box)
    clear = (np.abs(m0) > 1e-3) & (np.abs(m1) > 1e-3)
    assert np.array_equal(was[clear], now[clear]) and clear.mean() > 0.99
    lit = depth.astype(bool) & marker[None]
    assert now[lit].all() and lit.sum() == marker.sum()
    # The BEV: every marker lands in the cell of its moved point (binned here), the mass kept.
    bev = marker_bev(aug, depth, marker)
    cells = np.floor((after[lit][:, :2] - np.array(PC_RANGE[:2])) / np.array(VOXEL[:2])).astype(int)
    expected = np.zeros_like(bev)
    np.add.at(expected, (cells[:, 1], cells[:, 0]), 1.0)
    assert np.array_equal(bev, expected) and bev.sum() == marker.sum()


@pytest.mark.parametrize("rot, scale, flip", CASES)
def test_a_box_and_its_lifted_features_stay_together(scene, rot, scale, flip):
    sample, depth, marker = scene
    aug = global_transform(sample, rot, scale, flip)
    assert aug.image_features is sample.image_features and np.array_equal(aug.img_aug, sample.img_aug)
    check_together(sample, aug, global_matrix(rot, scale, flip), depth, marker)


def test_the_random_bev_augmentation_of_cached_features(scene):
    sample, depth, marker = scene
    cfg = AugmentConfig(image=False, rot_range=math.pi, scale_range=(0.9, 1.1), flip_y_prob=0.5)
    flips = set()
    for seed in range(6):
        aug = random_augment(sample, np.random.default_rng(seed), cfg)
        # No pixel or feature is touched; the draw is the lidar frame's similarity A.
        assert aug.image_features is sample.image_features and np.array_equal(aug.img_aug, sample.img_aug)
        A = aug.T_lidar_from_cam[0].astype(np.float64) @ np.linalg.inv(sample.T_lidar_from_cam[0].astype(np.float64))
        scale = abs(np.linalg.det(A[:3, :3])) ** (1 / 3)
        assert 0.9 - 1e-5 <= scale <= 1.1 + 1e-5
        np.testing.assert_allclose(A[:3, :3].T @ A[:3, :3], scale**2 * np.eye(3), atol=1e-5)
        flips.add(bool(np.linalg.det(A[:3, :3]) < 0))
        # The points come out shuffled: put them back in order to compare.
        order = np.lexsort(aug.points[:, :3].T)
        ref = np.lexsort(((sample.points[:, :3] @ A[:3, :3].T.astype(np.float32))).T)
        aug = replace(aug, points=aug.points[order][np.argsort(ref)])
        check_together(sample, aug, A, depth, marker)
    assert flips == {True, False}
    # With the image augmentation on, the same draws change the image geometry (img_aug) too.
    full = random_augment(replace(sample, images=np.zeros((1, 3, H, W), np.float32)), np.random.default_rng(0),
                          replace(cfg, image=True))
    assert not np.array_equal(full.img_aug, sample.img_aug)


def test_a_feature_map_flip_lifts_the_same_points():
    """Why the cached stage has no image flip: with the 1x1 depth net, a flipped feature map with
    img_aug flipped to match lifts the same frustum points with the same features."""
    torch.manual_seed(0)
    enc = CameraEncoder(18, 8, 16, BINS, 4, (H, W), STRIDE, PC_RANGE, VOXEL)
    enc.freeze_image_features()
    fpn = torch.randn(1, 2, 16, h, w)
    K2 = torch.from_numpy(K).float().expand(1, 2, 3, 3)
    T = torch.eye(4).expand(1, 2, 4, 4).clone()
    T[0, :, :3, :3] = torch.from_numpy(R_LIDAR_FROM_CAM).float()
    T[0, 1, :3, :3] = T[0, 1, :3, :3] @ torch.tensor([[0.0, 0, -1], [0, 1, 0], [1, 0, 0]])   # a second camera
    A = torch.eye(3).expand(1, 2, 3, 3)
    flip = torch.tensor([[-1.0, 0, W], [0, 1, 0], [0, 0, 1]])
    with torch.no_grad():
        bev, _, _ = enc.lift_splat(None, K2, T, A, fpn=fpn)
        bev_flipped, _, _ = enc.lift_splat(None, K2, T, flip @ A, fpn=fpn.flip(-1))
    assert bev.abs().sum() > 0
    torch.testing.assert_close(bev_flipped, bev, rtol=1e-5, atol=1e-5)
