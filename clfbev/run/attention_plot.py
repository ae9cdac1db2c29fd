"""The attention strip below ``clfbev show``'s sheet: one block per attention module, side by
side, each a zoom on the query's weights (the mean over heads, with a colour bar) and the heads
as small multiples, in metres in the lidar frame (x right, y up, as the sheet's BEV panel).
"""

from __future__ import annotations

import math

import numpy as np
import torch

from clfbev.run.attention_query import (MASS, AttentionMap, BEVScene, Query, attention_maps, choose_query,
                                        shown_mass, zoom_extent)

DPI = 100
BG, FG = (20 / 255,) * 3, "white"
GT_RGB, PRED_RGB = (60 / 255, 200 / 255, 60 / 255), (1.0, 140 / 255, 0.0)    # the sheet's GT_COLOR, PRED_COLOR
QUERY_RGB, ZOOM_RGB = (0.0, 1.0, 1.0), (1.0, 0.2, 0.6)


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