"""The nuScenes sensor rig: six cameras with their own intrinsics, and LIDAR_TOP.

Calibration is the v1.0-mini one (ego frame: x forward, y left, z up; origin at the rear axle).
Camera frames are x right, y down, z forward. Intrinsics are for 1600x900 and scale with the
resolution.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import geometry

NATIVE_RESOLUTION = (1600, 900)

# channel: (translation, rotation wxyz, fx = fy, cx, cy)
_CAMERAS = {
    "CAM_FRONT": ((1.7008, 0.0159, 1.5110), (0.49980, -0.50303, 0.49978, -0.49737), 1266.42, 816.27, 491.51),
    "CAM_FRONT_RIGHT": ((1.5508, -0.4934, 1.4957), (0.20603, -0.20269, 0.68245, -0.67136), 1260.85, 807.97, 495.33),
    "CAM_BACK_RIGHT": ((1.0149, -0.4806, 1.5624), (0.12281, -0.13240, -0.70043, 0.69050), 1259.51, 807.25, 501.20),
    "CAM_BACK": ((0.0283, 0.0035, 1.5791), (0.50379, -0.49740, -0.49419, 0.50455), 809.22, 829.22, 481.78),
    "CAM_BACK_LEFT": ((1.0357, 0.4848, 1.5910), (0.69242, -0.70316, -0.11648, 0.11203), 1256.74, 792.11, 492.78),
    "CAM_FRONT_LEFT": ((1.5239, 0.4946, 1.5093), (0.67573, -0.67363, 0.21214, -0.21123), 1272.60, 826.62, 479.75),
}
CAMERAS = tuple(_CAMERAS)
LIDAR = "LIDAR_TOP"
LIDAR_TRANSLATION = (0.943713, 0.0, 1.84023)
LIDAR_ROTATION = (0.70780, -0.00649, 0.01065, -0.70631)


@dataclass(frozen=True)
class Camera:
    """One camera: ``K`` (3, 3) for ``resolution`` and ``T_ego_from_cam`` (4, 4)."""
    channel: str
    translation: tuple
    rotation: tuple          # wxyz, normalised
    K: np.ndarray
    resolution: tuple[int, int]

    @property
    def T_ego_from_cam(self) -> np.ndarray:
        return geometry.transform_from_quat(self.translation, self.rotation)

    @property
    def center_azimuth(self) -> float:
        """Azimuth (rad, ego frame, from +x towards +y) of the optical axis."""
        axis = self.T_ego_from_cam[:3, 2]
        return float(np.arctan2(axis[1], axis[0]))


def _normalised(q) -> tuple:
    q = np.asarray(q, dtype=np.float64)
    return tuple(float(v) for v in q / np.linalg.norm(q))


def cameras(resolution: tuple[int, int] = NATIVE_RESOLUTION) -> list[Camera]:
    """The six cameras, with intrinsics scaled from 1600x900 to ``resolution`` (W, H)."""
    sx, sy = resolution[0] / NATIVE_RESOLUTION[0], resolution[1] / NATIVE_RESOLUTION[1]
    out = []
    for ch, (t, q, f, cx, cy) in _CAMERAS.items():
        K = geometry.scale_intrinsics(np.array([[f, 0, cx], [0, f, cy], [0, 0, 1.0]]), sx, sy)
        out.append(Camera(ch, tuple(t), _normalised(q), K, tuple(resolution)))
    return out


def T_ego_from_lidar() -> np.ndarray:
    """LIDAR_TOP extrinsics: sensor x points to ego -y and sensor y to ego +x."""
    return geometry.transform_from_quat(LIDAR_TRANSLATION, _normalised(LIDAR_ROTATION))


def lidar_rotation() -> tuple:
    return _normalised(LIDAR_ROTATION)
