"""`simgen show`: a contact sheet of one sample: the six cameras with their projected GT boxes,
and a lidar BEV with the boxes, read back through nuscenes-devkit from the written files."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from .errors import ConfigError, DataError
from .rig import CAMERAS
from .writer import write_png

CLASS_COLORS = {  # BGR
    "vehicle.car": (0, 140, 255), "vehicle.truck": (0, 90, 200), "vehicle.bus.rigid": (0, 60, 160),
    "vehicle.motorcycle": (180, 0, 200), "vehicle.bicycle": (60, 20, 220), "human.pedestrian.adult": (230, 60, 20),
    "movable_object.trafficcone": (0, 200, 255), "movable_object.barrier": (90, 90, 90),
}
NOISE_BGR = (255, 255, 255)
# devkit corner order: 0-3 the front face, 4-7 the back face
EDGES = [(0, 1), (1, 2), (2, 3), (3, 0), (4, 5), (5, 6), (6, 7), (7, 4), (0, 4), (1, 5), (2, 6), (3, 7)]


def load_nusc(dataroot: Path, version: str):
    """NuScenes(version, dataroot) with a clear error instead of a traceback."""
    from nuscenes import NuScenes
    if not (Path(dataroot) / version).is_dir():
        raise DataError(f"{dataroot}: no {version}/ folder with nuScenes tables")
    try:
        return NuScenes(version=version, dataroot=str(dataroot), verbose=False)
    except (OSError, ValueError, KeyError, AssertionError) as e:
        raise DataError(f"{dataroot}/{version}: cannot be loaded by nuscenes-devkit ({e})") from None


def draw_camera(nusc, sd_token: str, width: int) -> np.ndarray:
    """One camera image (BGR) with the GT boxes projected through the written calibration."""
    from nuscenes.utils.geometry_utils import view_points
    path, boxes, K = nusc.get_sample_data(sd_token)
    img = cv2.imread(path)
    if img is None:
        raise DataError(f"{path}: missing or not a readable image")
    for box in boxes:
        corners = box.corners()                       # (3, 8) camera frame
        if np.any(corners[2] < 0.5):
            continue
        uv = view_points(corners, K, normalize=True)[:2].T
        color = CLASS_COLORS.get(box.name, (255, 255, 255))
        for a, b in EDGES:
            cv2.line(img, tuple(int(v) for v in uv[a]), tuple(int(v) for v in uv[b]), color, 2, cv2.LINE_AA)
    channel = nusc.get("sample_data", sd_token)["channel"]
    cv2.putText(img, channel, (8, 24), cv2.FONT_HERSHEY_SIMPLEX, 0.7, (255, 255, 255), 2, cv2.LINE_AA)
    scale = width / img.shape[1]
    return cv2.resize(img, (width, int(round(img.shape[0] * scale))), interpolation=cv2.INTER_AREA)


def point_colors(nusc, sd_token: str, pts: np.ndarray) -> tuple[np.ndarray, str]:
    """(n, 3) BGR per point: the devkit's nuScenes-lidarseg colours when the sweep has labels,
    else grey by intensity and height; and a caption saying which."""
    seg = {r["sample_data_token"]: r for r in getattr(nusc, "lidarseg", [])}.get(sd_token)
    if seg is not None:
        path = Path(nusc.dataroot) / seg["filename"]
        try:
            labels = np.fromfile(path, dtype=np.uint8)
        except OSError as e:
            raise DataError(f"{path}: unreadable lidarseg labels ({e})") from None
        if len(labels) != pts.shape[1]:
            raise DataError(f"{path}: {len(labels)} lidarseg labels for a sweep of {pts.shape[1]} points")
        palette = np.array([nusc.colormap[nusc.lidarseg_idx2name_mapping[i]][::-1]
                            for i in range(len(nusc.lidarseg_idx2name_mapping))], np.uint8)
        # The devkit's colour of "noise" (the weather's clutter) is black: invisible on this BEV.
        palette[nusc.lidarseg_name2idx_mapping["noise"]] = NOISE_BGR
        return palette[np.minimum(labels, len(palette) - 1)], "lidarseg colours, noise white"
    shade = np.clip(80 + pts[3] * 0.7 + (pts[2] + 2) * 25, 60, 255).astype(np.uint8)
    return np.stack([shade] * 3, 1), "intensity"


def draw_bev(nusc, sd_token: str, size: int, half_range: float = 50.0) -> np.ndarray:
    """Lidar BEV (sensor frame, x right, y up) with the GT boxes, ``half_range`` metres each way;
    the points in their lidarseg class colours when the dataset has them."""
    from nuscenes.utils.data_classes import LidarPointCloud
    path, boxes, _ = nusc.get_sample_data(sd_token)
    try:
        pts = LidarPointCloud.from_file(path).points
    except (OSError, ValueError) as e:
        raise DataError(f"{path}: not a readable .pcd.bin ({e})") from None
    img = np.full((size, size, 3), 20, np.uint8)
    s = size / (2 * half_range)
    u = ((pts[0] + half_range) * s).astype(int)
    v = ((half_range - pts[1]) * s).astype(int)
    ok = (u >= 0) & (u < size) & (v >= 0) & (v < size)
    colors, caption = point_colors(nusc, sd_token, pts)
    img[v[ok], u[ok]] = colors[ok]
    for box in boxes:
        c = box.bottom_corners()[:2].T                 # (4, 2)
        poly = np.stack([(c[:, 0] + half_range) * s, (half_range - c[:, 1]) * s], 1).astype(np.int32)
        color = CLASS_COLORS.get(box.name, (255, 255, 255))
        cv2.polylines(img, [poly], True, color, 2, cv2.LINE_AA)
        front = ((poly[0] + poly[1]) / 2).astype(int)
        centre = poly.mean(0).astype(int)
        cv2.line(img, tuple(centre), tuple(front), color, 1, cv2.LINE_AA)
    cv2.circle(img, (size // 2, size // 2), 4, (0, 0, 255), -1)
    cv2.putText(img, f"LIDAR_TOP  {half_range:.0f} m, {caption}", (8, 24), cv2.FONT_HERSHEY_SIMPLEX, 0.7,
                (255, 255, 255), 2)
    return img


def contact_sheet(dataroot: Path, version: str, sample_index: int, out: Path, tile_width: int = 640) -> Path:
    """Write the contact sheet PNG: cameras in two rows (front row, back row) plus the BEV."""
    nusc = load_nusc(dataroot, version)
    if not 0 <= sample_index < len(nusc.sample):
        raise ConfigError(f"--sample {sample_index}: out of range [0, {len(nusc.sample) - 1}]")
    sample = nusc.sample[sample_index]
    tiles = {ch: draw_camera(nusc, sample["data"][ch], tile_width) for ch in CAMERAS}
    top = np.concatenate([tiles["CAM_FRONT_LEFT"], tiles["CAM_FRONT"], tiles["CAM_FRONT_RIGHT"]], 1)
    bottom = np.concatenate([tiles["CAM_BACK_LEFT"], tiles["CAM_BACK"], tiles["CAM_BACK_RIGHT"]], 1)
    cams = np.concatenate([top, bottom], 0)
    bev = draw_bev(nusc, sample["data"]["LIDAR_TOP"], cams.shape[0])
    sheet = np.concatenate([cams, bev], 1)
    write_png(Path(out), sheet)
    return Path(out)
