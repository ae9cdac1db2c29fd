"""clfbev.augment: global BEV and image augmentations keep points, boxes, cameras and pixels aligned.

The real sample comes from the session fixture ``tiny_dataset`` (simgen CLI, see tests/conftest.py);
image-content tests use a small synthetic Sample with drawn markers.
"""
from __future__ import annotations

import math
from dataclasses import fields, replace

import numpy as np
import pytest

from clfbev.augment import (
    AugmentConfig, crop_to_range, global_matrix, global_transform, image_matrix, image_transform, random_augment,
)
from clfbev.data import DataConfig, NuScenesDetection, Sample

VERSION = "v1.0-sim"
# (rot, scale, flip_y) cases: each alone, and all together with an awkward angle.
GLOBAL_CASES = [(0.3, 1.0, False), (0.0, 1.07, False), (0.0, 1.0, True), (-2.9, 0.93, True)]


@pytest.fixture(scope="module")
def sample32(tiny_dataset) -> Sample:
    """A real float32 sample (the loader's dtypes)."""
    return NuScenesDetection(tiny_dataset, VERSION, "sim-train", DataConfig(min_points=5))[0]


@pytest.fixture(scope="module")
def sample64(sample32) -> Sample:
    """The same sample with every float tensor in float64, to test geometry far below a pixel."""
    return replace(sample32, **{
        f.name: getattr(sample32, f.name).astype(np.float64) for f in fields(Sample)
        if isinstance(getattr(sample32, f.name), np.ndarray) and getattr(sample32, f.name).dtype.kind == "f"
    })


def project(sample: Sample, p_lidar: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (N, M, 2) of (M, 3) lidar-frame points in every camera and camera-frame z (N, M)."""
    T_cam_from_lidar = np.linalg.inv(sample.T_lidar_from_cam.astype(np.float64))           # (N, 4, 4)
    P = sample.img_aug.astype(np.float64) @ sample.intrinsics.astype(np.float64)              # (N, 3, 3)
    p_cam = np.einsum("nij,mj->nmi", T_cam_from_lidar[:, :3, :3], p_lidar) + T_cam_from_lidar[:, None, :3, 3]
    uvw = np.einsum("nij,nmj->nmi", P, p_cam)
    return uvw[..., :2] / uvw[..., 2:3], p_cam[..., 2]


def in_boxes(points: np.ndarray, boxes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(M, n) inside mask of (n, 3) points in (M, >=7) boxes, and the signed margin to the surface (m)."""
    c, s = np.cos(boxes[:, 6]), np.sin(boxes[:, 6])
    d = points[None, :, :3] - boxes[:, None, :3]
    local = np.stack([c[:, None] * d[..., 0] + s[:, None] * d[..., 1],
                      -s[:, None] * d[..., 0] + c[:, None] * d[..., 1], d[..., 2]], axis=-1)   # R(-yaw) d
    margin = (boxes[:, None, 3:6] / 2 - np.abs(local)).min(axis=-1)
    return margin >= 0, margin


def assert_samples_equal(a: Sample, b: Sample, atol: float = 0.0):
    for f in fields(Sample):
        x, y = getattr(a, f.name), getattr(b, f.name)
        if isinstance(x, np.ndarray):
            assert x.dtype == y.dtype and x.shape == y.shape, f.name
            if atol == 0.0:
                assert np.array_equal(x, y), f.name
            else:
                np.testing.assert_allclose(x, y, atol=atol, rtol=0, err_msg=f.name)
        else:
            assert x == y, f.name


# ---------------------------------------------------------------- global transform

@pytest.mark.parametrize("rot, scale, flip", GLOBAL_CASES)
def test_box_centres_project_to_the_same_pixels(sample64, sample32, rot, scale, flip):
    centres = sample64.gt_boxes[:, :3]
    uv0, z0 = project(sample64, centres)
    aug = global_transform(sample64, rot, scale, flip)
    uv1, z1 = project(aug, aug.gt_boxes[:, :3])
    seen = z0 > 0.1
    assert seen.sum() >= len(centres) > 0                   # every box is in front of some camera
    np.testing.assert_array_equal(z1 > 0.1, seen)
    np.testing.assert_allclose(uv1[seen], uv0[seen], atol=1e-6, rtol=0)
    # float32 (the loader's dtype) keeps the rounding of float32 extrinsics: still far below a
    # pixel on the image (far off-image projections grow the error with |u|).
    aug32 = global_transform(sample32, rot, scale, flip)
    uv32, _ = project(aug32, aug32.gt_boxes[:, :3].astype(np.float64))
    H, W = sample32.images.shape[-2:]
    on_image = seen & (uv0[..., 0] >= 0) & (uv0[..., 0] < W) & (uv0[..., 1] >= 0) & (uv0[..., 1] < H)
    assert on_image.any()
    np.testing.assert_allclose(uv32[on_image], uv0[on_image], atol=1e-3, rtol=0)
    # Points keep their global position through the updated T_global_from_lidar.
    g0 = sample64.T_global_from_lidar @ np.append(centres, np.ones((len(centres), 1)), 1).T
    c1 = aug.gt_boxes[:, :3]
    g1 = aug.T_global_from_lidar @ np.append(c1, np.ones((len(c1), 1)), 1).T
    np.testing.assert_allclose(g1, g0, atol=1e-9, rtol=0)


@pytest.mark.parametrize("rot, scale, flip", GLOBAL_CASES)
def test_points_inside_each_box_are_kept(sample32, rot, scale, flip):
    aug = global_transform(sample32, rot, scale, flip)
    inside0, margin0 = in_boxes(sample32.points.astype(np.float64), sample32.gt_boxes.astype(np.float64))
    inside1, _ = in_boxes(aug.points.astype(np.float64), aug.gt_boxes.astype(np.float64))
    assert inside0.sum(axis=1).min() >= 5                   # DataConfig(min_points=5): a real test
    # Same points in the same box, except those within float32 rounding (1e-5 m) of a face.
    clear = np.abs(margin0) > 1e-5
    np.testing.assert_array_equal(inside1[clear], inside0[clear])
    np.testing.assert_array_equal(inside1.sum(axis=1), inside0.sum(axis=1))
    # Non-geometric columns (intensity, time lag) and the images are untouched.
    assert np.array_equal(aug.points[:, 3:], sample32.points[:, 3:])
    assert aug.images is sample32.images and np.array_equal(aug.img_aug, sample32.img_aug)


def test_box_transform_by_hand():
    """Rotate by pi/2, scale 2, flip: worked out on paper."""
    s = synthetic_sample()
    s.gt_boxes = np.array([[10.0, 2.0, -1.0, 4.0, 2.0, 1.5, 0.3, 1.0, 2.0]], dtype=np.float64)
    out = global_transform(s, math.pi / 2, 2.0, True)
    expected = [-4.0, -20.0, -2.0, 8.0, 4.0, 3.0, -(0.3 + math.pi / 2), -4.0, -2.0]
    np.testing.assert_allclose(out.gt_boxes[0], expected, atol=1e-12)
    # A rotation past pi wraps the yaw back into [-pi, pi].
    wrapped = global_transform(s, 3.0, 1.0, False).gt_boxes[0, 6].item()
    assert wrapped == pytest.approx(0.3 + 3.0 - 2 * math.pi, abs=1e-12)


def test_identity_and_flip_twice(sample32, sample64):
    for s in (sample32, sample64):
        assert_samples_equal(global_transform(s, 0.0, 1.0, False), s)                   # bit-exact
        assert_samples_equal(global_transform(global_transform(s, 0.0, 1.0, True), 0.0, 1.0, True), s)
    # Rotation by r then -r, scale k then 1/k: identity to float64 rounding.
    back = global_transform(global_transform(sample64, 0.7, 1.04, False), -0.7, 1 / 1.04, False)
    assert_samples_equal(back, sample64, atol=1e-12)


def test_global_matrix_is_flip_scale_rotation():
    A = global_matrix(0.4, 1.1, True)
    c, s = math.cos(0.4), math.sin(0.4)
    R = np.array([[c, -s, 0, 0], [s, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]])
    np.testing.assert_allclose(A, np.diag([1.0, -1.0, 1.0, 1.0]) @ np.diag([1.1, 1.1, 1.1, 1.0]) @ R, atol=1e-15)


def test_crop_to_range_drops_points_and_boxes():
    s = synthetic_sample()
    s.points = np.array([[0.0, 0, 0, 0.5, 0], [60.0, 0, 0, 0.5, 0]], np.float32)
    s.gt_boxes = np.array([[1.0, 1, 0, 4, 2, 1.5, 0, 0, 0], [-52.0, 0, 0, 4, 2, 1.5, 0, 0, 0]], np.float32)
    s.gt_labels = np.array([3, 7])
    out = crop_to_range(s, DataConfig().point_range)
    assert out.points.tolist() == [[0.0, 0, 0, 0.5, 0]] and out.gt_labels.tolist() == [3]
    assert np.array_equal(out.gt_boxes, s.gt_boxes[:1])


# ---------------------------------------------------------------- image transform

def synthetic_sample(n_cam: int = 2, H: int = 48, W: int = 80) -> Sample:
    """Black (mean-coloured) images, a simple K and identity extrinsics."""
    K = np.array([[60.0, 0, W / 2], [0, 60.0, H / 2], [0, 0, 1]], dtype=np.float64)
    return Sample(
        images=np.zeros((n_cam, 3, H, W), np.float32), intrinsics=np.repeat(K[None], n_cam, 0),
        T_lidar_from_cam=np.repeat(np.eye(4)[None], n_cam, 0), img_aug=np.repeat(np.eye(3)[None], n_cam, 0),
        points=np.zeros((0, 5), np.float32), gt_boxes=np.zeros((0, 9), np.float32),
        gt_labels=np.zeros(0, dtype=np.int64), T_global_from_lidar=np.eye(4), sample_token="synthetic",
    )


IMAGE_CASES = [  # (resize, (top, left), out (H, W), flip)
    (1.0, (0, 0), (48, 80), True),
    (1.3, (5, 7), (48, 80), True),
    (0.8, (-3, -4), (48, 80), False),
    (1.17, (2.5, 11.25), (40, 64), True),   # subpixel crop and a different output size
]


@pytest.mark.parametrize("resize, crop, out_size, flip", IMAGE_CASES)
def test_image_content_moves_as_img_aug_predicts(resize, crop, out_size, flip):
    s = synthetic_sample()
    H, W = s.images.shape[-2:]
    # Camera 0, channel 0: a single bright pixel. Camera 1, channel 1: a Gaussian blob at a
    # subpixel centre (edge convention), whose intensity centroid is a subpixel-exact marker.
    r0, c0 = 17, 29
    s.images[0, 0, r0, c0] = 10.0
    u0, v0 = 33.3, 21.7
    vv, uu = np.meshgrid(np.arange(H) + 0.5, np.arange(W) + 0.5, indexing="ij")
    s.images[1, 1] = np.exp(-((uu - u0) ** 2 + (vv - v0) ** 2) / (2 * 2.0**2))
    out = image_transform(s, resize, crop, out_size, flip)
    M = image_matrix(resize, crop, out_size, flip)
    assert out.images.shape == (2, 3, *out_size)
    np.testing.assert_allclose(out.img_aug, M[None] @ s.img_aug, atol=1e-15)
    assert np.array_equal(out.intrinsics, s.intrinsics)

    # The single pixel: its centre goes to M (c0 + .5, r0 + .5); the brightest output pixel covers it.
    u1, v1, _ = M @ [c0 + 0.5, r0 + 0.5, 1.0]
    img = out.images[0, 0]
    r1, c1 = np.unravel_index(np.argmax(img), img.shape)
    assert abs(c1 + 0.5 - u1) <= 1.0 and abs(r1 + 0.5 - v1) <= 1.0
    # The blob's centroid follows M to a small fraction of a pixel.
    blob = out.images[1, 1].astype(np.float64)
    Ho, Wo = out_size
    vv1, uu1 = np.meshgrid(np.arange(Ho) + 0.5, np.arange(Wo) + 0.5, indexing="ij")
    ub, vb, _ = M @ [u0, v0, 1.0]
    np.testing.assert_allclose([(uu1 * blob).sum() / blob.sum(), (vv1 * blob).sum() / blob.sum()], [ub, vb],
                               atol=0.05)
    # Nothing leaks between channels or cameras.
    assert np.abs(out.images[0, 1:]).max() == 0 and np.abs(out.images[1, [0, 2]]).max() == 0


def test_box_centre_pixels_move_by_M(sample64):
    H, W = sample64.images.shape[-2:]
    uv0, z0 = project(sample64, sample64.gt_boxes[:, :3])
    out = image_transform(sample64, 1.12, (9, 14), (H, W), True)
    uv1, z1 = project(out, out.gt_boxes[:, :3])
    M = image_matrix(1.12, (9, 14), (H, W), True)
    expected = uv0 @ M[:2, :2].T + M[:2, 2]
    seen = z0 > 0.1
    np.testing.assert_allclose(uv1[seen], expected[seen], atol=1e-9)
    assert np.array_equal(out.gt_boxes, sample64.gt_boxes) and np.array_equal(out.T_lidar_from_cam, sample64.T_lidar_from_cam)


def test_image_identity_and_flip_twice(sample32):
    H, W = sample32.images.shape[-2:]
    ident = image_transform(sample32, 1.0, (0, 0), (H, W), False)
    np.testing.assert_allclose(ident.images, sample32.images, atol=1e-6, rtol=0)
    assert np.array_equal(ident.img_aug, sample32.img_aug)
    twice = image_transform(image_transform(sample32, 1.0, (0, 0), (H, W), True), 1.0, (0, 0), (H, W), True)
    np.testing.assert_allclose(twice.images, sample32.images, atol=1e-6, rtol=0)
    np.testing.assert_allclose(twice.img_aug, sample32.img_aug, atol=0, rtol=0)
    # One flip mirrors each row exactly.
    once = image_transform(sample32, 1.0, (0, 0), (H, W), True)
    np.testing.assert_allclose(once.images, sample32.images[..., ::-1], atol=1e-6, rtol=0)


# ---------------------------------------------------------------- random composition

def test_random_augment_is_deterministic_per_seed(sample32):
    cfg = AugmentConfig()
    a = random_augment(sample32, np.random.default_rng(0), cfg)
    b = random_augment(sample32, np.random.default_rng(0), cfg)
    c = random_augment(sample32, np.random.default_rng(1), cfg)
    assert_samples_equal(a, b)
    assert not np.array_equal(a.T_lidar_from_cam, c.T_lidar_from_cam)
    assert not np.array_equal(a.img_aug, c.img_aug)
    assert a.images.shape == sample32.images.shape
    # Still consistent: box centres land where the original geometry, moved by img_aug, puts them.
    uv0, z0 = project(sample32, sample32.gt_boxes[:, :3].astype(np.float64))
    uv1, _ = project(a, a.gt_boxes[:, :3].astype(np.float64))
    M = a.img_aug.astype(np.float64) @ np.linalg.inv(sample32.img_aug.astype(np.float64))    # (N, 3, 3)
    expected = np.einsum("nij,nmj->nmi", M[:, :2, :2], uv0) + M[:, None, :2, 2]
    H, W = sample32.images.shape[-2:]
    on_image = (z0 > 0.1) & (uv0[..., 0] >= 0) & (uv0[..., 0] < W) & (uv0[..., 1] >= 0) & (uv0[..., 1] < H)
    np.testing.assert_allclose(uv1[on_image], expected[on_image], atol=1e-3)


def test_random_augment_ranges_and_disabled():
    s = synthetic_sample()
    s.gt_boxes = np.array([[10.0, 0.0, 0.0, 4.0, 2.0, 1.5, 0.0, 0.0, 0.0]], dtype=np.float64)
    off = AugmentConfig(rot_range=0.0, scale_range=(1.0, 1.0), flip_y_prob=0.0,
                        img_resize_range=(1.0, 1.0), img_flip_prob=0.0)
    assert_samples_equal(random_augment(s, np.random.default_rng(3), off), s, atol=1e-6)
    cfg = AugmentConfig()
    for seed in range(20):
        box = random_augment(s, np.random.default_rng(seed), cfg).gt_boxes[0]
        assert 0.95 * 4.0 - 1e-9 <= box[3] <= 1.05 * 4.0 + 1e-9
        assert abs(box[6]) <= math.pi / 8 + 1e-12                  # |yaw| = |rot| with or without flip
    for bad in (dict(scale_range=(1.1, 0.9)), dict(flip_y_prob=1.5), dict(img_resize_range=(0.0, 1.0))):
        with pytest.raises(ValueError):
            AugmentConfig(**bad)
