"""The sheet of ``clfbev show``: the six cameras with boxes projected, over a lidar BEV, predictions
against GT.

Predictions come from a nuScenes results file (global frame); GT from the devkit. Both are
moved into each sensor's frame with that sensor's own ego pose and calibration, as the devkit's
``get_sample_data`` does, so what is drawn is exactly what the evaluation compares.
Colours (BGR): GT green, predictions orange, text white.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np

from clfbev.data import CAMERAS, LIDAR
from clfbev.errors import DataError

GT_COLOR, PRED_COLOR = (60, 200, 60), (0, 140, 255)
# devkit corner order: 0-3 the front face, 4-7 the back face
EDGES = [(0, 1), (1, 2), (2, 3), (3, 0), (4, 5), (5, 6), (6, 7), (7, 4), (0, 4), (1, 5), (2, 6), (3, 7)]


def load_results(path: str | Path) -> dict[str, list[dict]]:
    """``results`` of a nuScenes submission file; DataError naming the file if unusable. The
    records are checked where they are drawn (:func:`check_records`)."""
    path = Path(path)
    if not path.is_file():
        raise DataError(f"results file {path} does not exist")
    try:
        sub = json.loads(path.read_text())
    except (OSError, ValueError) as e:
        raise DataError(f"results file {path} is not JSON ({e})") from None
    results = sub.get("results") if isinstance(sub, dict) else None
    if not isinstance(results, dict):
        raise DataError(f"results file {path} is not a nuScenes submission: it lacks the mapping 'results' "
                        "of sample tokens to boxes")
    return results


def check_records(path: str | Path, token: str, records: object) -> list[dict]:
    """The result records of sample ``token`` of results file ``path``, refused (DataError naming
    the file, the sample and the field) unless each is a box the sheet can draw: a
    ``translation`` and a ``size`` of 3 finite numbers, a ``rotation`` quaternion of 4 (not all
    zero), a ``detection_name``, and a numeric ``detection_score`` where there is one."""
    if not isinstance(records, list):
        raise DataError(f"results file {path}: sample {token} holds {type(records).__name__}, not a list of boxes")
    for k, r in enumerate(records):
        where = f"results file {path}: sample {token}, box {k}"
        if not isinstance(r, dict):
            raise DataError(f"{where} is not a mapping")
        for key, n in (("translation", 3), ("size", 3), ("rotation", 4)):
            value = r.get(key)
            if not (isinstance(value, list) and len(value) == n and all(_finite(v) for v in value)):
                raise DataError(f"{where}: '{key}' must be {n} finite numbers, got {value!r}")
        if not any(r["rotation"]):
            raise DataError(f"{where}: 'rotation' is the zero quaternion")
        if not isinstance(r.get("detection_name"), str):
            raise DataError(f"{where}: 'detection_name' must be a string, got {r.get('detection_name')!r}")
        if "detection_score" in r and not _finite(r["detection_score"]):
            raise DataError(f"{where}: 'detection_score' must be a finite number, got {r['detection_score']!r}")
    return records


def _finite(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _boxes_in_sensor(nusc, sd_token: str, records: list[dict]):
    """devkit Boxes of result ``records`` (global frame) moved into sample_data ``sd_token``'s
    sensor frame through its own ego pose and calibration."""
    from nuscenes.utils.data_classes import Box
    from pyquaternion import Quaternion
    sd = nusc.get("sample_data", sd_token)
    pose = nusc.get("ego_pose", sd["ego_pose_token"])
    cs = nusc.get("calibrated_sensor", sd["calibrated_sensor_token"])
    boxes = []
    for r in records:
        b = Box(r["translation"], r["size"], Quaternion(r["rotation"]), name=r["detection_name"],
                score=r.get("detection_score", float("nan")))
        b.translate(-np.array(pose["translation"]))
        b.rotate(Quaternion(pose["rotation"]).inverse)
        b.translate(-np.array(cs["translation"]))
        b.rotate(Quaternion(cs["rotation"]).inverse)
        boxes.append(b)
    return boxes


def _gt_in_sensor(nusc, sd_token: str):
    _, boxes, _ = nusc.get_sample_data(sd_token)
    return boxes


def draw_camera(nusc, sd_token: str, preds: list[dict], width: int) -> np.ndarray:
    """A camera image (BGR, ``width`` pixels wide) with GT and predicted boxes projected."""
    from nuscenes.utils.geometry_utils import view_points
    sd = nusc.get("sample_data", sd_token)
    path = Path(nusc.dataroot) / sd["filename"]
    img = cv2.imread(str(path))
    if img is None:
        raise DataError(f"missing or unreadable image file {path}")
    K = np.array(nusc.get("calibrated_sensor", sd["calibrated_sensor_token"])["camera_intrinsic"])
    for boxes, color in ((_gt_in_sensor(nusc, sd_token), GT_COLOR), (_boxes_in_sensor(nusc, sd_token, preds), PRED_COLOR)):
        for box in boxes:
            corners = box.corners()                      # (3, 8) camera frame
            if np.any(corners[2] < 0.5):
                continue
            uv = view_points(corners, K, normalize=True)[:2].T
            for a, b in EDGES:
                cv2.line(img, tuple(int(v) for v in uv[a]), tuple(int(v) for v in uv[b]), color, 2, cv2.LINE_AA)
    cv2.putText(img, sd["channel"], (8, 24), cv2.FONT_HERSHEY_SIMPLEX, 0.7, (255, 255, 255), 2, cv2.LINE_AA)
    scale = width / img.shape[1]
    return cv2.resize(img, (width, int(round(img.shape[0] * scale))), interpolation=cv2.INTER_AREA)


def bev_canvas(points: np.ndarray, size: int, half_range: float) -> np.ndarray:
    """(size, size, 3) uint8 BEV of ``points`` (n, >=3) lidar frame; x right, y up."""
    img = np.full((size, size, 3), 20, np.uint8)
    s = size / (2 * half_range)
    u = ((points[:, 0] + half_range) * s).astype(int)
    v = ((half_range - points[:, 1]) * s).astype(int)
    ok = (u >= 0) & (u < size) & (v >= 0) & (v < size)
    shade = np.clip(90 + (points[:, 2] + 2) * 30, 60, 230).astype(np.uint8)
    img[v[ok], u[ok]] = shade[ok, None]
    return img


def draw_bev(nusc, sd_token: str, preds: list[dict], size: int, half_range: float = 50.0) -> np.ndarray:
    """Lidar BEV (key-frame lidar frame) with GT and predicted footprints; heading ticks."""
    from nuscenes.utils.data_classes import LidarPointCloud
    sd = nusc.get("sample_data", sd_token)
    path = Path(nusc.dataroot) / sd["filename"]
    try:
        pts = LidarPointCloud.from_file(str(path)).points.T
    except (OSError, ValueError) as e:
        raise DataError(f"missing or unreadable lidar file {path} ({e})") from None
    img = bev_canvas(pts, size, half_range)
    s = size / (2 * half_range)
    for boxes, color in ((_gt_in_sensor(nusc, sd_token), GT_COLOR), (_boxes_in_sensor(nusc, sd_token, preds), PRED_COLOR)):
        for box in boxes:
            c = box.bottom_corners()[:2].T              # (4, 2)
            poly = np.stack([(c[:, 0] + half_range) * s, (half_range - c[:, 1]) * s], 1).astype(np.int32)
            cv2.polylines(img, [poly], True, color, 2, cv2.LINE_AA)
            cv2.line(img, tuple(poly.mean(0).astype(int)), tuple(((poly[0] + poly[1]) / 2).astype(int)), color, 1)
    cv2.circle(img, (size // 2, size // 2), 4, (0, 0, 255), -1)
    cv2.putText(img, f"BEV {half_range:.0f} m  GT green, pred orange", (8, 24), cv2.FONT_HERSHEY_SIMPLEX, 0.6,
                (255, 255, 255), 2, cv2.LINE_AA)
    return img


def sample_sheet(nusc, sample_token: str, preds: list[dict], score_thr: float, width: int = 480) -> np.ndarray:
    """Six cameras (2 x 3, nuScenes order) over a BEV panel: one BGR image."""
    sample = nusc.get("sample", sample_token)
    preds = [p for p in preds if p.get("detection_score", 1.0) >= score_thr]
    cams = [draw_camera(nusc, sample["data"][c], preds, width) for c in CAMERAS]
    rows = [np.concatenate(cams[:3], 1), np.concatenate(cams[3:], 1)]
    grid = np.concatenate(rows, 0)
    bev = draw_bev(nusc, sample["data"][LIDAR], preds, grid.shape[0])
    return np.concatenate([grid, bev], 1)
