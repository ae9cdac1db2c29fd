"""Training-time data augmentation on a :class:`clfbev.data.Sample`, geometry kept consistent.

Two independent families, as in BEVDet / BEVFusion:

- Global BEV augmentation (:func:`global_transform`): one similarity ``A`` (rotation about z,
  isotropic scale, optional flip y -> -y) re-defines the lidar frame, ``lidar' = A @ lidar``.
  Everything expressed in the lidar frame moves with it: points, GT boxes (centre, size, yaw,
  velocity) and the camera extrinsics, ``T_lidar'_from_cam = A @ T_lidar_from_cam``. The images
  and ``img_aug`` are untouched, so each camera pixel still sees the same (moved) 3-D point and
  lift-splat stays aligned with the lidar BEV. This is BEVDet's BEV data augmentation (BDA,
  Huang et al. 2021): :func:`clfbev.camera_encoder.lift_geometry` places every frustum point at
  ``T_lidar'_from_cam p_cam = A (T_lidar_from_cam p_cam)``, the 4x4 ``A`` applied to the lifted
  geometry before the splat, with the boxes and the points moved by the same ``A``. It needs no
  pixel, so it stays exact with cached image features (:mod:`clfbev.feature_cache`).
- Image augmentation (:func:`image_transform`): resize, crop and horizontal flip of every camera
  image, composed into ``img_aug`` (original -> network pixels); ``intrinsics`` stays the ORIGINAL
  K, as :mod:`clfbev.camera_encoder` composes ``img_aug @ intrinsics`` itself. 3-D data are
  untouched. Off (``AugmentConfig.image``) with cached image features, which it would change.
  A horizontal flip of the feature map (with ``img_aug`` flipped to match) would be exact there
  too, but it augments nothing: the depth net and the semantic head are 1x1 convolutions, so the
  flipped map lifts the very same frustum points with the very same features.

Pixel coordinates use the pixel-edge convention of :mod:`clfbev.data`: pixel c covers [c, c + 1),
so a resize by r is u' = r u exactly and a horizontal flip of a W-wide image is u' = W - u.

Every function is pure (returns a new Sample; the input is not modified), works on the Sample's
numpy arrays, computes in float64 and returns each array in its input dtype, so a float64 Sample
round-trips to ~1e-12. Randomness only enters through :func:`random_augment`'s explicit ``rng``.

GT-paste (copy-paste of database objects) is :mod:`clfbev.gt_paste`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import cv2
import numpy as np

from clfbev.data import Sample


def _like(a: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """``a`` (computed in float64) in the dtype of ``ref``, C-contiguous."""
    return np.ascontiguousarray(a, dtype=ref.dtype)


def _wrap_angle(a: np.ndarray) -> np.ndarray:
    """Angles into [-pi, pi]; values already there are returned bit-exactly (identity stays exact)."""
    out = a.copy()
    bad = (out < -math.pi) | (out > math.pi)
    out[bad] = np.mod(out[bad] + math.pi, 2.0 * math.pi) - math.pi
    return out


# ---------------------------------------------------------------- global BEV augmentation

def global_matrix(rot_rad: float, scale: float, flip_y: bool) -> np.ndarray:
    """(4, 4) float64 ``T_lidar'_from_lidar = F @ S @ R_z(rot_rad)``: rotate, scale, then flip.

    F = diag(1, -1, 1) when ``flip_y`` (a reflection across the x axis), else identity.
    """
    c, s = math.cos(rot_rad), math.sin(rot_rad)
    A = np.eye(4)
    A[:2, :2] = scale * np.array([[c, -s], [s, c]])
    A[2, 2] = scale
    if flip_y:
        A[1, :3] = -A[1, :3]
    return A


def global_transform(sample: Sample, rot_rad: float, scale: float, flip_y: bool) -> Sample:
    """Rotate (about lidar z), scale and optionally flip (y -> -y) the whole scene.

    The new lidar frame is ``lidar' = A @ lidar`` with ``A = global_matrix(rot_rad, scale, flip_y)``.

    - points (n, C): x, y, z -> A (x, y, z); the other columns (intensity, time lag) are kept.
    - gt_boxes (M, 9) ``x, y, z, l, w, h, yaw, vx, vy``: centre -> A centre; l, w, h -> scale *;
      yaw -> yaw + rot_rad, then -yaw if flipped (wrapped to [-pi, pi]); velocity -> the xy
      block of A times (vx, vy): a scaled world moves proportionally faster in the same time.
    - T_lidar_from_cam (N, 4, 4) -> A @ T: camera pixels keep projecting onto the same (moved)
      points. With scale != 1 (or a flip) it is a similarity, not a rigid transform; the camera
      encoder only applies it to points, so that is what it needs.
    - T_global_from_lidar (4, 4) -> T_global_from_lidar @ A^-1, so points still map to the same
      global positions. Not rigid either when scaled/flipped: augmented samples are for training,
      not for sending predictions back with :func:`clfbev.data.box_lidar_to_global`.
    - images, intrinsics, img_aug: unchanged.
    """
    A = global_matrix(rot_rad, scale, flip_y)
    A3 = A[:3, :3]

    pts = sample.points.astype(np.float64)
    pts[:, :3] = pts[:, :3] @ A3.T

    boxes = sample.gt_boxes.astype(np.float64)
    boxes[:, 0:3] = boxes[:, 0:3] @ A3.T
    boxes[:, 3:6] = boxes[:, 3:6] * scale
    yaw = boxes[:, 6] + rot_rad
    boxes[:, 6] = _wrap_angle(-yaw if flip_y else yaw)
    if boxes.shape[1] >= 9:
        boxes[:, 7:9] = boxes[:, 7:9] @ A3[:2, :2].T

    T_lidar_from_cam = A[None] @ sample.T_lidar_from_cam.astype(np.float64)
    T_global_from_lidar = sample.T_global_from_lidar.astype(np.float64) @ np.linalg.inv(A)
    return replace(
        sample,
        points=_like(pts, sample.points),
        gt_boxes=_like(boxes, sample.gt_boxes),
        T_lidar_from_cam=_like(T_lidar_from_cam, sample.T_lidar_from_cam),
        T_global_from_lidar=_like(T_global_from_lidar, sample.T_global_from_lidar),
    )


def crop_to_range(sample: Sample, point_range: tuple[float, ...]) -> Sample:
    """Drop points and boxes (by centre) outside ``point_range`` (min <= p < max), as the loader
    does; a rotation or scale can move them out of the grid.
    """
    lo, hi = np.asarray(point_range[:3]), np.asarray(point_range[3:])
    keep_p = ((sample.points[:, :3] >= lo) & (sample.points[:, :3] < hi)).all(axis=1)
    keep_b = ((sample.gt_boxes[:, :3] >= lo) & (sample.gt_boxes[:, :3] < hi)).all(axis=1)
    pasted = None if sample.pasted is None else sample.pasted[keep_p]
    return replace(sample, points=sample.points[keep_p], gt_boxes=sample.gt_boxes[keep_b],
                   gt_labels=sample.gt_labels[keep_b], pasted=pasted,
                   gt_still=None if sample.gt_still is None else sample.gt_still[keep_b])


def shuffle_points(sample: Sample, rng: np.random.Generator) -> Sample:
    """The points (and their ``pasted`` flags) in a random order. The loader lists the key sweep
    first; the voxelizer's ``max_voxels`` cap keeps voxels by their first point's input order,
    so without a shuffle the oldest sweep would always be the first to lose voxels."""
    perm = rng.permutation(len(sample.points))
    pasted = None if sample.pasted is None else sample.pasted[perm]
    return replace(sample, points=sample.points[perm], pasted=pasted)


# ---------------------------------------------------------------- image augmentation

def image_matrix(resize: float, crop: tuple[float, float], out_size: tuple[int, int], flip: bool) -> np.ndarray:
    """(3, 3) float64 M: current network pixels -> new pixels (pixel-edge convention).

    Resize by ``resize``, then crop a window of ``out_size = (H, W)`` whose top-left corner is
    ``crop = (top, left)`` in resized pixels (negative or past the edge pads), then flip
    horizontally if ``flip``: u' = W - (r u - left), v' = r v - top.
    """
    top, left = crop
    H, W = out_size
    M = np.array([[resize, 0.0, -left], [0.0, resize, -top], [0.0, 0.0, 1.0]])
    if flip:
        M = np.array([[-1.0, 0.0, W], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]) @ M
    return M


def warp_images(images: np.ndarray, M: np.ndarray, out_size: tuple[int, int]) -> np.ndarray:
    """Warp (N, C, h, w) float32 images by the edge-convention affine M into (N, C, H, W).

    Pixels that fall outside the source are 0, i.e. the mean colour of normalised images.
    """
    H, W = out_size
    # cv2 indexes pixel centres: centre of pixel c is c + 0.5 in the edge convention, so the map
    # in cv2's coordinates is T(-0.5) M T(+0.5).
    half = np.array([[1.0, 0.0, 0.5], [0.0, 1.0, 0.5], [0.0, 0.0, 1.0]])
    M_cv = (np.linalg.inv(half) @ M @ half)[:2]
    n, c, h, w = images.shape
    planes = images.reshape(n * c, h, w)
    # One 2-D warp per camera channel (a loop over planes, not pixels): cv2 takes at most 4
    # channels per call, and a plane at a time keeps any channel count working.
    out = np.stack([
        cv2.warpAffine(np.ascontiguousarray(p, dtype=np.float32), M_cv, (W, H),
                       flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        for p in planes
    ]) if n * c else np.zeros((0, H, W), np.float32)
    return out.reshape(n, c, H, W)


def image_transform(
    sample: Sample, resize: float, crop: tuple[float, float], out_size: tuple[int, int], flip: bool,
) -> Sample:
    """Resize, crop and (optionally) flip every camera image; ``img_aug <- M @ img_aug``.

    sample.images : (N, 3, h, w) -> (N, 3, H, W) with ``out_size = (H, W)``. M is
    :func:`image_matrix`; the images are warped by exactly that map (bilinear), so a pixel's
    content and its projected geometry move together. ``intrinsics`` stays the original K.
    """
    M = image_matrix(resize, crop, out_size, flip)
    images = warp_images(sample.images, M, out_size)
    img_aug = M[None] @ sample.img_aug.astype(np.float64)
    return replace(sample, images=_like(images, sample.images), img_aug=_like(img_aug, sample.img_aug))


# ---------------------------------------------------------------- random composition

@dataclass(frozen=True)
class AugmentConfig:
    """Ranges of :func:`random_augment`. Setting a range to a point / a probability to 0 disables it.

    rot_range : yaw rotation drawn uniformly from [-rot_range, rot_range] (rad).
    scale_range : isotropic scale drawn uniformly from [lo, hi].
    flip_y_prob : probability of the BEV flip y -> -y.
    img_resize_range : image resize factor drawn uniformly from [lo, hi] (relative to the
        current network image).
    img_crop_random : crop offset uniform over the valid range (else centred). When the
        resized image is smaller than the output, the crop is centred and the border padded.
    img_flip_prob : probability of the horizontal image flip.
    image : apply the image augmentation at all (its values are drawn either way); False with
        cached image features (:mod:`clfbev.feature_cache`), leaving the BEV augmentation alone.
    """

    rot_range: float = math.pi / 8
    scale_range: tuple[float, float] = (0.95, 1.05)
    flip_y_prob: float = 0.5
    img_resize_range: tuple[float, float] = (0.9, 1.1)
    img_crop_random: bool = True
    img_flip_prob: float = 0.5
    image: bool = True

    def __post_init__(self):
        if self.rot_range < 0 or not (0 < self.scale_range[0] <= self.scale_range[1]):
            raise ValueError(f"need rot_range >= 0 and 0 < scale lo <= hi, got {self.rot_range}, {self.scale_range}")
        if not (0 < self.img_resize_range[0] <= self.img_resize_range[1]):
            raise ValueError(f"need 0 < img_resize_range lo <= hi, got {self.img_resize_range}")
        for name in ("flip_y_prob", "img_flip_prob"):
            p = getattr(self, name)
            if not 0.0 <= p <= 1.0:
                raise ValueError(f"{name} must be in [0, 1], got {p}")


def _crop_offset(rng: np.random.Generator, excess: int, randomise: bool) -> int:
    """Top-left offset for a crop whose source exceeds the output by ``excess`` pixels."""
    u = rng.random()                          # always drawn: a fixed number of draws per call
    if excess <= 0 or not randomise:
        return int(round(excess / 2))         # centred; negative pads both sides equally
    return min(int(u * (excess + 1)), excess)


def random_augment(sample: Sample, rng: np.random.Generator, cfg: AugmentConfig = AugmentConfig()) -> Sample:
    """Draw a global and an image augmentation from ``cfg`` with ``rng`` and apply both (the
    image one only with ``cfg.image``).

    Deterministic given the rng state. The draws are always made in the same order (rot, scale,
    flip_y, resize, crop top, crop left, image flip, point order), whatever is enabled, so one
    setting does not shift the random stream of the others. One image augmentation is shared by
    all cameras. The output image size equals the input's. The points come out shuffled
    (:func:`shuffle_points`).
    """
    rot = float(rng.uniform(-cfg.rot_range, cfg.rot_range))
    scale = float(rng.uniform(*cfg.scale_range))
    flip_y = bool(rng.random() < cfg.flip_y_prob)
    resize = float(rng.uniform(*cfg.img_resize_range))
    H, W = sample.images.shape[-2:]
    top = _crop_offset(rng, int(math.floor(H * resize)) - H, cfg.img_crop_random)
    left = _crop_offset(rng, int(math.floor(W * resize)) - W, cfg.img_crop_random)
    flip_img = bool(rng.random() < cfg.img_flip_prob)

    out = global_transform(sample, rot, scale, flip_y)
    if cfg.image:
        out = image_transform(out, resize, (top, left), (H, W), flip_img)
    return shuffle_points(out, rng)
