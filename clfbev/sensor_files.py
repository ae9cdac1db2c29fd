"""The sensor files of a nuScenes-format dataroot: ``.pcd.bin`` lidar sweeps and camera images,
and the resize and crop that makes a camera image the network's. Every unusable file raises a
one-line :class:`clfbev.errors.DataError` naming it.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from clfbev.errors import DataError

# ImageNet statistics (RGB, on [0, 1]): what a ResNet backbone is usually initialised for.
IMAGE_MEAN = np.array([0.485, 0.456, 0.406], dtype=np.float32)
IMAGE_STD = np.array([0.229, 0.224, 0.225], dtype=np.float32)
POINT_BYTES = 5 * 4       # a .pcd.bin point: x, y, z, intensity, ring as float32
JPEG_START, JPEG_END = b"\xff\xd8", b"\xff\xd9"   # the start- and end-of-image markers of a JPEG file


def load_points(path: Path) -> np.ndarray:
    """(n, 5) float32 x, y, z, intensity, ring of a nuScenes ``.pcd.bin`` (sensor frame)."""
    try:
        raw = path.read_bytes()
    except OSError as e:
        raise DataError(f"cannot read lidar file {path}: {e.strerror}") from None
    if len(raw) % POINT_BYTES:
        raise DataError(f"corrupt lidar file {path}: {len(raw)} bytes is not a multiple of {POINT_BYTES}")
    points = np.frombuffer(raw, dtype=np.float32).reshape(-1, 5)
    if not np.isfinite(points).all():
        raise DataError(f"corrupt lidar file {path}: it holds non-finite values")
    return points


def load_image(path: Path) -> np.ndarray:
    """(H, W, 3) uint8 RGB of an image file; a JPEG must end with its end-of-image marker (the
    decoder would fill a truncated file's missing rows with grey)."""
    try:
        raw = path.read_bytes()
    except OSError as e:
        raise DataError(f"cannot read image file {path}: {e.strerror}") from None
    if raw[:2] == JPEG_START and not raw.rstrip(b"\0").endswith(JPEG_END):
        raise DataError(f"truncated image file {path}: the JPEG has no end-of-image marker")
    img = cv2.imdecode(np.frombuffer(raw, np.uint8), cv2.IMREAD_COLOR)   # None for an undecodable file
    if img is None:
        raise DataError(f"unreadable image file {path}")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def resize_and_crop(rgb: np.ndarray, size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Resize (h0, w0, 3) uint8 to the width of ``size = (H, W)`` keeping the aspect ratio, then
    crop the top rows to height H (or pad the top with black when the image is too short).

    Returns the (H, W, 3) image and the (3, 3) float64 map from original to new pixels
    (pixel-edge convention): ``u' = (W / w0) u``, ``v' = (h1 / h0) v - top``, with h1 the
    resized height and ``top = h1 - H``. The bottom of the image (road, objects) is kept.
    """
    H, W = size
    h0, w0 = rgb.shape[:2]
    h1 = max(1, int(round(h0 * W / w0)))
    # INTER_AREA averages when shrinking (no aliasing); cv2 maps pixel centres, which is the
    # same map u' = s u in the pixel-edge convention.
    interp = cv2.INTER_AREA if (h1 < h0 and W < w0) else cv2.INTER_LINEAR
    resized = cv2.resize(rgb, (W, h1), interpolation=interp)
    top = h1 - H
    out = resized[top:] if top >= 0 else np.pad(resized, ((-top, 0), (0, 0), (0, 0)))
    A = np.array([[W / w0, 0.0, 0.0], [0.0, h1 / h0, -top], [0.0, 0.0, 1.0]])
    return np.ascontiguousarray(out), A
