"""Linear camera motion blur along each camera's horizon: the ``motion_blur`` load-time corruption.

While a camera's shutter is open the ego moves, and the image integrates the scene along each
point's image-plane path. For a ground vehicle that path has one exact direction for a whole set of
points: a static point in the horizontal plane through the camera centre stays in that plane under
any planar ego motion (driving in the ground plane and turning about the vertical), so its image
moves along the image of that plane, the camera's horizon line. That is the direction taken here.

The length is a severity in pixels of the original image rather than one derived from the ego's
speed: a translating camera's flow is f V / Z, so one spatially invariant kernel is only physical
for one depth, and a reference depth would be a severity in disguise. A length in pixels is
comparable with the robustness benchmarks' levels (MultiCorrupt, Beemelmanns et al., IEEE IV
2024; RoboBEV / nuScenes-C, Xie et al. 2023), which blur with a severity-scaled kernel too.
MultiCorrupt's levels 1 / 2 / 3 are a half-Gaussian kernel of sigma 6 / 10 / 13 px on nuScenes'
1600 x 900 images; a uniform line of the same spread (L / sqrt(12) = sigma sqrt(1 - 2 / pi)) is
12.5 / 20.9 / 27.1 px long.

The kernel is a centred line segment: each pixel weighs the share of the segment's length inside
it (pixel c covers [c - 1/2, c + 1/2) about the kernel's centre), so it sums to 1 and is point
symmetric (correlation and convolution agree). It is applied with replicated borders, which keeps
the sum 1 at the image border too: the blur then commutes with the per-channel normalisation of the
network input, so blurring the normalised image is blurring the image.
"""
from __future__ import annotations

import math

import cv2
import numpy as np

SUBSAMPLES = 32          # pieces per pixel of segment length when the segment is rasterised


def line_kernel(vector) -> np.ndarray:
    """(k, k) float32 kernel of the centred segment ``vector = (dx, dy)`` pixels (x right, y down).

    Pixel (row i, column j) weighs the share of the segment inside it, measured on
    ``SUBSAMPLES`` pieces per pixel of length; k = 2 ceil(max(|dx|, |dy|) / 2) + 1.
    """
    v = np.asarray(vector, dtype=np.float64)
    r = int(math.ceil(np.abs(v).max() / 2))
    n = max(1, math.ceil(float(np.hypot(*v)))) * SUBSAMPLES
    t = (np.arange(n) + 0.5) / n - 0.5                         # the pieces' midpoints, symmetric about 0
    cols, rows = np.rint(t[:, None] * v[None, :]).astype(np.int64).T + r
    kernel = np.zeros((2 * r + 1, 2 * r + 1))
    np.add.at(kernel, (rows, cols), 1.0 / n)
    return kernel.astype(np.float32)


def horizon_directions(T_lidar_from_cam: np.ndarray, up_lidar: np.ndarray, intrinsics: np.ndarray) -> np.ndarray:
    """(N, 2) unit directions (du, dv) of each camera's horizon line, original-image pixels.

    T_lidar_from_cam : (N, 4, 4) camera -> lidar.  up_lidar : (3,) the ego's up axis, lidar frame.
    intrinsics : (N, 3, 3) K. The horizon is the image of the directions d with d . up = 0: the
    line l = K^-T up_cam (points x on it have l . x = 0), whose direction is (l_1, -l_0).
    A camera looking straight up or down has no horizon; none of a vehicle's does.
    """
    up_cam = np.einsum("nji,j->ni", T_lidar_from_cam[:, :3, :3], up_lidar)      # R_cam_from_lidar @ up
    line = np.einsum("nji,nj->ni", np.linalg.inv(intrinsics), up_cam)           # K^-T @ up_cam
    d = np.stack([line[:, 1], -line[:, 0]], axis=1)
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def blur_vectors(length_px: float, T_lidar_from_cam: np.ndarray, up_lidar: np.ndarray, intrinsics: np.ndarray,
                 img_aug: np.ndarray) -> np.ndarray:
    """(N, 2) the blur segment of each camera in the network image's pixels: ``length_px`` pixels
    of the original image along its horizon, mapped by ``img_aug`` (N, 3, 3)."""
    d = horizon_directions(T_lidar_from_cam, up_lidar, intrinsics)
    return length_px * np.einsum("nij,nj->ni", img_aug[:, :2, :2], d)


def blur_images(images: np.ndarray, vectors: np.ndarray) -> np.ndarray:
    """images (N, C, H, W) float32 blurred, image i along the segment ``vectors[i]`` (px)."""
    out = np.empty_like(images)
    for i, (image, v) in enumerate(zip(images, vectors)):      # one filter per camera, each vectorised
        hwc = np.ascontiguousarray(image.transpose(1, 2, 0))
        blurred = cv2.filter2D(hwc, -1, line_kernel(v), borderType=cv2.BORDER_REPLICATE)
        out[i] = blurred.reshape(hwc.shape).transpose(2, 0, 1)
    return out
