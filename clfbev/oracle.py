"""The sensor-visibility oracle: the ground truth restricted to the objects that a condition's
degraded sensors still see, the upper bound of any detector under that condition.

An annotation is seen under a condition when

- **the lidar** puts at least one point of the condition's key-frame sweep inside its box (the
  devkit's ``num_lidar_pts``, counted with its ``points_in_box`` on the points the loader gives
  under the condition: the set's own files, after its load-time lidar corruptions), or
- **a camera** that delivers under the condition sees it as KITTI's "moderate" difficulty
  defines a visible object (Geiger et al., CVPR 2012): its 2D box at least 25 px tall at KITTI's
  focal length (an angular size, so scaled by each camera's own focal length), at most 30 % of
  it outside the image, and at most partly occluded (nuScenes visibility above 40 %, the set's
  own ``visibility_token``); and it lies within the cameras' meteorological optical range, where
  a black object's contrast falls to 5 % through the set's fog, rain and snowfall (simgen's
  ``camera_visibility_m``; Koschmieder).

Conditions that mislead a sensor without hiding anything from it (a wrong calibration, a stale
frame, extrinsic noise, motion blur) see what the clean set sees. Not modelled: lens dirt (its
mask is not on disk, so a dirty camera counts as seeing) and the night (street lights per EN
13201 C3 and the vehicles' lamps light every object in range; simgen's night camera keeps an
SNR of 15 on a grey car at 50 m).
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from pyquaternion import Quaternion

from clfbev.corruptions import CAMERA, LIDAR as LIDAR_CORRUPTIONS, missing_cameras
from clfbev.data import CAMERAS, LIDAR, NuScenesDetection, transform_from
from clfbev.errors import DataError
from clfbev.settings import DataConfig

KITTI_FOCAL_PX = 721.5377            # KITTI's rectified camera focal length (P2, 2011_09_26)
KITTI_MODERATE_HEIGHT_PX = 25.0      # "moderate": a 2D box at least 25 px tall ...
KITTI_MODERATE_TRUNCATION = 0.30     # ... at most 30 % outside the image ...
MIN_VISIBILITY_TOKEN = 2             # ... and at most partly occluded: nuScenes visibility > 40 %
MIN_DEPTH_M = 0.1                    # a corner closer to a camera's plane is behind it
# Everything the loader reads, and only the key sweep: num_lidar_pts counts the key sweep.
ORACLE_DATA = DataConfig(n_sweeps=1, min_points=0, point_range=(-1e4, -1e4, -1e4, 1e4, 1e4, 1e4))


@dataclass(frozen=True)
class Camera:
    """One camera of one sample: K (3, 3), T_cam_from_global (4, 4), size (W, H) px."""
    K: np.ndarray
    T_cam_from_global: np.ndarray
    size: tuple[int, int]


@dataclass(frozen=True)
class Sight:
    """What a condition's sensors see of one sample's annotations (M of them)."""
    tokens: tuple[str, ...]
    lidar_points: np.ndarray      # (M,) int: key-frame points inside each box
    camera: np.ndarray            # (M,) bool: seen by a delivering camera

    @property
    def seen(self) -> np.ndarray:
        return (self.lidar_points > 0) | self.camera


def set_sensors(root: Path, version: str) -> tuple[frozenset[str], float]:
    """The failed sensor channels of a set and its cameras' visibility (m; inf in clear air),
    from simgen's ``degradation.json`` (a set without one: none failed, clear air)."""
    path = Path(root) / version / "degradation.json"
    if not path.is_file():
        return frozenset(), math.inf
    try:
        rec = json.loads(path.read_text())
        failed = frozenset(rec.get("failed_sensors", ()))
        if "camera_visibility_m" in rec:
            mor = rec["camera_visibility_m"]
        else:   # a set made before the cameras' visibility was recorded: its fog alone
            mor = rec.get("fog_visibility_m")
        return failed, (math.inf if mor is None else float(mor))
    except (ValueError, TypeError, AttributeError):
        raise DataError(f"{path}: not a simgen degradation record") from None


def camera_sees(corners_global: np.ndarray, cameras: list[Camera], visible_range: float) -> np.ndarray:
    """(M, 8, 3) box corners (global) -> (M,) bool: some camera sees the box by KITTI's
    moderate size and truncation limits, within ``visible_range`` metres of that camera."""
    M = len(corners_global)
    seen = np.zeros(M, bool)
    for cam in cameras:
        R, t = cam.T_cam_from_global[:3, :3], cam.T_cam_from_global[:3, 3]
        p = corners_global @ R.T + t                                  # (M, 8, 3) camera frame
        z = p[..., 2]
        in_front = (z > MIN_DEPTH_M).all(axis=1)
        uv = (p @ cam.K.T)[..., :2] / np.where(z > MIN_DEPTH_M, z, 1.0)[..., None]
        lo, hi = uv.min(axis=1), uv.max(axis=1)                       # (M, 2) the 2D box
        W, H = cam.size
        clip_lo, clip_hi = np.clip(lo, 0, [W, H]), np.clip(hi, 0, [W, H])
        area = np.prod(hi - lo, axis=1)
        inside = np.prod(clip_hi - clip_lo, axis=1) / np.maximum(area, 1e-9)
        tall = (clip_hi[:, 1] - clip_lo[:, 1]) >= KITTI_MODERATE_HEIGHT_PX * cam.K[1, 1] / KITTI_FOCAL_PX
        near = np.linalg.norm(corners_global.mean(axis=1) - cam.T_cam_from_global[:3, :3].T @ -t, axis=1) <= visible_range
        seen |= in_front & (inside >= 1.0 - KITTI_MODERATE_TRUNCATION) & tall & near
    return seen


class Oracle:
    """The sights of one condition: a dataroot and its load-time corruptions, over one split.

    Only the corruptions that take data away count: the lidar's (``beam_missing``, ``density``,
    ``fov``, ``lidar_missing``) and the cameras that deliver nothing (``camera_crash``,
    ``frame_lost``).
    """

    def __init__(self, dataroot: str | Path, version: str, split: str, corruptions=()):
        lidar = tuple(c for c in corruptions if c.name in LIDAR_CORRUPTIONS)
        self.cameras_lost = tuple(c for c in corruptions if c.name in CAMERA)
        self.ds = NuScenesDetection(dataroot, version, split, ORACLE_DATA, lidar)
        self.failed, self.visible_range = set_sensors(Path(dataroot), version)

    def __len__(self) -> int:
        return len(self.ds)

    def sight(self, index: int) -> Sight:
        """What the condition's sensors see of sample ``index``'s annotations."""
        from nuscenes.utils.data_classes import Box
        from nuscenes.utils.geometry_utils import points_in_box

        nusc, token = self.ds.nusc, self.ds.sample_tokens[index]
        sample = nusc.get("sample", token)
        anns = [nusc.get("sample_annotation", t) for t in sample["anns"]]
        boxes = [Box(a["translation"], a["size"], Quaternion(a["rotation"])) for a in anns]
        corners = np.stack([b.corners().T for b in boxes]) if boxes else np.zeros((0, 8, 3))
        points = self.ds.lidar_points(index)[:, :3].T if LIDAR not in self.failed else np.zeros((3, 0))
        lidar_sd = nusc.get("sample_data", sample["data"][LIDAR])
        pose = nusc.get("ego_pose", lidar_sd["ego_pose_token"])
        calib = nusc.get("calibrated_sensor", lidar_sd["calibrated_sensor_token"])
        counts = np.array([int(points_in_box(self._in_sensor_frame(b, pose, calib), points).sum()) for b in boxes], int)
        visible = np.array([int(a["visibility_token"]) >= MIN_VISIBILITY_TOKEN for a in anns], bool)
        camera = camera_sees(corners, self._cameras(sample), self.visible_range) & visible
        return Sight(tuple(a["token"] for a in anns), counts, camera)

    def _cameras(self, sample: dict) -> list[Camera]:
        """The cameras of ``sample`` that deliver under the condition."""
        lost = missing_cameras(len(CAMERAS), self.cameras_lost, sample["token"])
        out = []
        for channel, gone in zip(CAMERAS, lost):
            if gone or channel in self.failed:
                continue
            sd = self.ds.nusc.get("sample_data", sample["data"][channel])
            calib = self.ds.nusc.get("calibrated_sensor", sd["calibrated_sensor_token"])
            out.append(Camera(np.asarray(calib["camera_intrinsic"], float),
                              np.linalg.inv(self._T_global_from(sd)), (int(sd["width"]), int(sd["height"]))))
        return out

    def _T_global_from(self, sd: dict) -> np.ndarray:
        """(4, 4) T_global_from_sensor of a sample_data record, from its true calibration."""
        nusc = self.ds.nusc
        pose = nusc.get("ego_pose", sd["ego_pose_token"])
        calib = nusc.get("calibrated_sensor", sd["calibrated_sensor_token"])
        return transform_from(pose["translation"], pose["rotation"]) @ transform_from(calib["translation"], calib["rotation"])

    @staticmethod
    def _in_sensor_frame(box, pose: dict, calib: dict):
        """A copy of a global devkit Box moved into a sensor's frame by the same operations, in
        the same order, as ``NuScenes.get_sample_data``: the counts are the devkit's to the bit."""
        box = box.copy()
        box.translate(-np.array(pose["translation"]))
        box.rotate(Quaternion(pose["rotation"]).inverse)
        box.translate(-np.array(calib["translation"]))
        box.rotate(Quaternion(calib["rotation"]).inverse)
        return box
