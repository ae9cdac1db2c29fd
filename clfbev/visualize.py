"""Pictures: camera overlays and a BEV of predictions against GT, MCM / BSM attention maps for one
BEV cell (as the paper's Fig. 6), and loss curves.

Predictions come from a nuScenes results file (global frame); GT from the devkit. Both are moved
into each sensor's frame with that sensor's own ego pose and calibration, as the devkit's
``get_sample_data`` does, so what is drawn is exactly what the evaluation compares.
Colours (BGR): GT green, predictions orange, text white.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import torch

from clfbev.data import CAMERAS, LIDAR, DataError

GT_COLOR, PRED_COLOR = (60, 200, 60), (0, 140, 255)
# devkit corner order: 0-3 the front face, 4-7 the back face
EDGES = [(0, 1), (1, 2), (2, 3), (3, 0), (4, 5), (5, 6), (6, 7), (7, 4), (0, 4), (1, 5), (2, 6), (3, 7)]


def load_results(path: str | Path) -> dict[str, list[dict]]:
    """``results`` of a nuScenes submission file; DataError naming the file if unusable."""
    path = Path(path)
    try:
        sub = json.loads(path.read_text())
        results = sub["results"]
        if not isinstance(results, dict):
            raise TypeError("'results' is not a mapping")
    except FileNotFoundError:
        raise DataError(f"results file {path} does not exist") from None
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise DataError(f"results file {path} is not a nuScenes submission ({e})") from None
    return results


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


# ---------------------------------------------------------------- attention maps

@torch.no_grad()
def attention_maps(model, batch, cell: tuple[int, int]) -> dict[str, np.ndarray]:
    """Head-averaged attention weights of BEV query ``cell`` (row, col): ``{'MCM': (H, W),
    'BSM': (H, W)}`` for the modules the model has (MCM: lidar query over the camera BEV; BSM:
    fused query over the fused BEV). Recomputes the BEV path of ``CLFusionBEV.bev_features``."""
    model.eval()
    out = {}
    if model.mcm is None and model.bsm is None:
        raise ValueError(f"variant '{model.variant}' has no attention module (use mcm or full)")
    lidar_bev = model.lidar_encoder(batch.points)
    cam_bev = model.camera_encoder(batch.images, batch.intrinsics, batch.T_lidar_from_cam, batch.img_aug)
    out["MCM"] = model.mcm.attention_map(lidar_bev, cam_bev, cell)[0].mean(0).cpu().numpy()
    fused = model.fuser(model.mcm(lidar_bev, cam_bev), cam_bev)
    if model.bsm is not None:
        out["BSM"] = model.bsm.attention_map(fused, cell)[0].mean(0).cpu().numpy()
    return out


def cell_of(xy: tuple[float, float], pc_range, bev_shape: tuple[int, int]) -> tuple[int, int]:
    """(row, col) of the BEV cell holding lidar-frame point ``xy`` (rows along y, cols along x)."""
    xmin, ymin, _, xmax, ymax, _ = pc_range
    ny, nx = bev_shape
    col = int(np.clip((xy[0] - xmin) / (xmax - xmin) * nx, 0, nx - 1))
    row = int(np.clip((xy[1] - ymin) / (ymax - ymin) * ny, 0, ny - 1))
    return row, col


def attention_panel(maps: dict[str, np.ndarray], points: np.ndarray, cell: tuple[int, int], pc_range,
                    size: int) -> np.ndarray:
    """One BGR panel per map: the weights as a heat map over the lidar BEV, query cell circled.
    Rows of the map run along +y, so they are flipped to put +y up as in the BEV plot."""
    xmin, ymin, _, xmax, ymax, _ = pc_range
    half = max(xmax, -xmin, ymax, -ymin)
    panels = []
    for name, m in maps.items():
        base = bev_canvas(points, size, half)
        heat = m / max(float(m.max()), 1e-12)
        heat = cv2.resize(np.flipud(heat).astype(np.float32), (size, size), interpolation=cv2.INTER_NEAREST)
        color = cv2.applyColorMap((heat * 255).astype(np.uint8), cv2.COLORMAP_INFERNO)
        img = cv2.addWeighted(base, 0.45, color, 0.55, 0)
        ny, nx = m.shape
        r, c = cell
        centre = (int((c + 0.5) / nx * size), int((1 - (r + 0.5) / ny) * size))
        cv2.circle(img, centre, 8, (255, 255, 255), 2)
        cv2.putText(img, f"{name}: attention of the circled query cell", (8, 24), cv2.FONT_HERSHEY_SIMPLEX, 0.6,
                    (255, 255, 255), 2, cv2.LINE_AA)
        panels.append(img)
    return np.concatenate(panels, 1)


# ---------------------------------------------------------------- curves

def plot_loss_curve(metrics_jsonl: str | Path, out_png: str | Path) -> Path:
    """Training loss (and its parts) against the step, val NDS/mAP on a second axis."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = [json.loads(ln) for ln in Path(metrics_jsonl).read_text().splitlines() if ln.strip()]
    train = [r for r in rows if "train/loss" in r]
    val = [r for r in rows if "val/NDS" in r]
    fig, ax = plt.subplots(figsize=(8, 4.5), dpi=110)
    steps = np.array([r["step"] for r in train])
    for key, style in (("train/loss", "-"), ("train/loss_cls", ":"), ("train/loss_reg", "--"), ("train/loss_dir", "-.")):
        y, x = np.array([r.get(key, np.nan) for r in train]), steps
        k = max(1, len(y) // 50)
        if k > 1:    # a trailing running mean makes the trend readable; raw values are in the JSONL
            y, x = np.convolve(y, np.ones(k) / k, mode="valid"), steps[k - 1:]
        ax.plot(x, y, style, label=key.split("/")[1])
    ax.set_yscale("log")
    ax.set_xlabel("step")
    ax.set_ylabel("loss")
    ax.grid(alpha=0.3)
    ax.legend(loc="upper left")
    if val:
        ax2 = ax.twinx()
        ax2.plot([r["step"] for r in val], [r["val/NDS"] for r in val], "o-", color="tab:green", label="val NDS")
        ax2.plot([r["step"] for r in val], [r["val/mAP"] for r in val], "s-", color="tab:red", label="val mAP")
        ax2.set_ylabel("val metric")
        ax2.set_ylim(0, 1)
        ax2.legend(loc="upper right")
    fig.tight_layout()
    out_png = Path(out_png)
    tmp = out_png.with_name(f".{out_png.stem}.tmp.png")
    fig.savefig(tmp)
    plt.close(fig)
    tmp.replace(out_png)
    return out_png
