"""Load-time sensor corruptions, for robustness evaluation on any nuScenes-format dataroot.

Applied by :class:`clfbev.data.NuScenesDetection` to what it loads; each one is a pure function
of the data and, where it draws, a generator seeded by (corruption, severity, sample token), so
every evaluation of a sample sees the same corruption. They follow the LiDAR-camera fusion
robustness benchmarks (Yu et al. 2022; Dong et al. 2023; MultiCorrupt, Beemelmanns et al.,
IEEE IV 2024). ``--corrupt NAME:SEVERITY``, or ``NAME:SENSOR:SEVERITY`` for the two that act on
one sensor (SENSOR: ``LIDAR_TOP`` or a camera channel, e.g. ``CAM_FRONT``):

================  ========  ===================================================================
name              severity  effect
================  ========  ===================================================================
beam_missing      1-32      drop that many of the 32 rings (ring index: .pcd.bin column 5)
density           0-1       drop exactly round(n * severity) of the n loaded points (every sweep,
                            within the point range), drawn uniformly without replacement; the
                            kept ones unchanged and in order (MultiCorrupt's "points reducing"
                            levels 1-3: 0.2, 0.4, 0.6)
fov               1-360     keep only the points within +-severity/2 deg of the ego's forward axis
lidar_missing     (none)    no points at all
camera_crash      1-6       that many cameras deliver nothing: their images are zeros and the
                            sample marks them missing (the model lifts nothing from them)
frame_lost        0-1       each camera image is lost with that probability (as camera_crash)
extrinsic_noise   0-10      T_lidar_from_cam perturbed: rotation noise sigma = severity deg per
                            axis, translation noise sigma = 0.02 * severity m per axis
motion_blur       1-100     each camera image blurred by a line of that many pixels of the
                            original image along the camera's horizon (:mod:`clfbev.motion_blur`;
                            12.5 / 21 / 27 px match MultiCorrupt's levels 1-3)
misalign:SENSOR   0-10      that sensor's calibration is off by an exact error: its believed
                            T_ego_from_sensor turned by s deg about each of the ego's x, y, z
                            axes (R_err = Rz(s) Ry(s) Rx(s), about the mount point) and shifted by
                            0.02 s m along each; the loader uses it wherever it uses that sensor's
                            calibration (MultiCorrupt's spatial misalignment levels 1-3: s = 1, 2, 3)
late:SENSOR       1-20      that sensor's data stream is that many frames behind its records: the
                            file of the record k frames earlier on its channel is read in place of
                            each record's own, with the current record's ego pose, calibration and
                            timestamp (MultiCorrupt's temporal misalignment; the oldest frame of
                            the scene stands in where there is no older one)
================  ========  ===================================================================

A missing camera's images are zeros, the "sensor missing" input of BEVFusion's robustness study
(Liang et al., "BEVFusion: A Simple and Robust LiDAR-Camera Fusion Framework", NeurIPS 2022),
and the sample marks it missing (``Sample.camera_missing``), as a vehicle's software knows which
camera delivered no frame: the model lifts nothing from it, and with every camera missing its
camera BEV is exactly the all-zero one that modality dropout trains it on. Without the mark a
frozen encoder would turn the zeros into features no training sample ever had.

``misalign`` and ``late`` act on every sample (a calibration error or a stale buffer persists),
where MultiCorrupt applies them to a random 20 / 40 / 60 % of the samples. ``late`` delivers old
data as current, as MultiCorrupt does and as a stream that has fallen behind its timestamps does:
loading the old frame with its own pose would undo the ego-motion part of the error.
"""
from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from clfbev import motion_blur

RANGES = {
    "beam_missing": (1, 32), "density": (0.0, 1.0), "fov": (1.0, 360.0), "lidar_missing": (0, 0),
    "camera_crash": (1, 6), "frame_lost": (0.0, 1.0), "extrinsic_noise": (0.0, 10.0),
    "motion_blur": (1.0, 100.0), "misalign": (0.0, 10.0), "late": (1, 20),
}
INTEGER = {"beam_missing", "camera_crash", "late"}
PER_SENSOR = {"misalign", "late"}                 # NAME:SENSOR:SEVERITY
LIDAR = ("beam_missing", "density", "fov", "lidar_missing")
CAMERA = ("camera_crash", "frame_lost", "extrinsic_noise", "motion_blur")
# The channels a per-sensor corruption may name: clfbev.data's LIDAR and CAMERAS (a test keeps them equal).
SENSORS = ("LIDAR_TOP", "CAM_FRONT_LEFT", "CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_BACK_LEFT", "CAM_BACK", "CAM_BACK_RIGHT")
N_RINGS = 32
MISALIGN_SHIFT_M = 0.02       # misalign's shift along each ego axis per unit of severity (m)


@dataclass(frozen=True)
class Corruption:
    """One corruption, its severity and, for ``misalign`` and ``late``, its sensor (see the module table)."""

    name: str
    severity: float = 0.0
    sensor: str = ""

    def __post_init__(self):
        if self.name not in RANGES:
            raise ValueError(f"unknown corruption {self.name!r} (known: {', '.join(RANGES)})")
        if self.name in PER_SENSOR and self.sensor not in SENSORS:
            raise ValueError(f"{self.name} needs a sensor, one of {', '.join(SENSORS)}; got {self.sensor!r}")
        if self.name not in PER_SENSOR and self.sensor:
            raise ValueError(f"{self.name} takes no sensor, got {self.sensor!r}")
        lo, hi = RANGES[self.name]
        if not lo <= self.severity <= hi or (self.name in INTEGER and self.severity != int(self.severity)):
            kind = "an integer" if self.name in INTEGER else "a number"
            raise ValueError(f"{self.name}'s severity must be {kind} in [{lo}, {hi}], got {self.severity:g}")

    def __str__(self) -> str:
        if self.name == "lidar_missing":
            return self.name
        return f"{self.name}:{self.sensor}:{self.severity:g}" if self.sensor else f"{self.name}:{self.severity:g}"

    def rng(self, token: str) -> np.random.Generator:
        """The generator of this corruption for one sample (stable across runs and machines)."""
        digest = hashlib.sha256(f"{self}|{token}".encode()).digest()
        return np.random.default_rng(int.from_bytes(digest[:8], "little"))


def syntax(name: str) -> str:
    """How ``--corrupt`` spells corruption ``name``, with its allowed values."""
    if name == "lidar_missing":
        return f"{name} (no severity)"
    lo, hi = RANGES[name]
    if name in PER_SENSOR:
        return f"{name}:SENSOR:SEVERITY (SENSOR one of {', '.join(SENSORS)}; SEVERITY in [{lo}, {hi}])"
    return f"{name}:SEVERITY (SEVERITY in [{lo}, {hi}])"


def parse(text: str) -> Corruption:
    """``NAME:SEVERITY``, ``NAME:SENSOR:SEVERITY`` or ``lidar_missing`` -> :class:`Corruption`;
    a one-line ValueError naming ``--corrupt`` and the allowed values otherwise."""
    parts = text.split(":")
    name = parts[0]
    if name not in RANGES:
        raise ValueError(f"--corrupt {text}: unknown corruption {name!r} (known: {', '.join(RANGES)})")
    lo, hi = RANGES[name]
    n_parts = 1 if name == "lidar_missing" else 3 if name in PER_SENSOR else 2
    if len(parts) != n_parts:
        raise ValueError(f"--corrupt {text}: write {syntax(name)}")
    try:
        severity = float(parts[-1]) if n_parts > 1 else 0.0
    except ValueError:
        raise ValueError(f"--corrupt {text}: severity {parts[-1]!r} is not a number (allowed: [{lo}, {hi}])") from None
    try:
        return Corruption(name, severity, parts[1] if n_parts == 3 else "")
    except ValueError as e:
        raise ValueError(f"--corrupt {text}: {e}") from None


def lidar_corruptions(corruptions) -> tuple[Corruption, ...]:
    return tuple(c for c in corruptions if c.name in LIDAR)


def camera_corruptions(corruptions) -> tuple[Corruption, ...]:
    return tuple(c for c in corruptions if c.name in CAMERA)


# ---------------------------------------------------------------- lidar

def corrupt_points(points: np.ndarray, rings: np.ndarray, forward_lidar: np.ndarray, corruptions, token: str) -> np.ndarray:
    """Points (n, C) in the key-frame lidar frame with their ring indices (n,) -> the kept points,
    in their order.

    forward_lidar : (3,) the ego's forward axis in the lidar frame (for ``fov``)."""
    keep = np.ones(len(points), bool)
    for c in corruptions:
        rng = c.rng(token)
        if c.name == "lidar_missing":
            keep[:] = False
        elif c.name == "beam_missing":
            dropped = rng.choice(N_RINGS, size=int(c.severity), replace=False)
            keep &= ~np.isin(rings.astype(np.int64), dropped)
        elif c.name == "density":          # of the points still kept, exactly round(n f) dropped
            kept = np.flatnonzero(keep)
            keep[rng.choice(kept, size=round(len(kept) * c.severity), replace=False)] = False
        elif c.name == "fov":
            az = np.arctan2(points[:, 1], points[:, 0]) - math.atan2(forward_lidar[1], forward_lidar[0])
            az = (az + np.pi) % (2 * np.pi) - np.pi
            keep &= np.abs(az) <= np.deg2rad(c.severity) / 2
    return points[keep]


# ---------------------------------------------------------------- cameras

def missing_cameras(n: int, corruptions, token: str) -> np.ndarray:
    """(n,) bool: the cameras of sample ``token`` that deliver nothing (``camera_crash``,
    ``frame_lost``), drawn from each corruption's own generator (:meth:`Corruption.rng`)."""
    missing = np.zeros(n, bool)
    for c in corruptions:
        if c.name == "camera_crash":
            missing[c.rng(token).choice(n, size=min(n, int(c.severity)), replace=False)] = True
        elif c.name == "frame_lost":
            missing[c.rng(token).random(n) < c.severity] = True
    return missing


def corrupt_cameras(images: np.ndarray, T_lidar_from_cam: np.ndarray, intrinsics: np.ndarray, img_aug: np.ndarray,
                    up_lidar: np.ndarray, corruptions, token: str):
    """images (N, 3, H, W) network input, T_lidar_from_cam (N, 4, 4) -> corrupted copies and
    missing (N,) bool, the cameras that delivered nothing (``camera_crash``, ``frame_lost``).

    intrinsics : (N, 3, 3) K of the original images; img_aug : (N, 3, 3) original -> network
    pixels; up_lidar : (3,) the ego's up axis in the lidar frame (``motion_blur``'s horizon)."""
    images, T = images.copy(), T_lidar_from_cam.copy()
    n = len(images)
    missing = missing_cameras(n, corruptions, token)
    for c in corruptions:
        rng = c.rng(token)
        if c.name == "extrinsic_noise":
            rot = Rotation.from_euler("xyz", rng.normal(0.0, c.severity, (n, 3)), degrees=True).as_matrix()
            shift = rng.normal(0.0, 0.02 * c.severity, (n, 3))
            noise = np.tile(np.eye(4), (n, 1, 1))
            noise[:, :3, :3], noise[:, :3, 3] = rot, shift
            T = T @ noise          # the camera frame is perturbed: T_lidar_from_cam' = T_lidar_from_cam @ T_cam_from_cam'
        elif c.name == "motion_blur":   # the geometry the loader was given, before any noise above
            vectors = motion_blur.blur_vectors(c.severity, T_lidar_from_cam, up_lidar, intrinsics, img_aug)
            images = motion_blur.blur_images(images, vectors)
    images[missing] = 0.0
    return images, T, missing


# ---------------------------------------------------------------- one sensor's records

def misalignment(severity: float) -> np.ndarray:
    """(4, 4) float64 the calibration error of ``misalign:SENSOR:severity`` in the ego's axes:
    rotation Rz(s) Ry(s) Rx(s) (s in degrees) and translation 0.02 s m along each axis."""
    E = np.eye(4)
    E[:3, :3] = Rotation.from_euler("xyz", [severity] * 3, degrees=True).as_matrix()
    E[:3, 3] = MISALIGN_SHIFT_M * severity
    return E


def miscalibrated(T_ego_from_sensor: np.ndarray, channel: str, corruptions) -> np.ndarray:
    """(4, 4) the T_ego_from_sensor the loader believes for ``channel``: the calibrated one unless a
    ``misalign`` names that channel, then turned by the error's rotation about the sensor's mount
    point and shifted by its translation: R' = R_err R, t' = t + t_err."""
    T = T_ego_from_sensor
    for c in corruptions:
        if c.name == "misalign" and c.sensor == channel:
            E, T = misalignment(c.severity), T.copy()
            T[:3, :3] = E[:3, :3] @ T[:3, :3]
            T[:3, 3] = T[:3, 3] + E[:3, 3]
    return T


def late_record(sd: dict, corruptions, get) -> dict:
    """The sample_data record whose file the loader reads for record ``sd``: ``sd`` itself, or,
    under ``late`` on its channel, the record that many frames earlier on that channel (the
    oldest one where the channel has fewer). ``get`` : the devkit's ``NuScenes.get``."""
    frames = sum(int(c.severity) for c in corruptions if c.name == "late" and c.sensor == sd["channel"])
    for _ in range(frames):
        if not sd["prev"]:
            break
        sd = get("sample_data", sd["prev"])
    return sd
