"""Pictures: camera overlays and a BEV of predictions against GT, the MCM / BSM attention of one
BEV query cell (as the paper's Fig. 6), and loss curves.

Sheet: predictions come from a nuScenes results file (global frame); GT from the devkit. Both are
moved into each sensor's frame with that sensor's own ego pose and calibration, as the devkit's
``get_sample_data`` does, so what is drawn is exactly what the evaluation compares.
Colours (BGR): GT green, predictions orange, text white.

Attention strip (below the sheet): the query cell sits under the centre of the model's own best
detection (else the GT box nearest the ego); each module's panel zooms on the cells the query
attends to (window mode: its window; exact / pooled: the cells holding most of the weight) and
draws the mean over heads, the whole map, and each head, in metres in the lidar frame.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
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


# ---------------------------------------------------------------- attention of one query cell
#
# Frames: a BEV map is (H, W) = (ny, nx) over ``cfg.pc_range``, rows along +y and columns along
# +x of the key-frame lidar frame; cell (r, c) is centred at x = xmin + (c + 0.5) dx,
# y = ymin + (r + 0.5) dy, as the anchors are. The panels are drawn in metres, x right and y up,
# as the sheet's BEV panel.

MASS = 0.95            # exact / pooled: the zoom holds at least this share of each head's weight
ZOOM_PAD_CELLS = 1     # exact / pooled: a margin around those cells
MIN_ZOOM_CELLS = 8     # exact / pooled: a peaked map is still shown with some context
DPI = 100
BG, FG = (20 / 255,) * 3, "white"
GT_RGB, PRED_RGB = (60 / 255, 200 / 255, 60 / 255), (1.0, 140 / 255, 0.0)    # the sheet's GT_COLOR, PRED_COLOR
QUERY_RGB, ZOOM_RGB = (0.0, 1.0, 1.0), (1.0, 0.2, 0.6)


@dataclass(frozen=True)
class Query:
    """The BEV query cell whose attention is drawn.

    xy : (x, y) metres, lidar frame; cell : (row, col) of the BEV cell holding ``xy``;
    what : what lies there, for the titles; box : (7+,) that object's box (lidar frame) or None.
    """

    xy: tuple[float, float]
    cell: tuple[int, int]
    what: str
    box: np.ndarray | None = None


@dataclass(frozen=True)
class AttentionMap:
    """One module's attention of the query cell.

    name : 'MCM' or 'BSM'; keys : what attends to what, for the title;
    weights : (heads, H, W), each head summing to 1 over the key cells;
    attn : the module's :class:`clfbev.attention.BEVAttention` (mode, window, pool_stride).
    """

    name: str
    keys: str
    weights: np.ndarray
    attn: object


@dataclass(frozen=True)
class BEVScene:
    """What the attention panels overlay, lidar frame: points (n, >=2), GT boxes (M, 7+),
    predicted boxes (K, 7+), all numpy; ``pc_range`` and the BEV ``shape`` (H, W) place the cells."""

    points: np.ndarray
    gt_boxes: np.ndarray
    pred_boxes: np.ndarray
    pc_range: tuple[float, ...]
    shape: tuple[int, int]

    @property
    def cell_size(self) -> tuple[float, float]:
        """(dx, dy) metres of one BEV cell."""
        xmin, ymin, _, xmax, ymax, _ = self.pc_range
        return (xmax - xmin) / self.shape[1], (ymax - ymin) / self.shape[0]

    def metres(self, extent: tuple[int, int, int, int]) -> tuple[float, float, float, float]:
        """(x0, x1, y0, y1) metres covered by the cells ``extent`` = (r0, r1, c0, c1), half-open."""
        r0, r1, c0, c1 = extent
        (dx, dy), xmin, ymin = self.cell_size, self.pc_range[0], self.pc_range[1]
        return xmin + c0 * dx, xmin + c1 * dx, ymin + r0 * dy, ymin + r1 * dy


def attention_modules(model) -> list[str]:
    """Names of the attention modules ``model`` has, in the order of the forward pass."""
    return [name for name, m in (("MCM", model.mcm), ("BSM", model.bsm)) if m is not None]


def cell_of(xy: tuple[float, float], pc_range, bev_shape: tuple[int, int]) -> tuple[int, int]:
    """(row, col) of the BEV cell holding lidar-frame point ``xy``; ValueError outside the map."""
    xmin, ymin, _, xmax, ymax, _ = pc_range
    ny, nx = bev_shape
    if not (xmin <= xy[0] < xmax and ymin <= xy[1] < ymax):
        raise ValueError(f"query point ({xy[0]:g}, {xy[1]:g}) m lies outside the BEV map "
                         f"x [{xmin:g}, {xmax:g}), y [{ymin:g}, {ymax:g})")
    col = min(int((xy[0] - xmin) / (xmax - xmin) * nx), nx - 1)   # min: float rounding at xmax
    row = min(int((xy[1] - ymin) / (ymax - ymin) * ny), ny - 1)
    return row, col


def choose_query(dets, gt_boxes: torch.Tensor, gt_labels: torch.Tensor, class_names, pc_range,
                 bev_shape: tuple[int, int], xy: tuple[float, float] | None = None) -> Query:
    """The query: the point ``xy`` if given, else the centre of the highest-scoring detection
    (``dets``: :class:`clfbev.head.Detections`, boxes (K, 7+) lidar frame), else the centre of
    the GT box (``gt_boxes`` (M, 7+), ``gt_labels`` (M,)) nearest the ego, the lidar origin."""
    box = None
    if xy is not None:
        what = "the point given by --cell"
    elif len(dets.scores):
        k = int(dets.scores.argmax())
        box = dets.boxes[k]
        what = f"predicted {class_names[int(dets.labels[k])]}, score {float(dets.scores[k]):.2f}"
    elif len(gt_boxes):
        k = int(gt_boxes[:, :2].norm(dim=1).argmin())
        box = gt_boxes[k]
        what = f"no detection: the GT {class_names[int(gt_labels[k])]} nearest the ego"
    else:
        raise ValueError("no detection and no GT box in this sample to put the query on; give one with --cell X,Y")
    if box is not None:
        box = box.detach().cpu().numpy()
        xy = (float(box[0]), float(box[1]))
        what += f", {math.hypot(*xy):.1f} m away"
    return Query(xy, cell_of(xy, pc_range, bev_shape), what, box)


@torch.no_grad()
def attention_maps(model, batch, cell: tuple[int, int]) -> list[AttentionMap]:
    """The attention of BEV query ``cell`` (row, col) of sample 0 of ``batch``, per head, for
    each module the model has: MCM (lidar query over the camera BEV), then BSM (fused query over
    the fused BEV). Recomputes the BEV path of ``CLFusionBEV.bev_features`` up to each module."""
    if not attention_modules(model):
        raise ValueError(f"variant '{model.variant}' has no attention module (MCM: 'mcm', 'full'; BSM: 'full')")
    model.eval()
    lidar_bev = model.lidar_encoder(batch.points)                                  # (B, Cl, H, W)
    cam_bev = model.camera_encoder(batch.images, batch.intrinsics, batch.T_lidar_from_cam,
                                   batch.img_aug)                                   # (B, Cc, H, W)
    maps = []
    if model.mcm is not None:
        w = model.mcm.attention_map(lidar_bev, cam_bev, cell)                       # (B, heads, H, W)
        maps.append(AttentionMap("MCM", "lidar BEV query over the camera BEV", w[0].cpu().numpy(), model.mcm.attn))
        lidar_bev = model.mcm(lidar_bev, cam_bev)
    if model.bsm is not None:
        fused = model.fuser(lidar_bev, cam_bev)
        w = model.bsm.attention_map(fused, cell)
        maps.append(AttentionMap("BSM", "fused BEV query over the fused BEV", w[0].cpu().numpy(), model.bsm.attn))
    return maps


def zoom_extent(attn, weights: np.ndarray, cell: tuple[int, int]) -> tuple[int, int, int, int]:
    """Cells (r0, r1, c0, c1), half-open, that a panel of (heads, H, W) ``weights`` shows.

    ``window`` mode: exactly the cells query ``cell`` attends to, its tile of the
    non-overlapping ``window x window`` tiling that starts at cell (0, 0). BEVAttention pads the
    grid at the bottom / right to whole tiles but gives the padded keys weight 0, so an edge tile
    ends at the map edge; a window larger than the grid is clipped to it.

    ``exact`` / ``pooled``: the bounding box, over the heads, of the fewest cells holding
    :data:`MASS` of each head's weight, with the query cell, padded, grown to a minimum size and
    clipped to the map. As every head keeps at least MASS inside it, so does their mean.
    """
    H, W = weights.shape[1:]
    r, c = cell
    if attn.mode == "window":
        wh, ww = min(attn.window, H), min(attn.window, W)      # as BEVAttention._window_sizes
        r0, c0 = r // wh * wh, c // ww * ww
        return r0, min(r0 + wh, H), c0, min(c0 + ww, W)
    rows, cols = [r], [c]
    for w in weights:
        rr, cc = np.nonzero(_top_mass(w, MASS))
        rows += [rr.min(), rr.max()]
        cols += [cc.min(), cc.max()]
    return (*_span(min(rows), max(rows) + 1, H), *_span(min(cols), max(cols) + 1, W))


def _top_mass(w: np.ndarray, mass: float) -> np.ndarray:
    """Boolean mask (as ``w``) of the fewest cells of ``w`` whose weights sum to ``mass`` of its total."""
    order = np.argsort(w, axis=None)[::-1]
    cum = np.cumsum(w.ravel()[order])
    n = min(int(np.searchsorted(cum, mass * cum[-1])) + 1, w.size)
    keep = np.zeros(w.size, bool)
    keep[order[:n]] = True
    return keep.reshape(w.shape)


def _span(lo: int, hi: int, n: int) -> tuple[int, int]:
    """[lo, hi) padded and grown to MIN_ZOOM_CELLS, then moved and clipped into [0, n)."""
    lo, hi = lo - ZOOM_PAD_CELLS, hi + ZOOM_PAD_CELLS
    grow = max(0, MIN_ZOOM_CELLS - (hi - lo))
    lo, hi = lo - grow // 2, hi + grow - grow // 2
    # Shift a span hanging over one edge back inside before clipping, so it keeps its size.
    shift = max(0, -lo) - max(0, hi - n)
    return max(0, lo + shift), min(n, hi + shift)


def shown_mass(weights: np.ndarray, extent: tuple[int, int, int, int]) -> np.ndarray:
    """(heads,) share of each head's weight inside the cells ``extent`` = (r0, r1, c0, c1)."""
    r0, r1, c0, c1 = extent
    return weights[:, r0:r1, c0:c1].sum(axis=(1, 2)) / weights.sum(axis=(1, 2))


def draw_attention(model, batch, width: int, score_thr: float, xy: tuple[float, float] | None = None) -> np.ndarray:
    """The attention strip (BGR, ``width`` pixels wide) of sample 0 of ``batch`` for an 'mcm' or
    'full' model: the query goes on the model's own best detection scoring at least
    ``score_thr``, else on the GT box nearest the ego, or on lidar-frame point ``xy`` (metres).
    The model's own detections, not a results file's, so that the object queried is one this
    model sees."""
    cfg = model.cfg
    model.eval()
    dets = model.predict(batch, score_thr=score_thr)[0]
    query = choose_query(dets, batch.gt_boxes[0], batch.gt_labels[0], cfg.class_names, cfg.pc_range,
                         cfg.head_feature_size, xy)
    maps = attention_maps(model, batch, query.cell)
    scene = BEVScene(batch.points[0].cpu().numpy(), batch.gt_boxes[0].cpu().numpy(), dets.boxes.cpu().numpy(),
                     tuple(cfg.pc_range), tuple(cfg.head_feature_size))
    missing = [n for n in ("MCM", "BSM") if n not in {m.name for m in maps}]
    note = (f"variant '{model.variant}' has no {' or '.join(missing)} (MCM is in 'mcm' and 'full', BSM in 'full')"
            if missing else None)
    return attention_strip(maps, query, scene, width, note)


# ---------------------------------------------------------------- drawing the attention strip

def attention_strip(maps: list[AttentionMap], query: Query, scene: BEVScene, width: int,
                    note: str | None = None) -> np.ndarray:
    """(h, ``width``, 3) BGR uint8: one block per map, side by side, each a zoom on the weights
    (mean over the heads, with a colour bar) and the heads as small multiples; ``note`` a line
    at the bottom."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    note_h = 24 if note else 0
    # A lone block is as wide as the sheet: taller, its small multiples go on two rows, not one.
    height = max(420, round(width * (0.3 if len(maps) > 1 else 0.4))) + note_h
    fig = Figure(figsize=(width / DPI, height / DPI), dpi=DPI, facecolor=BG)
    block_w = width / len(maps)
    for i, m in enumerate(maps):
        _draw_block(fig, m, query, scene, (i * block_w, block_w, height - note_h), (width, height))
    if note:
        fig.text(8 / width, 6 / height, note, color=FG, fontsize=10, va="bottom")
    canvas = FigureCanvasAgg(fig)
    canvas.draw()
    rgb = np.asarray(canvas.buffer_rgba())[..., :3]
    return np.ascontiguousarray(rgb[..., ::-1])


def _axes(fig, rect_px: tuple[float, float, float, float], fig_px: tuple[int, int]):
    """Axes at ``rect_px`` = (left, top, width, height) pixels from the figure's top-left."""
    x, y, w, h = rect_px
    W, H = fig_px
    return fig.add_axes((x / W, 1 - (y + h) / H, w / W, h / H))


def _draw_block(fig, m: AttentionMap, query: Query, scene: BEVScene, block: tuple[float, float, float],
                fig_px: tuple[int, int]) -> None:
    """One module in ``block`` = (left, width, height) pixels: four title lines, the zoom on the
    mean over heads with its colour bar, then small multiples: the whole map with the zoom
    outlined (unless the zoom is the whole map) and each head (if more than one). All share one
    colour scale, so that their weights compare; a square-root scale keeps faint weights visible."""
    from matplotlib.colors import PowerNorm
    from matplotlib.patches import Rectangle

    x0, bw, bh = block
    title_h, bottom, left, bar_w, bar_gap = 90, 44, 52, 12, 80
    extent = zoom_extent(m.attn, m.weights, query.cell)
    r0, r1, c0, c1 = extent
    whole = (0, scene.shape[0], 0, scene.shape[1])
    mean = m.weights.mean(0)
    vmax = max(float(w[r0:r1, c0:c1].max()) for w in [mean, *m.weights])
    norm = PowerNorm(0.5, vmin=0.0, vmax=vmax or 1.0)

    r, c = query.cell
    lines = [f"{m.name}: {m.keys}",
             f"query cell (row {r}, col {c}) at x {query.xy[0]:.1f}, y {query.xy[1]:.1f} m: {query.what}",
             _zoom_text(m, extent, scene),
             "cyan square and ring: the query cell; dashed cyan: its object; GT green, this model's "
             "predictions orange; dots: lidar points"]
    fig.text((x0 + 8) / fig_px[0], 1 - 6 / fig_px[1], "\n".join(lines), color=FG, fontsize=9.5, va="top",
             linespacing=1.45)

    small = [(mean, whole, "whole map, zoom in pink")] if extent != whole else []
    if len(m.weights) > 1:
        mass = shown_mass(m.weights, extent)
        small += [(w, extent, f"head {k}: {mass[k]:.0%} in view") for k, w in enumerate(m.weights)]
    bar_space = 8 + bar_w + bar_gap
    side, grid = _split_block(bw - left - bar_space - 10, bh - title_h - bottom, len(small))

    ax = _axes(fig, (x0 + left, title_h, side, side), fig_px)
    image = _draw_map(ax, mean, extent, query, scene, norm)
    ax.set_xlabel("x [m]", color=FG)
    ax.set_ylabel("y [m]", color=FG)
    cax = _axes(fig, (x0 + left + side + 8, title_h, bar_w, side), fig_px)
    bar = fig.colorbar(image, cax=cax)
    bar.set_label("weight per cell (sqrt scale)", color=FG)
    bar.ax.tick_params(colors=FG, labelsize=8)

    for (w, ext, title), (top, lft, s) in zip(small, grid):
        ax = _axes(fig, (x0 + left + bar_space + lft, title_h + top, s, s), fig_px)
        _draw_map(ax, w, ext, query, scene, norm, small=True)
        ax.set_title(title, color=FG, fontsize=8, pad=3)
        if ext != extent:
            xa, xb, ya, yb = scene.metres(extent)
            ax.add_patch(Rectangle((xa, ya), xb - xa, yb - ya, fill=False, edgecolor=ZOOM_RGB, linewidth=1.5))


def _split_block(width: float, height: float, n: int) -> tuple[float, list[tuple[float, float, float]]]:
    """Side of the main square panel and the places (top, left, side) of ``n`` small squares to
    its right, in pixels from the area's top-left, in a ``width`` x ``height`` area. The main panel
    shrinks from ``height`` until the small ones, on their best grid, are about as tall: neither
    then leaves an empty band beside the other."""
    if n == 0:
        return min(width, height), []
    title, gap = 16, 8
    for main in range(int(min(width, height)), int(0.55 * height), -2):
        w = width - main
        rows = max(range(1, n + 1), key=lambda k: min(w / math.ceil(n / k), height / k - title))
        cols = math.ceil(n / rows)
        side = min(w / cols, height / rows - title) - gap
        if rows * (side + title + gap) >= 0.9 * main:
            break
    # Centre the grid in what is left, so that the spare width falls on both sides of it.
    x0 = main + (width - main - cols * (side + gap)) / 2
    grid = [(i * (side + title + gap) + title, x0 + j * (side + gap), side) for i, j in
            (divmod(k, cols) for k in range(n))]
    return main, grid


def _zoom_text(m: AttentionMap, extent, scene: BEVScene) -> str:
    """What the zoom covers, for the title."""
    r0, r1, c0, c1 = extent
    dx, dy = scene.cell_size
    heads = f"mean of {len(m.weights)} heads"
    size = f"{r1 - r0} x {c1 - c0} cells ({(c1 - c0) * dx:.1f} x {(r1 - r0) * dy:.1f} m)"
    if m.attn.mode == "window":
        return f"window attention: the query's window, {size}, all it attends to; {heads}"
    keys = f"keys pooled by {m.attn.pool_stride}, " if m.attn.mode == "pooled" and m.attn.pool_stride > 1 else ""
    return (f"{m.attn.mode} attention ({keys}global): zoom on {size} holding >= {MASS:.0%} of each head's "
            f"weight; {heads}")


def _draw_map(ax, w: np.ndarray, extent, query: Query, scene: BEVScene, norm, small: bool = False):
    """Weights ``w`` (H, W) over the cells ``extent`` in metres (x right, y up: row 0 at the
    bottom), the lidar points and the boxes faint over them, the query cell and box marked."""
    from matplotlib import patches as mpatches

    r0, r1, c0, c1 = extent
    x0, x1, y0, y1 = scene.metres(extent)
    ax.set_facecolor(BG)
    image = ax.imshow(w[r0:r1, c0:c1], origin="lower", extent=(x0, x1, y0, y1), cmap="inferno", norm=norm,
                      interpolation="nearest")
    p = scene.points
    inside = (p[:, 0] >= x0) & (p[:, 0] < x1) & (p[:, 1] >= y0) & (p[:, 1] < y1)
    # Dots thinner as the view widens, so the dense rings near the ego do not turn into a blot.
    dot = min(1.5, 40.0 / (x1 - x0)) * (0.4 if small else 1.0)
    ax.scatter(p[inside, 0], p[inside, 1], s=dot, c="white", alpha=0.3, linewidths=0)
    for boxes, color in ((scene.gt_boxes, GT_RGB), (scene.pred_boxes, PRED_RGB)):
        for corners in _footprints(boxes):
            ax.add_patch(mpatches.Polygon(corners, closed=True, fill=False, edgecolor=color, alpha=0.6,
                                          linewidth=0.8 if small else 1.2))
    if query.box is not None:
        ax.add_patch(mpatches.Polygon(_footprints(query.box[None])[0], closed=True, fill=False,
                                      edgecolor=QUERY_RGB, linewidth=1.0 if small else 1.8, linestyle="--"))
    (dx, dy), (r, c) = scene.cell_size, query.cell
    qx, qy = scene.pc_range[0] + c * dx, scene.pc_range[1] + r * dy             # the cell's lower-left corner
    ax.add_patch(mpatches.Rectangle((qx, qy), dx, dy, fill=False, edgecolor=QUERY_RGB, linewidth=1.2 if small else 2.0))
    # A ring of fixed screen size finds the cell when the view is wide and the cell a few pixels.
    ax.scatter([qx + dx / 2], [qy + dy / 2], s=90 if small else 260, facecolors="none", edgecolors=[QUERY_RGB],
               linewidths=1.0 if small else 1.5)
    ax.set_xlim(x0, x1)
    ax.set_ylim(y0, y1)
    ax.set_aspect("equal")
    ax.tick_params(colors=FG, labelsize=8)
    if small:
        ax.set_xticks([])
        ax.set_yticks([])
    for spine in ax.spines.values():
        spine.set_color("0.5")
    return image


def _footprints(boxes: np.ndarray) -> np.ndarray:
    """(n, 4, 2) BEV corners (x, y) of boxes (n, 7+) x, y, z, l, w, h, yaw, lidar frame."""
    from clfbev.ops.boxes import boxes_bev_corners
    if len(boxes) == 0:
        return np.zeros((0, 4, 2))
    return boxes_bev_corners(torch.as_tensor(np.asarray(boxes[:, :7], np.float64))).numpy()


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
    parts = (("train/loss", "-"), ("train/loss_cls", ":"), ("train/loss_reg", "--"), ("train/loss_dir", "-."),
             ("train/loss_depth", (0, (1, 3))))
    for key, style in (p for p in parts if any(p[0] in r for r in train)):
        y, x = np.array([r.get(key, np.nan) for r in train]), steps
        k = max(1, len(y) // 50)
        if k > 1:    # a trailing running mean makes the trend readable; raw values are in the JSONL
            y, x = np.convolve(y, np.ones(k) / k, mode="valid"), steps[k - 1:]
        ax.plot(x, y, linestyle=style, label=key.split("/")[1])
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
