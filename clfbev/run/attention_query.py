"""The attention of one BEV query cell, as the paper's Fig. 6 draws it: which cell (under the
model's own best detection, else the GT box nearest the ego, or a point given), the weights each
attention module gives it, and the cells a panel zooms on (window mode: the query's window;
exact / pooled: the cells holding most of the weight).

Frames: a BEV map is (H, W) = (ny, nx) over ``cfg.pc_range``, rows along +y and columns along
+x of the key-frame lidar frame; cell (r, c) is centred at x = xmin + (c + 0.5) dx,
y = ymin + (r + 0.5) dy, as the anchors are.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from clfbev.errors import ConfigError

MASS = 0.95            # exact / pooled: the zoom holds at least this share of each head's weight
ZOOM_PAD_CELLS = 1     # exact / pooled: a margin around those cells
MIN_ZOOM_CELLS = 8     # exact / pooled: a peaked map is still shown with some context


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
    """(row, col) of the BEV cell holding lidar-frame point ``xy``; ConfigError outside the map."""
    xmin, ymin, _, xmax, ymax, _ = pc_range
    ny, nx = bev_shape
    if not (xmin <= xy[0] < xmax and ymin <= xy[1] < ymax):
        raise ConfigError(f"query point ({xy[0]:g}, {xy[1]:g}) m lies outside the BEV map "
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
        raise ConfigError("no detection and no GT box in this sample to put the query on; give one with --cell X,Y")
    if box is not None:
        box = box.detach().cpu().numpy()
        xy = (float(box[0]), float(box[1]))
        what += f", {math.hypot(*xy):.1f} m away"
    return Query(xy, cell_of(xy, pc_range, bev_shape), what, box)


@torch.no_grad()
def attention_maps(model, batch, cell: tuple[int, int]) -> list[AttentionMap]:
    """The attention of BEV query ``cell`` (row, col) of sample 0 of ``batch``, per head, for
    each module the model has: MCM (lidar query over the camera BEV), then BSM (fused query over
    the fused BEV), from the inputs the model's own forward gave each module."""
    if not attention_modules(model):
        raise ConfigError(f"variant '{model.variant}' has no attention module (MCM: 'mcm', 'full'; BSM: 'full')")
    model.eval()
    inputs = model(batch).attention
    maps = []
    if model.mcm is not None:
        w = model.mcm.attention_map(inputs.mcm_lidar, inputs.mcm_camera, cell)        # (B, heads, H, W)
        maps.append(AttentionMap("MCM", "lidar BEV query over the camera BEV", w[0].cpu().numpy(), model.mcm.attn))
    if model.bsm is not None:
        w = model.bsm.attention_map(inputs.bsm, cell)
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
