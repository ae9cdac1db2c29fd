"""The attention picture of `clfbev show --attention`: which query cell, which zoom, what weights
are drawn, the strip's layout, and the command end to end on a randomly initialised model.

A micro config (the tiny preset, narrower) keeps a forward pass well under a second; the query,
zoom and layout logic does not depend on the model's size.
"""
from __future__ import annotations

import dataclasses
import json
import math

import cv2
import numpy as np
import pytest
import torch

from clfbev.anchors import make_anchors
from clfbev.attention import BEVAttention
from clfbev.config import tiny
from clfbev.data import Batch
from clfbev.errors import EXIT_BAD_INPUT, ConfigError
from clfbev.head import Detections
from clfbev.model import CLFusionBEV
from clfbev.run import cli
from clfbev.run.attention_plot import _split_block, attention_strip
from clfbev.run.attention_query import (MASS, MIN_ZOOM_CELLS, AttentionMap, BEVScene, Query, attention_maps, cell_of,
                                        choose_query, shown_mass, zoom_extent)
from clfbev.run.checkpoint import save_checkpoint

pytestmark = pytest.mark.usefixtures("one_thread")

CFG = tiny()
MICRO = dataclasses.replace(CFG, image_size=(64, 176), cam_width=8, fpn_ch=32, context_ch=16, vfe_ch=16,
                            fusion_dim=32, attn_heads=2, bev_channels=(16, 32), bev_blocks=1, bev_up_ch=16)
CLASSES = CFG.class_names


def _dets(boxes: list[list[float]], scores: list[float], labels: list[int]) -> Detections:
    b = torch.zeros(len(boxes), 9)
    if boxes:
        b[:, :7] = torch.tensor(boxes)
    return Detections(b, torch.tensor(scores), torch.tensor(labels, dtype=torch.int64))


NO_DETS = _dets([], [], [])
NO_GT = (torch.zeros(0, 9), torch.zeros(0, dtype=torch.int64))


# ---------------------------------------------------------------- the query cell

@pytest.mark.parametrize("cell", [(40, 13), (0, 0), (127, 127), (63, 64)])
def test_query_lands_on_the_best_detections_centre_cell(cell):
    """The best detection's centre, anywhere inside a cell, picks that cell: the one whose
    anchors the model centres there (the head's own grid, not a second convention)."""
    anchors = make_anchors(CLASSES, CFG.head_feature_size, CFG.pc_range)     # (ny, nx, cls, rot, 7)
    cx, cy = (float(v) for v in anchors[cell][0, 0, :2])
    half = 0.5 * (CFG.pc_range[3] - CFG.pc_range[0]) / CFG.head_feature_size[1]
    xy = (cx + 0.9 * half, cy - 0.9 * half)                                    # near the cell's corner
    dets = _dets([[xy[0], xy[1], 0, 4, 2, 1.5, 0.3], [-20, 30, 0, 4, 2, 1.5, 0]], [0.9, 0.4], [0, 1])
    dets = Detections(dets.boxes.flip(0), dets.scores.flip(0), dets.labels.flip(0))   # best one second
    q = choose_query(dets, *NO_GT, CLASSES, CFG.pc_range, CFG.head_feature_size)
    assert q.cell == cell
    assert q.xy == pytest.approx(xy, abs=1e-5)
    assert f"{CLASSES[0]}, score 0.90, {math.hypot(*xy):.1f} m away" in q.what
    assert q.box[:2] == pytest.approx(xy, abs=1e-5)


def test_without_detection_the_query_is_the_gt_box_nearest_the_ego():
    gt = torch.zeros(3, 9)
    gt[:, :2] = torch.tensor([[20.0, 0.0], [-3.0, 4.0], [0.0, -30.0]])
    q = choose_query(NO_DETS, gt, torch.tensor([0, 3, 1]), CLASSES, CFG.pc_range, CFG.head_feature_size)
    assert q.xy == (-3.0, 4.0)
    # 0.8 m cells from -51.2 m: row floor(55.2 / 0.8) = 69, column floor(48.2 / 0.8) = 60.
    assert q.cell == cell_of((-3.0, 4.0), CFG.pc_range, CFG.head_feature_size) == (69, 60)
    assert q.what == f"no detection: the GT {CLASSES[3]} nearest the ego, 5.0 m away"


def test_a_query_point_off_the_map_or_nothing_to_query_is_refused():
    with pytest.raises(ConfigError, match="outside the BEV map"):
        cell_of((51.2, 0.0), CFG.pc_range, CFG.head_feature_size)      # the range is half-open
    assert cell_of((51.19, -51.2), CFG.pc_range, CFG.head_feature_size) == (0, 127)
    with pytest.raises(ConfigError, match="--cell"):
        choose_query(NO_DETS, *NO_GT, CLASSES, CFG.pc_range, CFG.head_feature_size)
    q = choose_query(NO_DETS, *NO_GT, CLASSES, CFG.pc_range, CFG.head_feature_size, xy=(10.0, 5.0))
    assert q.cell == (70, 76) and q.box is None        # floor(56.2 / 0.8), floor(61.2 / 0.8)


# ---------------------------------------------------------------- the zoom

def _window_weights(H, W, window, cell, heads=3, seed=0):
    g = torch.Generator().manual_seed(seed)
    attn = BEVAttention(heads, "window", window=window)
    q, k = torch.randn(1, H, W, 4 * heads, generator=g), torch.randn(1, H, W, 4 * heads, generator=g)
    return attn, attn.query_attention_map(q, k, cell)[0].numpy()               # (heads, H, W)


@pytest.mark.parametrize("H,W,window,cell", [
    (16, 16, 8, (9, 3)),       # an inner tile
    (10, 7, 4, (9, 6)),        # the corner tile, cut by the padding at the bottom / right edge
    (10, 7, 4, (0, 5)),        # a tile cut on the right only
    (6, 5, 16, (2, 2)),        # a window larger than the grid is the whole grid
])
def test_window_zoom_is_exactly_the_window_the_query_attends_to(H, W, window, cell):
    attn, w = _window_weights(H, W, window, cell)
    rows, cols = np.nonzero((w > 0).any(0))
    assert zoom_extent(attn, w, cell) == (rows.min(), rows.max() + 1, cols.min(), cols.max() + 1)
    assert (w > 0).all(axis=0)[rows.min():rows.max() + 1, cols.min():cols.max() + 1].all()   # a full box


@pytest.mark.parametrize("H,W,window,cell", [(16, 16, 8, (9, 3)), (10, 7, 4, (9, 6))])
def test_window_weights_shown_sum_to_one_per_head(H, W, window, cell):
    attn, w = _window_weights(H, W, window, cell)
    extent = zoom_extent(attn, w, cell)
    assert shown_mass(w, extent) == pytest.approx(np.ones(len(w)), abs=1e-5)
    r0, r1, c0, c1 = extent
    assert w[:, r0:r1, c0:c1].sum(axis=(1, 2)) == pytest.approx(np.ones(len(w)), abs=1e-5)


def test_global_zoom_holds_the_mass_of_every_head_and_the_query():
    """exact / pooled: two heads peaked at different places; the zoom spans both peaks and the
    query, padded, and is well inside the map; each head keeps >= MASS of its weight in it."""
    H = W = 40
    w = np.full((2, H, W), 0.02 / (H * W - 1))
    w[0, 10, 12] = w[1, 18, 20] = 0.98
    w /= w.sum(axis=(1, 2), keepdims=True)
    for mode in ("exact", "pooled"):
        extent = zoom_extent(BEVAttention(2, mode), w, (14, 25))
        assert extent == (9, 20, 11, 27)                     # rows 10..18 and 14, cols 12..25, +1 each side
        assert (shown_mass(w, extent) >= MASS).all()


def test_a_peaked_zoom_at_the_map_corner_keeps_its_minimum_size():
    w = np.zeros((1, 30, 30))
    w[0, 0, 29] = 1.0
    r0, r1, c0, c1 = zoom_extent(BEVAttention(1, "exact"), w, (0, 29))
    assert (r0, r1, c0, c1) == (0, MIN_ZOOM_CELLS, 30 - MIN_ZOOM_CELLS, 30)


def test_diffuse_weights_zoom_out_to_the_whole_map():
    w = np.full((2, 12, 9), 1 / (12 * 9))
    assert zoom_extent(BEVAttention(2, "pooled"), w, (3, 3)) == (0, 12, 0, 9)


# ---------------------------------------------------------------- the model's maps

def _batch(seed=0) -> Batch:
    """One synthetic sample for MICRO: points ahead and around, 6 grey images."""
    g = torch.Generator().manual_seed(seed)
    n, (h, w) = 4000, MICRO.image_size
    pts = torch.cat([(torch.rand(n, 2, generator=g) - 0.5) * 80, torch.rand(n, 1, generator=g) * 3 - 2,
                     torch.rand(n, 1, generator=g), torch.zeros(n, 1)], 1)
    K = torch.tensor([[100.0, 0, w / 2], [0, 100.0, h / 2], [0, 0, 1]])
    cam_to_lidar = torch.tensor([[0.0, 0, 1, 0], [-1, 0, 0, 0], [0, -1, 0, 1.5], [0, 0, 0, 1]])  # looking +x
    return Batch(images=torch.randn(1, 6, 3, h, w, generator=g) * 0.1, intrinsics=K.expand(1, 6, 3, 3),
                 T_lidar_from_cam=cam_to_lidar.expand(1, 6, 4, 4), img_aug=torch.eye(3).expand(1, 6, 3, 3),
                 points=[pts], gt_boxes=[torch.zeros(0, 9)], gt_labels=[torch.zeros(0, dtype=torch.int64)],
                 T_global_from_lidar=torch.eye(4, dtype=torch.float64)[None])


def test_model_maps_are_per_head_distributions_over_the_bev():
    torch.manual_seed(0)
    model = CLFusionBEV(MICRO, "full")
    maps = attention_maps(model, _batch(), (21, 40))
    assert [m.name for m in maps] == ["MCM", "BSM"]
    assert maps[0].attn is model.mcm.attn and maps[1].attn is model.bsm.attn
    for m in maps:
        assert m.weights.shape == (MICRO.attn_heads, *MICRO.head_feature_size)
        assert m.weights.sum(axis=(1, 2)) == pytest.approx(np.ones(MICRO.attn_heads), abs=1e-5)
        extent = zoom_extent(m.attn, m.weights, (21, 40))
        assert extent == (16, 24, 40, 48)                    # the query's 8 x 8 window
        assert shown_mass(m.weights, extent) == pytest.approx(np.ones(MICRO.attn_heads), abs=1e-5)
    assert [m.name for m in attention_maps(CLFusionBEV(MICRO, "mcm"), _batch(), (0, 0))] == ["MCM"]
    with pytest.raises(ConfigError, match="variant 'concat' has no attention"):
        attention_maps(CLFusionBEV(MICRO, "concat"), _batch(), (0, 0))


# ---------------------------------------------------------------- the strip

def _fake_map(name, seed, heads=2):
    rng = np.random.default_rng(seed)
    w = rng.random((heads, *CFG.head_feature_size)) ** 8
    return AttentionMap(name, "a query over a key map", w / w.sum(axis=(1, 2), keepdims=True),
                        BEVAttention(heads, "window", window=8))


def _scene():
    rng = np.random.default_rng(1)
    boxes = np.array([[3.0, 4.0, 0, 4, 2, 1.5, 0.4, 0, 0]])
    return BEVScene(rng.uniform(-50, 50, (2000, 5)), boxes, boxes + [1, 0, 0, 0, 0, 0, 0, 0, 0],
                    CFG.pc_range, CFG.head_feature_size)


def _inked(img: np.ndarray) -> float:
    """Share of the image's pixels that are not the strip's plain background."""
    return float((np.abs(img.astype(int) - 20).max(-1) > 12).mean())


@pytest.mark.parametrize("width,height,n", [(838, 460, 5), (838, 460, 4), (1828, 680, 5), (1828, 680, 9),
                                            (500, 300, 1), (838, 460, 0)])
def test_block_layout_keeps_every_panel_inside_and_apart(width, height, n):
    main, grid = _split_block(width, height, n)
    assert len(grid) == n and 0.5 * min(width, height) <= main <= min(width, height)
    rects = [(0, 0, main, main)] + [(left, top - 16, side, side + 16) for top, left, side in grid]   # with titles
    for i, (x, y, w, h) in enumerate(rects):
        assert x >= 0 and y >= 0 and x + w <= width + 1e-6 and y + h <= height + 1e-6 and w > 50
        for x2, y2, w2, h2 in rects[i + 1:]:
            assert x + w <= x2 or x2 + w2 <= x or y + h <= y2 or y2 + h2 <= y        # no overlap


def test_strip_puts_the_modules_side_by_side_leaving_no_half_empty():
    query = Query((3.0, 4.0), cell_of((3.0, 4.0), CFG.pc_range, CFG.head_feature_size), "predicted car")
    strip = attention_strip([_fake_map("MCM", 0), _fake_map("BSM", 1)], query, _scene(), 1600)
    assert strip.shape[1] == 1600 and strip.shape[2] == 3 and strip.dtype == np.uint8
    half = strip.shape[1] // 2
    assert _inked(strip[:, :half]) > 0.3 and _inked(strip[:, half:]) > 0.3

    lone = attention_strip([_fake_map("MCM", 0)], query, _scene(), 1600, note="no BSM in this variant")
    assert lone.shape[1] == 1600
    assert _inked(lone[:, :half]) > 0.3 and _inked(lone[:, half:]) > 0.2


# ---------------------------------------------------------------- the command

@pytest.fixture(scope="module")
def micro_ckpts(tmp_path_factory):
    """Randomly initialised MICRO checkpoints of the variants 'full' and 'concat'."""
    out = tmp_path_factory.mktemp("ckpt")
    paths = {}
    for variant in ("full", "concat"):
        torch.manual_seed(0)
        model = CLFusionBEV(MICRO, variant)
        paths[variant] = save_checkpoint(out / f"{variant}.pt", {"model": model.state_dict(),
                                         "config": MICRO.to_dict(), "variant": variant, "step": 0, "epoch": 0})
    return paths


@pytest.fixture(scope="module")
def empty_results(tiny_dataset, tmp_path_factory):
    """A results file with no box for every sample: the query falls back to the nearest GT."""
    samples = json.loads((tiny_dataset / "v1.0-sim" / "sample.json").read_text())
    path = tmp_path_factory.mktemp("res") / "results.json"
    path.write_text(json.dumps({"meta": {}, "results": {s["token"]: [] for s in samples}}))
    return path


def test_show_attention_appends_the_strip_below_the_sheet(tiny_dataset, micro_ckpts, empty_results, tmp_path,
                                                          capsys):
    common = ["show", "--data", str(tiny_dataset), "--results", str(empty_results), "--sample", "1"]
    assert cli.main([*common, "--out", str(tmp_path / "plain.png")]) == 0
    assert cli.main([*common, "--out", str(tmp_path / "att.png"), "--attention", "--ckpt",
                     str(micro_ckpts["full"])]) == 0
    assert f"wrote {tmp_path / 'att.png'}" in capsys.readouterr().out
    plain, att = cv2.imread(str(tmp_path / "plain.png")), cv2.imread(str(tmp_path / "att.png"))
    assert att.shape[1] == plain.shape[1] and att.shape[0] > plain.shape[0] + 400
    assert np.array_equal(att[: plain.shape[0]], plain)             # the sheet itself is unchanged
    assert _inked(att[plain.shape[0]:, att.shape[1] // 2:]) > 0.3     # BSM fills the right half


def test_show_attention_of_a_variant_without_attention_exits_2_in_one_line(tiny_dataset, micro_ckpts,
                                                                          empty_results, tmp_path, capsys):
    out = tmp_path / "s.png"
    rc = cli.main(["show", "--data", str(tiny_dataset), "--results", str(empty_results), "--out", str(out),
                   "--attention", "--ckpt", str(micro_ckpts["concat"])])
    err = capsys.readouterr().err
    assert rc == EXIT_BAD_INPUT and not out.exists()
    assert err.count("\n") == 1 and "variant 'concat', which has no MCM or BSM" in err
    assert cli.main(["show", "--data", str(tiny_dataset), "--results", str(empty_results), "--out", str(out),
                     "--attention"]) == EXIT_BAD_INPUT
    assert "--attention needs --ckpt" in capsys.readouterr().err
    with pytest.raises(SystemExit) as e:
        cli.main(["show", "--data", str(tiny_dataset), "--results", str(empty_results), "--out", str(out),
                  "--cell", "ten,5"])
    assert e.value.code == 2 and "expected X,Y in metres" in capsys.readouterr().err
