"""Tests for clfbev.ops.boxes: coder round trip, rotated BEV IoU against shapely, rotated NMS
against a pure-Python greedy reference."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from shapely.geometry import Polygon

from clfbev.ops.boxes import (
    points_in_boxes,
    bev_iou,
    bev_iou_aligned,
    boxes_bev_corners,
    decode_boxes,
    encode_boxes,
    limit_period,
    rotated_nms,
)

def assert_close(actual: torch.Tensor, expected: torch.Tensor, atol: float = 1e-6, rtol: float = 1e-6) -> None:
    """numpy's assert_allclose on tensors: torch.testing.assert_close costs ~2 s of imports on
    its first call, a large share of this file's budget."""
    assert actual.shape == expected.shape
    np.testing.assert_allclose(actual.detach().cpu().double().numpy(), expected.detach().cpu().double().numpy(), atol=atol, rtol=rtol)


# ----------------------------------------------------------------------------------------------
# Independent numpy / shapely references
# ----------------------------------------------------------------------------------------------


def corners_np(box: np.ndarray) -> np.ndarray:
    """(7,) box -> (4, 2) BEV corners, counter-clockwise, written independently of the torch
    code: rotate the local rectangle with an explicit rotation matrix."""
    x, y, _, l, w, _, yaw = box[:7]
    local = np.array([[l / 2, w / 2], [-l / 2, w / 2], [-l / 2, -w / 2], [l / 2, -w / 2]])
    rot = np.array([[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]])
    return local @ rot.T + np.array([x, y])


def shapely_iou(a: np.ndarray, b: np.ndarray) -> float:
    pa, pb = Polygon(corners_np(a)), Polygon(corners_np(b))
    inter = pa.intersection(pb).area
    union = pa.area + pb.area - inter
    return inter / union


def greedy_nms_reference(boxes: np.ndarray, scores: np.ndarray, thr: float) -> list[int]:
    """Textbook greedy NMS: visit boxes by (score desc, index asc), keep one unless it overlaps
    a kept box by (shapely) IoU > thr."""
    polys = [Polygon(corners_np(b)) for b in boxes]

    def iou(i: int, k: int) -> float:
        inter = polys[i].intersection(polys[k]).area
        return inter / (polys[i].area + polys[k].area - inter)

    order = sorted(range(len(scores)), key=lambda i: (-scores[i], i))
    kept: list[int] = []
    for i in order:
        if all(iou(i, k) <= thr for k in kept):
            kept.append(i)
    return kept


def random_boxes(rng: np.random.Generator, n: int, spread: float = 3.0) -> np.ndarray:
    box = np.zeros((n, 7))
    box[:, 0:2] = rng.uniform(-spread, spread, (n, 2))
    box[:, 2] = rng.uniform(-2, 2, n)
    box[:, 3:6] = rng.uniform(0.3, 5.0, (n, 3))
    box[:, 6] = rng.uniform(-math.pi, math.pi, n)
    return box


def iou_case_pairs(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """>= 500 pairs covering rotated, nested, touching, identical, disjoint, axis-aligned
    (collinear edges), nearly parallel, same-centre and far-from-origin cases."""
    a_list, b_list = [], []

    def add(a: np.ndarray, b: np.ndarray) -> None:
        a_list.append(a)
        b_list.append(b)

    # Random rotated, mostly overlapping.
    add(random_boxes(rng, 200), random_boxes(rng, 200))
    # Nested: b strictly inside a (b's circumscribed circle inside a's inscribed one), both ways.
    a = random_boxes(rng, 60)
    a[:, 3:5] = rng.uniform(3.0, 6.0, (60, 2))
    b = a.copy()
    b[:, 3:5] = rng.uniform(0.2, 1.0, (60, 2))
    b[:, 0:2] += rng.uniform(-0.5, 0.5, (60, 2))
    b[:, 6] = rng.uniform(-math.pi, math.pi, 60)
    add(a, b)
    add(b, a)
    # Touching along an edge (same yaw, shifted by half-lengths along the heading, various widths).
    a = random_boxes(rng, 60)
    b = random_boxes(rng, 60)
    b[:, 6] = a[:, 6]
    shift = 0.5 * (a[:, 3] + b[:, 3])
    b[:, 0] = a[:, 0] + shift * np.cos(a[:, 6])
    b[:, 1] = a[:, 1] + shift * np.sin(a[:, 6])
    add(a, b)
    # Touching at a corner (axis aligned).
    a = random_boxes(rng, 20)
    a[:, 6] = 0.0
    b = random_boxes(rng, 20)
    b[:, 6] = 0.0
    b[:, 0] = a[:, 0] + 0.5 * (a[:, 3] + b[:, 3])
    b[:, 1] = a[:, 1] + 0.5 * (a[:, 4] + b[:, 4])
    add(a, b)
    # Identical, including axis-aligned yaws.
    a = random_boxes(rng, 60)
    a[:20, 6] = rng.choice([0.0, math.pi / 2, -math.pi, math.pi], 20)
    add(a, a.copy())
    # Disjoint, far apart.
    a = random_boxes(rng, 40)
    b = random_boxes(rng, 40)
    b[:, 0] += 30.0
    add(a, b)
    # Axis aligned and overlapping: many exactly collinear edges.
    a = random_boxes(rng, 60)
    b = random_boxes(rng, 60)
    a[:, 0:2] = np.round(a[:, 0:2], 1)
    b[:, 0:2] = np.round(b[:, 0:2], 1)
    a[:, 3:5] = np.round(a[:, 3:5], 1)
    b[:, 3:5] = np.round(b[:, 3:5], 1)
    a[:, 6] = rng.choice([0.0, math.pi / 2, math.pi], 60)
    b[:, 6] = rng.choice([0.0, math.pi / 2, -math.pi / 2], 60)
    add(a, b)
    # Half-metre grid, yaw in multiples of pi/4, some nudged by 1e-9: exactly and nearly
    # parallel or collinear edges (an ill-conditioned line-line solve fails here).
    a = random_boxes(rng, 200)
    b = random_boxes(rng, 200)
    for box in (a, b):
        box[:, 0:2] = np.round(box[:, 0:2] * 2) / 2
        box[:, 3:5] = np.round(box[:, 3:5] * 2) / 2 + 0.5
        box[:, 6] = rng.integers(-4, 5, 200) * math.pi / 4
        box[100:, 6] += rng.normal(0, 1e-9, 100)
    add(a, b)
    # Same centre, different yaw: up to 8-vertex intersections.
    a = random_boxes(rng, 40)
    b = random_boxes(rng, 40)
    b[:, 0:2] = a[:, 0:2]
    add(a, b)
    # Far from the origin (float32 cancellation).
    a = random_boxes(rng, 40, spread=1.0)
    b = random_boxes(rng, 40, spread=1.0)
    offset = rng.uniform(-60, 60, (40, 2))
    a[:, 0:2] += offset
    b[:, 0:2] += offset
    add(a, b)
    return np.concatenate(a_list), np.concatenate(b_list)


# ----------------------------------------------------------------------------------------------
# Coder
# ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-10), (torch.float32, 1e-5)])
def test_coder_round_trip(dtype: torch.dtype, tol: float) -> None:
    rng = np.random.default_rng(0)
    gt = torch.tensor(random_boxes(rng, 1000, spread=50.0), dtype=dtype)
    anchors = torch.tensor(random_boxes(rng, 1000, spread=50.0), dtype=dtype)
    decoded = decode_boxes(encode_boxes(gt, anchors), anchors)
    assert_close(decoded, gt, atol=tol, rtol=tol)


def test_coder_known_values_and_extras() -> None:
    anchor = torch.tensor([[1.0, 2.0, -1.0, 4.0, 3.0, 2.0, 0.5]])
    gt = torch.tensor([[6.0, -3.0, 0.0, 8.0, 1.5, 2.0, 0.25, 3.0, -4.0]])  # + vx, vy
    deltas = encode_boxes(gt, anchor)
    expected = torch.tensor([[1.0, -1.0, 0.5, math.log(2.0), math.log(0.5), 0.0, -0.25, 3.0, -4.0]])
    assert_close(deltas, expected)  # d = sqrt(4^2 + 3^2) = 5
    assert_close(decode_boxes(deltas, anchor), gt)
    # Anchors with velocity columns: extras become plain differences.
    anchor_v = torch.cat([anchor, torch.tensor([[1.0, 1.0]])], dim=1)
    assert_close(encode_boxes(gt, anchor_v)[:, 7:], torch.tensor([[2.0, -5.0]]))
    assert_close(decode_boxes(encode_boxes(gt, anchor_v), anchor_v), gt)
    # Encoding an anchor against itself gives zero residuals.
    assert torch.equal(encode_boxes(anchor, anchor), torch.zeros(1, 7))


def test_coder_broadcasts_over_batch() -> None:
    rng = np.random.default_rng(1)
    anchors = torch.tensor(random_boxes(rng, 50))
    deltas = torch.randn(3, 50, 9, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    boxes = decode_boxes(deltas, anchors)
    assert boxes.shape == (3, 50, 9)
    assert_close(encode_boxes(boxes, anchors), deltas)


def test_limit_period() -> None:
    angle = torch.linspace(-10, 10, 1001, dtype=torch.float64)
    wrapped = limit_period(angle)
    assert wrapped.min() >= -math.pi / 2 and wrapped.max() < math.pi / 2
    k = (angle - wrapped) / math.pi
    assert_close(k, k.round())  # differs by whole periods
    wrapped01 = limit_period(angle, offset=0.0, period=2 * math.pi)
    # <= : an angle a hair below 0 wraps to exactly 2 pi in floating point.
    assert wrapped01.min() >= 0 and wrapped01.max() <= 2 * math.pi


# ----------------------------------------------------------------------------------------------
# BEV corners and IoU
# ----------------------------------------------------------------------------------------------


def test_bev_corners_match_reference() -> None:
    boxes = random_boxes(np.random.default_rng(2), 100)
    corners = boxes_bev_corners(torch.tensor(boxes)).numpy()
    np.testing.assert_allclose(corners, np.stack([corners_np(b) for b in boxes]), atol=1e-12)
    # Counter-clockwise: positive signed (shoelace) area equal to l * w.
    x, y = corners[..., 0], corners[..., 1]
    signed = 0.5 * (x * np.roll(y, -1, 1) - np.roll(x, -1, 1) * y).sum(1)
    np.testing.assert_allclose(signed, boxes[:, 3] * boxes[:, 4], rtol=1e-12)


@pytest.fixture(scope="module")
def case_pairs() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The case pairs and their shapely IoU, computed once for both dtypes."""
    a, b = iou_case_pairs(np.random.default_rng(3))
    return a, b, np.array([shapely_iou(x, y) for x, y in zip(a, b)])


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_bev_iou_matches_shapely_pairs(dtype: torch.dtype, case_pairs) -> None:
    a, b, expected = case_pairs
    assert len(a) >= 500
    ta, tb = torch.tensor(a, dtype=dtype), torch.tensor(b, dtype=dtype)
    np.testing.assert_allclose(bev_iou_aligned(ta, tb).double().numpy(), expected, atol=1e-4, rtol=0)
    # The all-pairs path must agree with the aligned path on the diagonal (for every case kind).
    rows = np.arange(0, len(a), 7)
    diag = torch.diagonal(bev_iou(ta[rows], tb[rows])).double().numpy()
    np.testing.assert_allclose(diag, expected[rows], atol=1e-4, rtol=0)


def test_bev_iou_matrix_matches_shapely() -> None:
    rng = np.random.default_rng(4)
    a, b = random_boxes(rng, 40, spread=6.0), random_boxes(rng, 30, spread=6.0)
    expected = np.array([[shapely_iou(x, y) for y in b] for x in a])
    iou = bev_iou(torch.tensor(a), torch.tensor(b)).numpy()
    assert iou.shape == (40, 30)
    np.testing.assert_allclose(iou, expected, atol=1e-4, rtol=0)
    assert (expected > 0).sum() > 50 and (expected == 0).sum() > 50  # both regimes exercised


def test_bev_iou_self_and_symmetry() -> None:
    boxes = torch.tensor(random_boxes(np.random.default_rng(5), 100))
    iou = bev_iou(boxes, boxes)
    assert_close(torch.diagonal(iou), torch.ones(100, dtype=iou.dtype), atol=1e-9, rtol=0)
    assert_close(iou, iou.T, atol=1e-9, rtol=0)
    assert iou.min() >= 0 and iou.max() <= 1 + 1e-9
    # The IoU ignores z and h (BEV) and is invariant to yaw + pi (same rectangle).
    moved = boxes.clone()
    moved[:, 2] += 5.0
    moved[:, 5] *= 2.0
    moved[:, 6] += math.pi
    assert_close(torch.diagonal(bev_iou(boxes, moved)), torch.ones(100, dtype=iou.dtype), atol=1e-9, rtol=0)


def test_bev_iou_empty_and_large() -> None:
    assert bev_iou(torch.zeros(0, 7), torch.zeros(5, 7)).shape == (0, 5)
    assert bev_iou(torch.zeros(5, 7), torch.zeros(0, 7)).shape == (5, 0)
    # Anchor-assignment scale: 20000 anchors on a grid x 50 GT; checked on a sample of rows.
    rng = np.random.default_rng(6)
    gx, gy = np.meshgrid(np.linspace(-50, 50, 100), np.linspace(-50, 50, 100))
    anchors = np.zeros((100, 100, 2, 7))
    anchors[..., 0], anchors[..., 1] = gx[..., None], gy[..., None]
    anchors[..., 3:6] = [4.5, 1.9, 1.6]
    anchors[..., 1, 6] = math.pi / 2
    anchors = anchors.reshape(-1, 7)
    gt = random_boxes(rng, 50, spread=50.0)
    iou = bev_iou(torch.tensor(anchors, dtype=torch.float32), torch.tensor(gt, dtype=torch.float32))
    assert iou.shape == (20000, 50)
    best = iou.argmax(dim=0).numpy()  # best anchor per GT: all should overlap their GT
    rows = np.concatenate([best, rng.choice(20000, 30, replace=False)])
    expected = np.array([[shapely_iou(anchors[r], g) for g in gt] for r in rows])
    np.testing.assert_allclose(iou[rows].double().numpy(), expected, atol=1e-4, rtol=0)
    assert (expected[:50].max(axis=1) > 0).all()


# ----------------------------------------------------------------------------------------------
# NMS
# ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("thr", [0.05, 0.2, 0.5])
def test_rotated_nms_matches_greedy_reference(thr: float) -> None:
    rng = np.random.default_rng(7)
    boxes = random_boxes(rng, 100, spread=6.0)
    scores = rng.uniform(0, 1, 100).round(2)  # rounding creates ties: checks the tie-break
    expected = greedy_nms_reference(boxes, scores, thr)
    kept = rotated_nms(torch.tensor(boxes), torch.tensor(scores), thr)
    assert kept.dtype == torch.long
    assert kept.tolist() == expected
    # max_out truncates the same greedy sequence; float32 input gives the same result.
    kept_f32 = rotated_nms(torch.tensor(boxes, dtype=torch.float32), torch.tensor(scores, dtype=torch.float32), thr, max_out=5)
    assert kept_f32.tolist() == expected[:5]


def test_rotated_nms_edge_cases() -> None:
    assert rotated_nms(torch.zeros(0, 7), torch.zeros(0), 0.5).shape == (0,)
    box = torch.tensor([[0.0, 0.0, 0.0, 4.0, 2.0, 1.5, 0.3]])
    boxes = box.repeat(4, 1)
    boxes[3, 0] = 20.0  # far away, survives
    scores = torch.tensor([0.5, 0.9, 0.9, 0.1])
    # Equal scores: the lower index wins; identical boxes are suppressed.
    assert rotated_nms(boxes, scores, 0.5).tolist() == [1, 3]
    # pre_max drops the lowest-scoring box before NMS.
    assert rotated_nms(boxes, scores, 0.5, pre_max=3).tolist() == [1]


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_matches_cpu() -> None:
    rng = np.random.default_rng(8)
    a, b = iou_case_pairs(rng)
    ta, tb = torch.tensor(a), torch.tensor(b)
    cpu = bev_iou_aligned(ta, tb)
    gpu = bev_iou_aligned(ta.to("cuda"), tb.to("cuda"))
    assert gpu.device.type == "cuda"
    assert_close(gpu.cpu(), cpu, atol=1e-9, rtol=0)
    scores = torch.tensor(rng.uniform(0, 1, len(a)))
    kept_gpu = rotated_nms(ta.to("cuda"), scores.to("cuda"), 0.3)
    assert kept_gpu.device.type == "cuda"
    assert kept_gpu.cpu().tolist() == rotated_nms(ta, scores, 0.3).tolist()


def test_points_in_boxes_rotated_faces_included_numpy_and_torch_alike():
    box = np.array([[1.0, 2.0, 0.0, 4.0, 2.0, 2.0, np.pi / 2]])           # length along y after the rotation
    pts = np.array([[1.0, 3.9, 0.0], [1.0, 4.1, 0.0], [1.9, 2.0, 0.5], [2.1, 2.0, 0.0], [1.0, 2.0, 1.1],
                    [1.0, 2.0, 1.0]])                                    # the last on the top face
    expected = [[True], [False], [True], [False], [False], [True]]
    np.testing.assert_array_equal(points_in_boxes(pts, box), expected)
    assert points_in_boxes(torch.from_numpy(pts), torch.from_numpy(box)).tolist() == expected
    grown = points_in_boxes(pts, box, pad=0.2)[:, 0]
    np.testing.assert_array_equal(grown, [True, True, True, True, True, True])
    # Many random boxes: the two array types give the same answer, point by point.
    g = np.random.default_rng(0)
    boxes = np.concatenate([g.uniform(-5, 5, (40, 3)), g.uniform(0.3, 4, (40, 3)), g.uniform(-4, 4, (40, 1))], 1)
    points = g.uniform(-7, 7, (3000, 3))
    inside = points_in_boxes(points, boxes)
    assert inside.shape == (3000, 40) and 50 < inside.sum() < 3000 * 40 // 4
    np.testing.assert_array_equal(points_in_boxes(torch.from_numpy(points), torch.from_numpy(boxes)).numpy(), inside)
