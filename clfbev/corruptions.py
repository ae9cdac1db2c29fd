"""Load-time sensor corruptions, for robustness evaluation on any nuScenes-format dataroot.

Applied by :class:`clfbev.data.NuScenesDetection` to what it loads; each one is a pure function
of the data and a generator seeded by (corruption, severity, sample token), so every evaluation
of a sample sees the same corruption. They follow the LiDAR-camera fusion robustness
benchmarks (Yu et al. 2022; Dong et al. 2023):

=================  =========  ==================================================================
name               severity   effect
=================  =========  ==================================================================
beam_missing       1-32       drop that many of the 32 rings (ring index: .pcd.bin column 5)
density            0-1        drop that fraction of the points, uniformly
fov                1-360      keep only the points within +-severity/2 deg of the ego's forward axis
lidar_missing      (none)     no points at all
camera_crash       1-6        that many cameras deliver nothing (the network input is all zeros)
frame_lost         0-1        each camera image is lost (zeros) with that probability
extrinsic_noise    0-10       T_lidar_from_cam perturbed: rotation noise sigma = severity deg per
                              axis, translation noise sigma = 0.02 * severity m per axis
=================  =========  ==================================================================

Zeros are the "sensor missing" input that BEVFusion's robustness study feeds (Liang et al.,
"BEVFusion: A Simple and Robust LiDAR-Camera Fusion Framework", NeurIPS 2022).
"""
from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

RANGES = {
    "beam_missing": (1, 32), "density": (0.0, 1.0), "fov": (1.0, 360.0), "lidar_missing": (0, 0),
    "camera_crash": (1, 6), "frame_lost": (0.0, 1.0), "extrinsic_noise": (0.0, 10.0),
}
INTEGER = {"beam_missing", "camera_crash"}
N_RINGS = 32


@dataclass(frozen=True)
class Corruption:
    """One corruption and its severity (see the module table)."""

    name: str
    severity: float = 0.0

    def __post_init__(self):
        if self.name not in RANGES:
            raise ValueError(f"unknown corruption {self.name!r} (known: {', '.join(RANGES)})")
        lo, hi = RANGES[self.name]
        if not lo <= self.severity <= hi or (self.name in INTEGER and self.severity != int(self.severity)):
            kind = "an integer" if self.name in INTEGER else "a number"
            raise ValueError(f"corruption {self.name}: severity must be {kind} in [{lo}, {hi}], got {self.severity:g}")

    def __str__(self) -> str:
        return self.name if self.name == "lidar_missing" else f"{self.name}:{self.severity:g}"

    def rng(self, token: str) -> np.random.Generator:
        """The generator of this corruption for one sample (stable across runs and machines)."""
        digest = hashlib.sha256(f"{self}|{token}".encode()).digest()
        return np.random.default_rng(int.from_bytes(digest[:8], "little"))


def parse(text: str) -> Corruption:
    """``NAME:SEVERITY`` (or ``lidar_missing``) -> :class:`Corruption`; ValueError naming it."""
    name, _, sev = text.partition(":")
    try:
        severity = float(sev) if sev else 0.0
    except ValueError:
        raise ValueError(f"--corrupt {text}: severity {sev!r} is not a number") from None
    if name in RANGES and name != "lidar_missing" and not sev:
        raise ValueError(f"--corrupt {text}: give a severity, e.g. {name}:{RANGES[name][1]}")
    try:
        return Corruption(name, severity)
    except ValueError as e:
        raise ValueError(f"--corrupt {text}: {e}") from None


# ---------------------------------------------------------------- lidar

def corrupt_points(points: np.ndarray, rings: np.ndarray, forward_lidar: np.ndarray, corruptions, token: str) -> np.ndarray:
    """Points (n, C) in the key-frame lidar frame with their ring indices (n,) -> the kept points.

    forward_lidar : (3,) the ego's forward axis in the lidar frame (for ``fov``)."""
    keep = np.ones(len(points), bool)
    for c in corruptions:
        rng = c.rng(token)
        if c.name == "lidar_missing":
            keep[:] = False
        elif c.name == "beam_missing":
            dropped = rng.choice(N_RINGS, size=int(c.severity), replace=False)
            keep &= ~np.isin(rings.astype(np.int64), dropped)
        elif c.name == "density":
            keep &= rng.random(len(points)) >= c.severity
        elif c.name == "fov":
            az = np.arctan2(points[:, 1], points[:, 0]) - math.atan2(forward_lidar[1], forward_lidar[0])
            az = (az + np.pi) % (2 * np.pi) - np.pi
            keep &= np.abs(az) <= np.deg2rad(c.severity) / 2
    return points[keep]


# ---------------------------------------------------------------- cameras

def corrupt_cameras(images: np.ndarray, T_lidar_from_cam: np.ndarray, corruptions, token: str):
    """images (N, 3, H, W) network input, T_lidar_from_cam (N, 4, 4) -> corrupted copies."""
    images, T = images.copy(), T_lidar_from_cam.copy()
    n = len(images)
    for c in corruptions:
        rng = c.rng(token)
        if c.name == "camera_crash":
            images[rng.choice(n, size=min(n, int(c.severity)), replace=False)] = 0.0
        elif c.name == "frame_lost":
            images[rng.random(n) < c.severity] = 0.0
        elif c.name == "extrinsic_noise":
            rot = Rotation.from_euler("xyz", rng.normal(0.0, c.severity, (n, 3)), degrees=True).as_matrix()
            shift = rng.normal(0.0, 0.02 * c.severity, (n, 3))
            noise = np.tile(np.eye(4), (n, 1, 1))
            noise[:, :3, :3], noise[:, :3, 3] = rot, shift
            T = T @ noise          # the camera frame is perturbed: T_lidar_from_cam' = T_lidar_from_cam @ T_cam_from_cam'
    return images, T


def lidar_corruptions(corruptions) -> tuple[Corruption, ...]:
    return tuple(c for c in corruptions if c.name in ("beam_missing", "density", "fov", "lidar_missing"))


def camera_corruptions(corruptions) -> tuple[Corruption, ...]:
    return tuple(c for c in corruptions if c.name in ("camera_crash", "frame_lost", "extrinsic_noise"))
