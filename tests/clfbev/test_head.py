"""Tests for clfbev.anchors, clfbev.head, clfbev.supervision.assign and clfbev.supervision.losses: exact anchor grids, SECOND-style
class-aware assignment on hand-computed IoUs, hand-computed losses, decode(encode) round trips."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from clfbev.anchors import MATCH_THRESHOLDS, anchor_class_ids, make_anchors, match_thresholds
from clfbev.config import ModelConfig
from clfbev.errors import ConfigError
from clfbev.geometry import direction_target
from clfbev.head import AnchorHead, FlatPredictions, HeadOutput, decode, heading_from_motion
from clfbev.settings import ANCHOR_SIZES, DETECTION_CLASSES, LossWeights
from clfbev.supervision.assign import AnchorTargets, assign_targets, stack_targets
from clfbev.supervision.losses import (
    detection_loss, direction_cross_entropy, sigmoid_focal_loss, sin_difference, smooth_l1,
)
from clfbev.ops.boxes import bev_iou, encode_boxes

# The assignment tests run full 128 x 128 grids: multi-threaded kernels on the shared cores
# would spin and cost seconds.
pytestmark = pytest.mark.usefixtures("one_thread")

CAR_L, CAR_W, CAR_H = ANCHOR_SIZES["car"]


def assert_close(actual: torch.Tensor, expected, atol: float = 1e-6, rtol: float = 1e-6) -> None:
    """numpy's assert_allclose on tensors (torch.testing's first call costs seconds of imports)."""
    expected = np.asarray(expected.detach().cpu().double().numpy() if torch.is_tensor(expected) else expected)
    actual_np = actual.detach().cpu().double().numpy()
    assert actual_np.shape == expected.shape, (actual_np.shape, expected.shape)
    np.testing.assert_allclose(actual_np, expected, atol=atol, rtol=rtol)


def to_map(flat: torch.Tensor, ny: int, nx: int, n_anchors: int) -> torch.Tensor:
    """Inverse of HeadOutput.flatten for one sample: (N, k) rows in (iy, ix, a) order ->
    (1, A * k, ny, nx) anchor-major channels. Written independently of the library code."""
    k = flat.shape[1]
    return flat.reshape(ny, nx, n_anchors, k).permute(2, 3, 0, 1).reshape(1, n_anchors * k, ny, nx)


def line_anchors(class_names, nx: int = 8):
    """One row of 1 m cells along x: centres x = 0.5 .. nx - 0.5, y = 0."""
    return make_anchors(class_names, (1, nx), (0.0, -0.5, -5.0, float(nx), 0.5, 3.0))


def car(x, y=0.0, yaw=0.0, vx=0.0, vy=0.0, l=CAR_L, w=CAR_W):
    return [x, y, -1.84 + CAR_H / 2, l, w, CAR_H, yaw, vx, vy]


# ----------------------------------------------------------------------------------------------
# Anchors
# ----------------------------------------------------------------------------------------------


def test_anchor_grid_centres_sizes_exact():
    names = ("car", "pedestrian")
    anchors = make_anchors(names, (2, 4), (0.0, -4.0, -5.0, 8.0, 4.0, 3.0))
    assert anchors.shape == (2, 4, 2, 2, 7) and anchors.dtype == torch.float32
    xs, ys = [1.0, 3.0, 5.0, 7.0], [-2.0, 2.0]  # 2 m cells, centred
    expected = np.zeros((2, 4, 2, 2, 7))
    for iy, y in enumerate(ys):
        for ix, x in enumerate(xs):
            for c, name in enumerate(names):
                l, w, h = ANCHOR_SIZES[name]
                for r, yaw in enumerate([0.0, math.pi / 2]):
                    expected[iy, ix, c, r] = [x, y, -1.84 + h / 2, l, w, h, yaw]
    assert_close(anchors, expected)
    assert_close(anchors[0, 0, 0, 0, 2], torch.tensor(-0.98))  # a car's centre, lidar frame
    # Flattened order is (iy, ix, cls, rot).
    ids = anchor_class_ids(anchors)
    assert ids.tolist() == [0, 0, 1, 1] * 8
    assert torch.equal(anchors.reshape(-1, 7)[((0 * 4 + 1) * 2 + 0) * 2 + 1], anchors[0, 1, 0, 1])


def test_anchor_tables_cover_all_classes():
    assert set(DETECTION_CLASSES) == set(ANCHOR_SIZES) == set(MATCH_THRESHOLDS)
    assert all(pos > neg for pos, neg in MATCH_THRESHOLDS.values())
    assert match_thresholds(["car", "pedestrian"]) == [(0.6, 0.45), (0.5, 0.35)]
    with pytest.raises(ValueError, match="no anchor size"):
        make_anchors(["car", "spaceship"], (2, 2), (0, 0, 0, 1, 1, 1))


# ----------------------------------------------------------------------------------------------
# Head and layout
# ----------------------------------------------------------------------------------------------


def test_head_shapes_prior_and_flatten_layout():
    head = AnchorHead(in_ch=16, n_classes=3, n_rot=2, code_size=9, n_dir_bins=2)
    out = head(torch.randn(2, 16, 5, 6))
    assert out.cls_logits.shape == (2, 6, 5, 6)
    assert out.box_deltas.shape == (2, 54, 5, 6)
    assert out.dir_logits.shape == (2, 12, 5, 6)
    # Focal prior: every anchor starts near score 0.01.
    assert_close(torch.sigmoid(out.cls_logits).mean(), torch.tensor(0.01), atol=2e-3)
    flat = out.flatten()
    assert flat.cls_logits.shape == (2, 180)
    assert flat.box_deltas.shape == (2, 180, 9) and flat.dir_logits.shape == (2, 180, 2)

    # Channel a * k + j at (iy, ix) -> row (iy * W + ix) * A + a, column j.
    h, w, a, k = 2, 3, 4, 5
    ch = torch.arange(a * k).view(a * k, 1, 1)
    iy = torch.arange(h).view(1, h, 1)
    ix = torch.arange(w).view(1, 1, w)
    code = (ch * 100 + iy * 10 + ix).float()[None]  # (1, A * k, H, W)
    rows = HeadOutput(code[:, :a], code, code[:, : a * 2]).flatten().box_deltas[0]
    for y in range(h):
        for x in range(w):
            for anchor in range(a):
                for j in range(k):
                    assert rows[(y * w + x) * a + anchor, j] == (anchor * k + j) * 100 + y * 10 + x
    assert torch.equal(to_map(rows, h, w, a), code)


# ----------------------------------------------------------------------------------------------
# Assignment
# ----------------------------------------------------------------------------------------------


def test_velocity_tower_owns_the_velocity_residuals_only():
    """With a tower, residuals 0-6 of every anchor are the 1x1 head's and 7-8 the tower's, in
    the anchor-major layout; only the velocity loss reaches the tower, and the motion channels
    reach the velocity alone."""
    torch.manual_seed(0)
    head = AnchorHead(in_ch=16, n_classes=3, n_rot=2, code_size=9, velocity_tower=8, motion_ch=5).eval()
    bev, motion = torch.randn(2, 16, 6, 7), torch.randn(2, 5, 6, 7)
    out = head(bev, motion)
    assert out.box_deltas.shape == (2, 6 * 9, 6, 7)
    box = out.box_deltas.view(2, 6, 9, 6, 7)
    assert torch.equal(box[:, :, :7], head.conv_box(bev).view(2, 6, 7, 6, 7))
    assert torch.equal(box[:, :, 7:], head.velocity(torch.cat([bev, motion], 1)).view(2, 6, 2, 6, 7))
    other = head(bev, motion + 1.0).box_deltas.view(2, 6, 9, 6, 7)
    assert torch.equal(other[:, :, :7], box[:, :, :7]) and not torch.equal(other[:, :, 7:], box[:, :, 7:])

    head.train()
    box = head(bev, motion).box_deltas.view(2, 6, 9, 6, 7)
    box[:, :, :7].sum().backward(retain_graph=True)
    assert all(p.grad is None or not p.grad.any() for p in head.velocity.parameters())
    head.zero_grad(set_to_none=True)
    box[:, :, 7:].sum().backward()
    assert head.conv_box.weight.grad is None or not head.conv_box.weight.grad.any()
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in head.velocity.parameters())
    with pytest.raises(ValueError, match="code_size 9"):
        AnchorHead(in_ch=16, n_classes=3, code_size=7, velocity_tower=8)


def test_velocity_gate_is_the_towers_third_output():
    """``velocity_gate``: the tower gives (vx, vy, moving logit) per anchor; the first two are the
    velocity residuals, the third the head's ``moving_logits``, flattened in the anchors' order."""
    torch.manual_seed(0)
    head = AnchorHead(in_ch=16, n_classes=3, n_rot=2, code_size=9, velocity_tower=8, motion_ch=5,
                      velocity_gate=True).eval()
    bev, motion = torch.randn(2, 16, 6, 7), torch.randn(2, 5, 6, 7)
    out = head(bev, motion)
    tower = head.velocity(torch.cat([bev, motion], 1)).view(2, 6, 3, 6, 7)
    assert torch.equal(out.box_deltas.view(2, 6, 9, 6, 7)[:, :, 7:], tower[:, :, :2])
    assert torch.equal(out.moving_logits, tower[:, :, 2])
    flat = out.flatten()
    assert torch.equal(flat.moving_logits, tower[:, :, 2].permute(0, 2, 3, 1).reshape(2, -1))
    assert AnchorHead(in_ch=16, n_classes=3, velocity_tower=8)(bev).moving_logits is None
    with pytest.raises(ValueError, match="gate needs a velocity tower"):
        AnchorHead(in_ch=16, n_classes=3, velocity_gate=True)


def test_detached_velocity_tower_sends_no_gradient_into_the_bev():
    """``velocity_detach``: the velocity residuals give the BEV features no gradient (so the
    velocity loss cannot reshape what the boxes read) and still train the tower; the box
    residuals' gradient reaches the BEV as before. The forward values are the same."""
    torch.manual_seed(0)
    attached = AnchorHead(in_ch=16, n_classes=3, n_rot=2, code_size=9, velocity_tower=8, motion_ch=5)
    detached = AnchorHead(in_ch=16, n_classes=3, n_rot=2, code_size=9, velocity_tower=8, motion_ch=5,
                          velocity_detach=True)
    detached.load_state_dict(attached.state_dict())
    motion = torch.randn(2, 5, 6, 7)
    bev_grad, tower_grad, values = {}, {}, {}
    for name, head in (("attached", attached), ("detached", detached)):
        bev = torch.randn(2, 16, 6, 7, generator=torch.Generator().manual_seed(1)).requires_grad_()
        box = head(bev, motion).box_deltas.view(2, 6, 9, 6, 7)
        box[:, :, 7:].sum().backward(retain_graph=True)       # the velocity residuals alone
        bev_grad[name] = bev.grad.clone()
        tower_grad[name] = [p.grad.abs().sum() for p in head.velocity.parameters()]
        bev.grad = None
        box[:, :, :7].sum().backward()                        # the box residuals alone
        assert bev.grad.abs().sum() > 0
        values[name] = box.detach()
    assert bev_grad["attached"].abs().sum() > 0
    assert not bev_grad["detached"].any()
    assert all(g > 0 for g in tower_grad["detached"])
    assert torch.equal(values["attached"], values["detached"])


def test_gt_on_anchor_is_positive_with_zero_residuals_class_aware():
    names = ("car", "construction_vehicle", "pedestrian")
    anchors = line_anchors(names)
    gt = torch.tensor([car(3.5, vx=1.5, vy=-0.5)])
    targets = assign_targets(anchors, gt, torch.tensor([0]), match_thresholds(names))
    n = 8 * 3 * 2
    assert targets.labels.shape == (n,) and targets.box_targets.shape == (n, 9)
    lab = targets.labels.view(8, 3, 2)
    # Car anchors at x = 3.5 +- 1: same size, shifted along l, IoU (l - 1) / (l + 1) = 0.64 >= 0.6.
    expected_car = torch.zeros(8, dtype=torch.long)
    expected_car[2:5] = 1
    assert torch.equal(lab[:, 0, 0], expected_car)
    assert torch.equal(lab[:, 0, 1], torch.zeros(8, dtype=torch.long))  # crossing: IoU 0.27
    # The construction-vehicle anchor on the car has IoU 0.52 >= its pos 0.5, and is still
    # background: matching is class-aware.
    iou_cv = bev_iou(anchors[0, 3, 1, 0][None], gt)
    assert 0.5 < float(iou_cv) < 0.55
    assert (lab[:, 1:] == 0).all()
    row = 3 * 6  # (ix = 3, car, rot 0)
    assert int(targets.matched_gt[row]) == 0
    assert_close(targets.box_targets[row], [0, 0, 0, 0, 0, 0, 0, 1.5, -0.5], atol=1e-6)
    assert_close(targets.box_weights[row], np.ones(9))
    assert int(targets.dir_targets[row]) == 0
    assert (targets.cls_weights == 1).all()
    assert targets.box_weights[targets.labels == 0].abs().sum() == 0
    assert (targets.matched_gt[targets.labels <= 0] == -1).all()


def test_between_thresholds_is_ignored():
    anchors = line_anchors(("car",))
    shift = 0.3
    gt = torch.tensor([car(3.5 + shift, yaw=math.pi)])
    targets = assign_targets(anchors, gt, torch.tensor([0]), [(0.6, 0.45)])
    lab = targets.labels.view(8, 2)
    # Same-size boxes shifted by s along their length: IoU = (l - s) / (l + s).
    expected = []
    for ix in range(8):
        s = abs(3.5 + shift - (ix + 0.5))
        iou = max(CAR_L - s, 0.0) / (CAR_L + s)
        expected.append(1 if iou >= 0.6 else (0 if iou < 0.45 else -1))
    assert expected == [0, 0, -1, 1, 1, -1, 0, 0]  # the case is non-trivial
    assert lab[:, 0].tolist() == expected
    assert (lab[:, 1] == 0).all()
    assert (targets.cls_weights.view(8, 2)[:, 0] == torch.tensor([e >= 0 for e in expected])).all()
    # Heading pi: residual pi (regression is pi-periodic), direction bin 1.
    assert_close(targets.box_targets.view(8, 2, 9)[3, 0, 6], torch.tensor(math.pi), atol=1e-6)
    assert int(targets.dir_targets.view(8, 2)[3, 0]) == 1


def test_best_anchor_is_forced_positive():
    names = ("pedestrian",)
    anchors = line_anchors(names)
    l, w, h = ANCHOR_SIZES["pedestrian"]
    gt = torch.tensor([[3.8, 0.0, -1.0, l, w, h, 0.0, 0.0, 0.0]])
    iou = bev_iou(anchors.reshape(-1, 7), gt).view(8, 2)
    assert 0.35 <= float(iou[3, 0]) < 0.5  # best anchor, between thresholds
    assert float(iou.max()) == float(iou[3, 0])
    targets = assign_targets(anchors, gt, torch.tensor([0]), match_thresholds(names))
    lab = targets.labels.view(8, 2)
    assert int(lab[3, 0]) == 1 and int(targets.matched_gt.view(8, 2)[3, 0]) == 0
    assert int((targets.labels > 0).sum()) == 1
    assert int(lab[3, 1]) == -1  # crossing anchor: IoU 0.37, between thresholds, not the best

    # A GT exactly between two anchors: both tie for best, the lower index is forced (both
    # used to be: one forced anchor per GT now, so that crowds share fairly).
    gt_mid = torch.tensor([[4.0, 0.0, -1.0, l, w, h, 0.0, 0.0, 0.0]])
    iou_mid = bev_iou(anchors.reshape(-1, 7), gt_mid).view(8, 2)
    assert float(iou_mid[3, 0]) == float(iou_mid[4, 0]) == float(iou_mid.max()) > 0
    targets = assign_targets(anchors, gt_mid, torch.tensor([0]), match_thresholds(names))
    assert torch.nonzero(targets.labels > 0).flatten().tolist() == [3 * 2]


def test_forced_anchor_has_the_closest_rotation():
    """A bicycle at 35 degrees, off the anchor row, overlaps the crossing anchor more than the
    parallel one and is still forced onto the parallel anchor: the rotation closest to its
    yaw. (Forcing the best anchor of any rotation flips between the two as the yaw crosses
    the IoU break-even, sample to sample.)"""
    names = ("bicycle",)
    anchors = line_anchors(names)
    l, w, h = ANCHOR_SIZES["bicycle"]
    gt = torch.tensor([[3.5, 0.4, -1.2, l, w, h, math.radians(35.0) + math.pi, 0.0, 0.0]])
    iou = bev_iou(anchors.reshape(-1, 7), gt).view(8, 2)
    assert float(iou[:, 1].max()) > float(iou[:, 0].max()) > 0  # crossing anchor is the best
    assert float(iou.max()) < 0.35  # all below the negative threshold: only forcing helps
    assert float(iou[3, 0]) == float(iou[:, 0].max())
    targets = assign_targets(anchors, gt, torch.tensor([0]), match_thresholds(names))
    assert torch.nonzero(targets.labels > 0).flatten().tolist() == [3 * 2 + 0]
    # Heading pi + 35 degrees: residual relative to the yaw-0 anchor, direction bin 1.
    assert_close(targets.box_targets[3 * 2, 6], gt[0, 6])
    assert int(targets.dir_targets[3 * 2]) == 1


def test_gt_touching_no_anchor_forces_the_nearest_centre():
    """Used to stay unmatched (a forced match needed IoU > 0): a traffic cone between anchor
    centres overlaps no cone anchor, and now forces the one whose centre is nearest, in the
    rotation closest to its yaw."""
    names = ("traffic_cone", "car")
    anchors = line_anchors(names)  # 1 m cells; cone anchors 0.4 m: gaps of 0.6 m
    l, w, h = ANCHOR_SIZES["traffic_cone"]
    thresholds = match_thresholds(names)
    cases = [(4.03, 1.2, 4, 1), (3.98, -0.1, 3, 0), (4.0, 0.3, 3, 0)]  # x, yaw, cell, rotation
    for x, yaw, cell, rot in cases:
        gt = torch.tensor([[x, 0.0, -1.3, l, w, h, yaw, 0.0, 0.0]])
        assert float(bev_iou(anchors[:, :, 0].reshape(-1, 7), gt).max()) == 0.0
        targets = assign_targets(anchors, gt, torch.tensor([0]), thresholds)
        row = (cell * 2 + 0) * 2 + rot
        assert torch.nonzero(targets.labels > 0).flatten().tolist() == [row], (x, yaw)
        assert int(targets.labels[row]) == 1 and int(targets.matched_gt[row]) == 0
        # It regresses the cone from that anchor.
        assert_close(targets.box_targets[row, 0], torch.tensor((x - (cell + 0.5)) / math.hypot(l, w)), atol=1e-6)
    # x = 4.0 is exactly between the centres 3.5 and 4.5: the lower index wins (the last case).


def test_two_gt_forcing_one_anchor_higher_iou_wins():
    """Two pedestrians whose forced anchor is the same: the one with the higher IoU keeps it,
    on equal IoU the lower GT index; the other forces nothing."""
    names = ("pedestrian",)
    anchors = line_anchors(names)
    l, w, h = ANCHOR_SIZES["pedestrian"]
    thresholds = match_thresholds(names)
    near, nearer = [3.75, 0.2, -1.0, l, w, h, 0.0, 0.0, 0.0], [3.6, -0.2, -1.0, l, w, h, 0.0, 0.0, 0.0]
    for gt, winner in [([near, nearer], 1), ([nearer, near], 0)]:
        targets = assign_targets(anchors, torch.tensor(gt), torch.tensor([0, 0]), thresholds)
        assert torch.nonzero(targets.labels > 0).flatten().tolist() == [3 * 2]
        assert int(targets.matched_gt[3 * 2]) == winner
    mirrored = [[3.6, 0.2, -1.0, l, w, h, 0.0, 0.0, 0.0], [3.6, -0.2, -1.0, l, w, h, 0.0, 0.0, 0.0]]
    targets = assign_targets(anchors, torch.tensor(mirrored), torch.tensor([0, 0]), thresholds)
    assert torch.nonzero(targets.labels > 0).flatten().tolist() == [3 * 2]
    assert int(targets.matched_gt[3 * 2]) == 0


def closest_rotation(yaw: float, rotations) -> int:
    """Index of the rotation nearest to ``yaw`` modulo pi (first of equals), in float64."""
    gaps = [abs(math.remainder(yaw - r, math.pi)) for r in rotations]
    return gaps.index(min(gaps))


def test_assignment_matches_literal_reference_on_random_scene():
    """Vectorised assignment == a per-anchor loop written straight from the rules."""
    gen = torch.Generator().manual_seed(3)
    names = ("car", "pedestrian", "barrier")
    thresholds = match_thresholds(names)
    anchors = make_anchors(names, (12, 12), (-6.0, -6.0, -5.0, 6.0, 6.0, 3.0))
    m = 12
    labels = torch.arange(m) % 3
    sizes = torch.tensor([ANCHOR_SIZES[n] for n in names])[labels] * (0.8 + 0.4 * torch.rand(m, 1, generator=gen))
    gt = torch.cat(
        [
            torch.rand(m, 2, generator=gen) * 12 - 6,
            torch.full((m, 1), -1.0),
            sizes,
            torch.rand(m, 1, generator=gen) * 2 * math.pi - math.pi,
            torch.randn(m, 2, generator=gen),
        ],
        dim=1,
    )
    # A small pedestrian on the corner between four cells: it overlaps no anchor, and the four
    # nearest centres are equally far.
    pl, pw, ph = ANCHOR_SIZES["pedestrian"]
    gt = torch.cat([gt, torch.tensor([[0.0, 0.0, -1.0, 0.4 * pl, 0.4 * pw, ph, 0.0, 0.0, 0.0]])])
    labels = torch.cat([labels, torch.tensor([1])])
    m += 1
    targets = assign_targets(anchors, gt, labels, thresholds)

    flat = anchors.reshape(-1, 7)
    cls_of = anchor_class_ids(anchors).tolist()
    rot_of = [i % 2 for i in range(len(flat))]
    iou = bev_iou(flat, gt).tolist()  # all classes; the loops apply class-awareness
    # Forced anchor of each GT: best IoU in its closest rotation, else the nearest centre.
    forced: dict[int, tuple[float, int]] = {}  # anchor -> (IoU, -GT) of the winner so far
    for j in range(m):
        r = closest_rotation(float(gt[j, 6]), anchors[0, 0, 0, :, 6].tolist())
        mine = [i for i in range(len(flat)) if cls_of[i] == labels[j] and rot_of[i] == r]
        best = max(mine, key=lambda i: (iou[i][j], -i))
        if iou[best][j] == 0:
            best = min(mine, key=lambda i: (math.dist(flat[i, :2].tolist(), gt[j, :2].tolist()), i))
        forced[best] = max(forced.get(best, (-1.0, 0)), (iou[best][j], -j))
    for i in range(len(flat)):
        mine = [j for j in range(m) if labels[j] == cls_of[i]]
        best = max((iou[i][j] for j in mine), default=0.0)
        pos_thr, neg_thr = thresholds[cls_of[i]]
        if i in forced:
            assert int(targets.labels[i]) == cls_of[i] + 1 and int(targets.matched_gt[i]) == -forced[i][1], i
        elif best >= pos_thr:
            assert int(targets.labels[i]) == cls_of[i] + 1, i
            assert int(targets.matched_gt[i]) == max(mine, key=lambda j: (iou[i][j], -j))
        else:
            assert int(targets.labels[i]) == (0 if best < neg_thr else -1), i
    # The scene exercises every case, a GT touching no anchor of its class (a pedestrian
    # between 1 m cells) included; every GT has a positive.
    assert {-1, 0, 1, 2, 3} <= set(targets.labels.tolist())
    assert any(max(iou[i][j] for i in range(len(flat)) if cls_of[i] == labels[j]) == 0 for j in range(m))
    assert set(targets.matched_gt[targets.positives].tolist()) == set(range(m))


def all_pairs_assignment(anchors, gt, labels, thresholds):
    """The assignment rules on the full (anchors of class c) x (GT of class c) IoU matrix of
    ``bev_iou``, a loop over the GT for the forced anchors: (labels, matched_gt) per anchor."""
    flat = anchors.reshape(-1, 7)
    n, n_rot = flat.shape[0], anchors.shape[3]
    cls_of = anchor_class_ids(anchors)
    rot_of = torch.arange(n) % n_rot
    rotations = anchors[0, 0, 0, :, 6].tolist()
    out_labels = torch.zeros(n, dtype=torch.long)
    matched = torch.full((n,), -1, dtype=torch.long)
    forced: dict[int, tuple[float, int]] = {}  # anchor -> (IoU, -GT) of the winner so far
    for c, (pos_thr, neg_thr) in enumerate(thresholds):
        rows = torch.nonzero(cls_of == c).flatten()
        cols = torch.nonzero(labels == c).flatten()
        if cols.numel() == 0:
            continue
        iou = bev_iou(flat[rows], gt[cols])
        best, best_gt = iou.max(dim=1).values, iou.argmax(dim=1)  # argmax: first of equals
        out_labels[rows] = torch.where(best >= pos_thr, c + 1, torch.where(best < neg_thr, 0, -1))
        matched[rows] = torch.where(best >= pos_thr, cols[best_gt], -1)
        for k, j in enumerate(cols.tolist()):
            in_rot = rot_of[rows] == closest_rotation(float(gt[j, 6]), rotations)
            column = torch.where(in_rot, iou[:, k], -1.0)
            if float(column.max()) > 0:
                row, value = int(rows[column.argmax()]), float(column.max())
            else:
                dist = (flat[rows, :2].double() - gt[j, :2].double()).pow(2).sum(dim=1)
                row, value = int(rows[torch.where(in_rot, dist, math.inf).argmin()]), 0.0
            forced[row] = max(forced.get(row, (-1.0, 0)), (value, -j))
    for row, (_, neg_j) in forced.items():
        out_labels[row] = int(cls_of[row]) + 1
        matched[row] = -neg_j
    return out_labels, matched


def random_scene(gen, n_per_class, half_range, size_jitter=0.3, classes=range(len(DETECTION_CLASSES)), clustered=0.0):
    """GT boxes (M, 9) of the given classes (mean size times 1 +- size_jitter), uniform over
    the square +-half_range, any yaw; a share ``clustered`` sits within 1.5 m of the previous
    box of its class (crowds: several GT compete for one forced anchor). Labels (M,)."""
    labels = torch.tensor(list(classes)).repeat_interleave(n_per_class)
    m = labels.shape[0]
    sizes = torch.tensor([ANCHOR_SIZES[DETECTION_CLASSES[c]] for c in labels.tolist()])
    sizes = sizes * (1 + size_jitter * (2 * torch.rand(m, 3, generator=gen) - 1))
    xy = (2 * torch.rand(m, 2, generator=gen) - 1) * half_range
    near = torch.rand(m, generator=gen) < clustered
    near[::n_per_class] = False  # the first of each class has no previous one
    prev = torch.arange(m) - 1
    xy = torch.where(near[:, None], xy[prev.clamp(min=0)] + 1.5 * (2 * torch.rand(m, 2, generator=gen) - 1), xy)
    xy = xy.clamp(-half_range, half_range - 1e-3)
    yaw = (2 * torch.rand(m, 1, generator=gen) - 1) * math.pi
    z = torch.full((m, 1), -1.0)
    return torch.cat([xy, z, sizes, yaw, torch.randn(m, 2, generator=gen)], dim=1), labels


SMALL_CLASSES = [DETECTION_CLASSES.index(name) for name in ("barrier", "motorcycle", "bicycle", "pedestrian", "traffic_cone")]


@pytest.mark.parametrize(
    ("seed", "size", "half_range", "per_class", "clustered", "classes"),
    [
        (0, 128, 51.2, 5, 0.0, range(10)),
        (1, 64, 51.2, 6, 0.5, range(10)),
        (2, 32, 12.8, 4, 0.6, range(10)),
        (3, 16, 12.8, 3, 0.3, range(10)),
        (4, 16, 12.8, 25, 0.3, SMALL_CLASSES),  # 1.6 m cells: many barely-touching small boxes
    ],
)
def test_assignment_equals_all_pairs_reference(seed, size, half_range, per_class, clustered, classes):
    """Windowed, bounded matching == the all-pairs IoU matrix: labels, matched GT, box targets."""
    gen = torch.Generator().manual_seed(seed)
    anchors = make_anchors(DETECTION_CLASSES, (size, size), (-half_range, -half_range, -5.0, half_range, half_range, 3.0))
    thresholds = match_thresholds(DETECTION_CLASSES)
    gt, labels = random_scene(gen, per_class, half_range, classes=classes, clustered=clustered)
    labels[:2] = torch.tensor([-1, len(DETECTION_CLASSES)])  # classes the head does not detect
    targets = assign_targets(anchors, gt, labels, thresholds)
    ref_labels, ref_matched = all_pairs_assignment(anchors, gt, labels, thresholds)
    assert torch.equal(targets.labels, ref_labels)
    assert torch.equal(targets.matched_gt, ref_matched)
    pos = ref_matched >= 0
    ref_codes = encode_boxes(gt[ref_matched[pos]], anchors.reshape(-1, 7)[pos])
    assert torch.equal(targets.box_targets[pos], ref_codes)
    assert (targets.box_targets[~pos] == 0).all()
    # GT of classes the head does not detect match nothing.
    assert set(targets.matched_gt[pos].tolist()) <= set(range(2, gt.shape[0]))
    assert {-1, 0} <= set(targets.labels.tolist())


def grid_points(size: int, half_range: float, gen, k: int) -> torch.Tensor:
    """k points (k, 2) exactly between anchor centres: cell corners and edge midpoints."""
    cell = 2 * half_range / size
    corner = torch.randint(1, size, (k, 2), generator=gen).double() * cell - half_range
    shift = torch.randint(0, 2, (k, 1), generator=gen).double() * 0.5 * cell  # corner or midpoint
    return (corner + torch.cat([shift, torch.zeros_like(shift)], dim=1)).float()


def spread_out(xy: torch.Tensor, labels: torch.Tensor, min_dist: torch.Tensor) -> torch.Tensor:
    """(M,) bool keeping, greedily in order, boxes at least min_dist[class] from every kept box
    of their class (kept GT never compete for the same anchor)."""
    keep = torch.zeros(xy.shape[0], dtype=torch.bool)
    for j in range(xy.shape[0]):
        same = keep & (labels == labels[j])
        keep[j] = not bool(((xy[same] - xy[j]).norm(dim=1) < min_dist[labels[j]]).any())
    return keep


@pytest.mark.parametrize("size", [64, 128])
def test_every_gt_gets_a_positive_with_the_closest_rotation(size):
    """Boxes of every class at its mean size, anywhere in range (uniform, and exactly between
    anchor centres), any yaw: each has a positive anchor of its class, and one of its positives
    has the anchor rotation closest to its yaw (modulo pi). Before forcing on every GT, about
    15% of pedestrians and 72% of traffic cones had no positive at 1.6 m cells."""
    gen = torch.Generator().manual_seed(size)
    half_range = 51.2
    anchors = make_anchors(DETECTION_CLASSES, (size, size), (-half_range, -half_range, -5.0, half_range, half_range, 3.0))
    k = 40  # draws per class, half uniform, half between centres
    labels = torch.arange(len(DETECTION_CLASSES)).repeat_interleave(k)
    xy = (2 * torch.rand(labels.shape[0], 2, generator=gen) - 1) * half_range
    between = torch.arange(labels.shape[0]) % 2 == 1
    xy[between] = grid_points(size, half_range, gen, int(between.sum()))
    yaw = (2 * torch.rand(labels.shape[0], generator=gen) - 1) * math.pi
    yaw[::7] = torch.tensor([0.0, math.pi / 2, -math.pi, 3 * math.pi / 4])[torch.arange(yaw[::7].shape[0]) % 4]
    sizes = torch.tensor([ANCHOR_SIZES[name] for name in DETECTION_CLASSES])
    # A forced anchor overlaps its GT or is its nearest centre: GT of one class further apart
    # than twice the diagonal plus two cells never share one.
    min_dist = 2 * sizes[:, :2].norm(dim=1) + 4 * half_range / size
    keep = spread_out(xy, labels, min_dist)
    labels, xy, yaw = labels[keep], xy[keep], yaw[keep]
    assert torch.bincount(labels).min() >= 5  # buses and trailers need the most room
    z, velocity = torch.full_like(yaw[:, None], -1.0), torch.zeros(len(yaw), 2)
    gt = torch.cat([xy, z, sizes[labels], yaw[:, None], velocity], dim=1)

    targets = assign_targets(anchors, gt, labels, match_thresholds(DETECTION_CLASSES))
    pos = torch.nonzero(targets.labels > 0).flatten()
    gt_of = targets.matched_gt[pos]
    assert (gt_of >= 0).all() and torch.equal(anchor_class_ids(anchors)[pos], labels[gt_of])
    assert torch.equal(targets.labels[pos], labels[gt_of] + 1)
    missing = sorted(set(range(gt.shape[0])) - set(gt_of.tolist()))
    assert not missing, [(DETECTION_CLASSES[labels[j]], gt[j, [0, 1, 6]].tolist()) for j in missing]
    # The anchors' own yaws (float32 pi/2 is not pi/2): on the diagonals they decide.
    rotations = anchors[0, 0, 0, :, 6].tolist()
    closer = torch.tensor([closest_rotation(float(y), rotations) for y in yaw])
    with_closer = set(gt_of[pos % 2 == closer[gt_of]].tolist())
    wrong = sorted(set(range(gt.shape[0])) - with_closer)
    assert not wrong, [(DETECTION_CLASSES[labels[j]], gt[j, [0, 1, 6]].tolist()) for j in wrong]


def test_assignment_rejects_anchors_off_a_grid_and_bad_thresholds():
    names = ("car", "pedestrian")
    anchors = make_anchors(names, (4, 4), (-4.0, -4.0, -5.0, 4.0, 4.0, 3.0))
    gt, labels = torch.tensor([car(0.5, 0.5)]), torch.tensor([0])
    moved = anchors.clone()
    moved[-1, -1, 1, 0, 3] += 0.1  # one anchor of another size: the windows would miss pairs
    with pytest.raises(ValueError, match="regular grid"):
        assign_targets(moved, gt, labels, match_thresholds(names))
    with pytest.raises(ValueError, match="0 < neg <= pos"):
        assign_targets(anchors, gt, labels, [(0.6, 0.0), (0.5, 0.35)])


def test_empty_gt_all_negative_and_unknown_velocity():
    names = ("car", "pedestrian")
    anchors = line_anchors(names)
    targets = assign_targets(anchors, torch.zeros(0, 9), torch.zeros(0, dtype=torch.long), match_thresholds(names))
    assert (targets.labels == 0).all() and (targets.cls_weights == 1).all()
    assert (targets.box_weights == 0).all() and (targets.matched_gt == -1).all()
    # GT of a class the head does not detect (label -1) are ignored: still all negative.
    other = assign_targets(anchors, torch.tensor([car(3.5)]), torch.tensor([-1]), match_thresholds(names))
    assert (other.labels == 0).all()
    # NaN velocity: regressed position etc., but no velocity loss.
    nan_v = assign_targets(anchors, torch.tensor([car(3.5, vx=float("nan"), vy=float("nan"))]), torch.tensor([0]), match_thresholds(names))
    pos = nan_v.labels > 0
    assert pos.any() and torch.isfinite(nan_v.box_targets).all()
    assert (nan_v.box_weights[pos][:, :7] == 1).all() and (nan_v.box_weights[pos][:, 7:] == 0).all()


def test_direction_target_bins():
    yaw = torch.tensor([0.0, math.pi / 2, math.pi, -math.pi / 2, -0.8, -0.7, 2.3, 2.4, 2 * math.pi])
    # Bin 0 is [-pi/4, 3pi/4) modulo 2 pi (-pi/4 = -0.785, 3pi/4 = 2.356), bin 1 the rest.
    assert direction_target(yaw).tolist() == [0, 0, 1, 1, 1, 0, 0, 1, 0]


# ----------------------------------------------------------------------------------------------
# Losses
# ----------------------------------------------------------------------------------------------


def test_focal_loss_hand_computed_and_perfect():
    logits = torch.tensor([2.0, -1.0, 0.5, 0.0], dtype=torch.float64)
    targets = torch.tensor([1.0, 0.0, 1.0, 0.0], dtype=torch.float64)
    expected = []
    for x, t in zip(logits.tolist(), targets.tolist()):
        p = 1 / (1 + math.exp(-x))
        expected.append(-0.25 * (1 - p) ** 2 * math.log(p) if t else -0.75 * p**2 * math.log(1 - p))
    assert_close(sigmoid_focal_loss(logits, targets), expected, atol=1e-12)
    # (logit 0, target 0): 0.75 * 0.25 * log 2.
    assert_close(sigmoid_focal_loss(logits, targets)[3], torch.tensor(0.75 * 0.25 * math.log(2)), atol=1e-12)
    perfect = sigmoid_focal_loss(torch.tensor([30.0, -30.0]), torch.tensor([1.0, 0.0]))
    assert float(perfect.max()) < 1e-20
    assert torch.isfinite(sigmoid_focal_loss(torch.tensor([-200.0]), torch.tensor([1.0]))).all()


def test_smooth_l1_and_direction_ce():
    beta = 1 / 9
    x = torch.tensor([0.05, -0.05, 1.0, -2.0], dtype=torch.float64)
    assert_close(smooth_l1(x, beta), [0.5 * 0.0025 / beta] * 2 + [1 - beta / 2, 2 - beta / 2], atol=1e-12)
    assert_close(smooth_l1(x, 0.0), x.abs())
    ce = direction_cross_entropy(torch.tensor([[[2.0, 0.0]]]), torch.tensor([[1]]))
    assert ce.shape == (1, 1)
    assert_close(ce[0, 0], torch.tensor(math.log(1 + math.exp(2.0))), atol=1e-6)


def test_sin_difference_encodes_sine_of_error():
    a = torch.tensor([0.3, -2.0, 3.0, 1.0], dtype=torch.float64)
    b = torch.tensor([1.1, 2.5, -3.0, 1.0 + math.pi], dtype=torch.float64)
    pa, pb = sin_difference(a, b)
    assert_close(pa - pb, torch.sin(a - b), atol=1e-12)


def _single_target_batch():
    """One car GT (heading pi) on a line of car anchors, and predictions equal to the targets."""
    anchors = line_anchors(("car",))
    targets = assign_targets(anchors, torch.tensor([car(3.5, yaw=math.pi, vx=1.0)]), torch.tensor([0]), [(0.6, 0.45)])
    batch = stack_targets([targets])
    pos = batch.positives.float()
    cls = torch.where(batch.positives, 30.0, -30.0)
    dir_logits = torch.nn.functional.one_hot(batch.dir_targets, 2).float() * 30.0 - 15.0
    return batch, pos, cls, batch.box_targets.clone(), dir_logits


def test_loss_perfect_and_off_by_pi():
    batch, pos, cls, box, dir_logits = _single_target_batch()
    assert batch.labels.shape == (1, 16) and int(pos.sum()) == 3
    perfect = detection_loss(FlatPredictions(cls, box, dir_logits), batch)
    for key in ("loss", "loss_cls", "loss_reg", "loss_reg_theta", "loss_dir"):
        assert float(perfect[key]) < 1e-6, key
    assert float(perfect["num_pos"]) == 3

    # Heading off by exactly pi with the wrong direction bin: the angle loss does not see it
    # (sin-difference), only the direction classifier does.
    flipped = box.clone()
    flipped[..., 6] += math.pi
    wrong_dir = -dir_logits
    off = detection_loss(FlatPredictions(cls, flipped, wrong_dir), batch)
    assert float(off["loss_reg_theta"]) < 1e-6
    # Logits 30 apart the wrong way: CE ~30 per positive. Negatives (whose dir logits are just
    # as wrong here) must not count: they have no heading.
    assert_close(off["loss_dir"], torch.tensor(30.0), atol=1e-4)
    assert float(off["loss_reg"]) < 1e-6
    # A quarter-turn error is penalised by the angle term: SmoothL1(sin(pi/2)) per positive.
    quarter = box.clone()
    quarter[..., 6] += math.pi / 2
    q = detection_loss(FlatPredictions(cls, quarter, dir_logits), batch)
    assert_close(q["loss_reg_theta"], torch.tensor(1 - (1 / 9) / 2), atol=1e-5)

    # Weighted total (eq. 9) and the velocity code weight.
    vel = box.clone()
    vel[..., 7] += 1.0  # 1 m/s error on every positive
    w = LossWeights()
    v = detection_loss(FlatPredictions(cls, vel, wrong_dir), batch, w)
    assert_close(v["loss_reg"], torch.tensor(0.2 * (1 - (1 / 9) / 2)), atol=1e-5)
    assert_close(v["loss_vel"], v["loss_reg"], atol=1e-7)          # all of it is velocity here
    assert float(q["loss_vel"]) < 1e-6 and float(perfect["loss_vel"]) < 1e-6
    total = w.cls * v["loss_cls"] + w.reg * (v["loss_reg"] + v["loss_reg_theta"]) + w.dir * v["loss_dir"]
    assert_close(v["loss"], total, atol=1e-6)


def test_ignored_anchors_do_not_count():
    anchors = line_anchors(("car",))
    batch = stack_targets([assign_targets(anchors, torch.tensor([car(3.8)]), torch.tensor([0]), [(0.6, 0.45)])])
    ignored = batch.labels == -1
    assert int(ignored.sum()) == 2
    # Confidently "positive" on the ignored anchors: no classification loss there.
    cls = torch.where(batch.positives | ignored, 30.0, -30.0)
    dir_logits = torch.nn.functional.one_hot(batch.dir_targets, 2).float() * 30.0
    losses = detection_loss(FlatPredictions(cls, batch.box_targets, dir_logits), batch)
    assert float(losses["loss_cls"]) < 1e-6 and float(losses["loss"]) < 1e-6


# ----------------------------------------------------------------------------------------------
# Decoding
# ----------------------------------------------------------------------------------------------


def test_decode_of_encoded_targets_returns_gt_after_nms():
    names = ("car", "pedestrian")
    ny, nx = 4, 16
    anchors = make_anchors(names, (ny, nx), (0.0, 0.0, -5.0, 16.0, 16.0, 3.0))  # 1 m x 4 m cells
    pl, pw, ph = ANCHOR_SIZES["pedestrian"]
    gt = torch.tensor(
        [
            car(3.7, 6.0, yaw=math.pi + 0.1, vx=2.0, vy=-1.0, l=4.9),  # heading in bin 1
            car(10.5, 2.0, yaw=-3.0, vx=-0.5, vy=0.25),  # bin 1 as well, wraps below -pi
            [13.5, 14.0, -1.0, pl * 1.1, pw, ph, math.pi / 2 + 0.05, 0.3, 0.0],  # on a pi/2 anchor
        ]
    )
    labels = torch.tensor([0, 0, 1])
    targets = assign_targets(anchors, gt, labels, match_thresholds(names))
    pos = targets.positives
    assert int(pos.sum()) > 3  # several anchors per car: duplicates for NMS to remove
    assert (targets.matched_gt[pos] >= 0).all()

    n_anchors = len(names) * 2
    cls = torch.where(pos, 8.0, -8.0)[:, None]
    dir_logits = torch.nn.functional.one_hot(targets.dir_targets, 2).float() * 8.0
    out = HeadOutput(
        to_map(cls, ny, nx, n_anchors),
        to_map(targets.box_targets, ny, nx, n_anchors),
        to_map(dir_logits, ny, nx, n_anchors),
    )
    # A second sample with nothing in it.
    empty = HeadOutput(*(torch.cat([t, torch.full_like(t, -8.0)]) for t in (out.cls_logits, out.box_deltas, out.dir_logits)))
    dets = decode(empty.cls_logits, empty.box_deltas, empty.dir_logits, anchors, score_thr=0.3, nms_iou=0.2, max_per_sample=50, pre_nms=100)
    assert len(dets) == 2
    boxes, scores, det_labels = dets[0][:3]
    assert boxes.shape == (3, 9)
    assert_close(scores, np.full(3, 1 / (1 + math.exp(-8.0))), atol=1e-6)
    order = torch.argsort(boxes[:, 0])
    boxes, det_labels = boxes[order], det_labels[order]
    assert det_labels.tolist() == [0, 0, 1]
    assert_close(boxes[:, :6], gt[:, :6], atol=1e-5)
    assert_close(boxes[:, 7:], gt[:, 7:], atol=1e-5)
    # Full heading recovered (not just modulo pi), compared modulo 2 pi.
    dyaw = torch.remainder(boxes[:, 6] - gt[:, 6] + math.pi, 2 * math.pi) - math.pi
    assert_close(dyaw, np.zeros(3), atol=1e-5)
    assert ((boxes[:, 6] >= -math.pi / 4 - 1e-6) & (boxes[:, 6] < 7 * math.pi / 4)).all()
    assert dets[1].boxes.shape == (0, 9) and dets[1].labels.shape == (0,)

    # The velocity gate: a box whose gate says still decodes at 0 m/s, the others keep theirs.
    gate = to_map(torch.where(targets.matched_gt == 0, 5.0, -5.0)[:, None], ny, nx, n_anchors)
    gated = decode(out.cls_logits, out.box_deltas, out.dir_logits, anchors, 0.3, 0.2, 50, 100,
                   moving_logits=gate)[0].boxes
    gated = gated[torch.argsort(gated[:, 0])]
    assert_close(gated[:, :7], boxes[:, :7], atol=0)
    assert_close(gated[:, 7:], torch.stack([gt[0, 7:], torch.zeros(2), torch.zeros(2)]), atol=1e-5)

    # Wild size residuals of an untrained head stay finite (clamped log ratios).
    wild = decode(out.cls_logits, torch.full_like(out.box_deltas, 100.0), out.dir_logits, anchors, 0.3, 0.2, 50, 100)[0]
    assert wild.boxes.shape[0] > 0 and torch.isfinite(wild.boxes).all()

    # Flipping the direction bins turns every heading by pi.
    flipped = decode(out.cls_logits, out.box_deltas, -out.dir_logits, anchors, 0.3, 0.2, 50, 100)[0]
    fb = flipped.boxes[torch.argsort(flipped.boxes[:, 0])]
    dyaw = torch.remainder(fb[:, 6] - gt[:, 6], 2 * math.pi)
    assert_close(dyaw, np.full(3, math.pi), atol=1e-5)

    # Without NMS suppression (threshold 1) every positive anchor comes back.
    all_pos = decode(out.cls_logits, out.box_deltas, out.dir_logits, anchors, 0.3, 1.0, 500, 1000)[0]
    assert all_pos.boxes.shape[0] == int(pos.sum())


# ----------------------------------------------------------------------------------------------
# End to end
# ----------------------------------------------------------------------------------------------


def test_gradients_reach_all_head_parameters():
    torch.manual_seed(0)
    names = ("car", "pedestrian", "barrier")
    ny, nx = 8, 8
    anchors = make_anchors(names, (ny, nx), (-8.0, -8.0, -5.0, 8.0, 8.0, 3.0))
    head = AnchorHead(in_ch=8, n_classes=3)
    bev = torch.randn(2, 8, ny, nx)
    l, w, h = ANCHOR_SIZES["barrier"]
    gt = torch.tensor([car(1.0, 1.0, yaw=0.4, vx=1.0), [-3.0, 4.0, -1.3, l, w, h, 1.2, 0.0, 0.0]])
    targets = stack_targets(
        [
            assign_targets(anchors, gt, torch.tensor([0, 2]), match_thresholds(names)),
            assign_targets(anchors, torch.zeros(0, 9), torch.zeros(0, dtype=torch.long), match_thresholds(names)),
        ]
    )
    assert isinstance(targets, AnchorTargets) and targets.labels.shape == (2, ny * nx * 6)
    losses = detection_loss(head(bev), targets)
    assert all(torch.isfinite(v) for v in losses.values())
    assert float(losses["num_pos"]) >= 2 and float(losses["loss"].detach()) > 0
    losses["loss"].backward()
    for name, param in head.named_parameters():
        assert param.grad is not None and torch.isfinite(param.grad).all(), name
        assert float(param.grad.abs().sum()) > 0, name

    out = head(bev)
    dets = decode(out.cls_logits, out.box_deltas, out.dir_logits, anchors, score_thr=0.0, nms_iou=0.5, max_per_sample=20, pre_nms=64)
    assert len(dets) == 2
    for d in dets:
        assert d.boxes.shape[1] == 9 and d.boxes.shape[0] == d.scores.shape[0] == d.labels.shape[0] <= 20
        assert (d.scores[:-1] >= d.scores[1:]).all()


def test_heading_follows_a_clear_velocity():
    """A box moving against its yaw faster than the threshold turns by pi; slower, or along
    its yaw, it keeps its yaw; the result stays in [offset, offset + 2 pi)."""
    boxes = torch.tensor([[0, 0, 0, 4, 2, 1.5, 0.2, -5.0, -1.0],     # against, fast: turns
                          [0, 0, 0, 4, 2, 1.5, 0.2, -0.5, 0.0],      # against, slow: keeps
                          [0, 0, 0, 4, 2, 1.5, 2.0, -3.0, 4.0],      # along: keeps
                          [0, 0, 0, 4, 2, 1.5, 3.0, 5.0, 0.0]])      # against: turns, wraps
    yaw = heading_from_motion(boxes, 1.0, dir_offset=-math.pi / 4)
    expected = torch.tensor([0.2 + math.pi, 0.2, 2.0, 3.0 - math.pi])
    torch.testing.assert_close(yaw, expected)
    assert (yaw >= -math.pi / 4).all() and (yaw < 7 * math.pi / 4).all()


def test_heading_of_a_following_class_is_its_velocitys_direction():
    """A walker (``follow``) moving faster than the threshold takes its velocity's direction
    whatever its yaw said, across the axis too; slower it keeps its yaw; a car beside it in
    the same call is only turned by pi."""
    boxes = torch.tensor([[0, 0, 0, 0.7, 0.7, 1.7, 0.3, 0.0, 1.4],     # walker, across its yaw: set
                          [0, 0, 0, 0.7, 0.7, 1.7, 0.3, 0.0, 0.4],     # walker, slow: keeps
                          [0, 0, 0, 4.5, 1.9, 1.5, 0.2, -5.0, -1.0]])  # car, against: turns by pi
    follow = torch.tensor([True, True, False])
    yaw = heading_from_motion(boxes, 1.0, dir_offset=-math.pi / 4, follow=follow)
    torch.testing.assert_close(yaw, torch.tensor([math.pi / 2, 0.3, 0.2 + math.pi]))


def test_decode_sets_the_heading_of_the_named_classes_only():
    """Through decode: one walker anchor and one car anchor, both moving along -x at 2 m/s with
    yaw 0 regressed; with ``heading_follow`` naming the walker's class both end up at pi (the
    walker set, the car turned), and at 1 m/s threshold 3 m/s both keep yaw 0."""
    n_cls, ny, nx = 2, 1, 2
    anchors = torch.zeros(ny, nx, n_cls, 1, 7)
    anchors[..., 3:6] = torch.tensor([1.0, 1.0, 1.0])
    anchors[0, 1, :, :, 0] = 10.0                                      # the second cell 10 m away
    cls = torch.full((1, n_cls, ny, nx), -10.0)
    cls[0, 0, 0, 0] = cls[0, 1, 0, 1] = 5.0                             # car at cell 0, walker at cell 1
    deltas = torch.zeros(1, n_cls * 9, ny, nx)
    deltas[0, 7::9] = -2.0                                              # vx: -2 m/s (not scaled by the anchor)
    dirs = torch.zeros(1, n_cls * 2, ny, nx)
    dirs[0, 0::2] = 5.0                                                 # direction bin 0: yaw 0
    for speed, expected in ((1.0, math.pi), (3.0, 0.0)):
        det, = decode(cls, deltas, dirs, anchors, score_thr=0.5, dir_offset=-math.pi / 4,
                      heading_speed=speed, heading_follow=(1,))
        assert sorted(det.labels.tolist()) == [0, 1]
        torch.testing.assert_close(det.boxes[:, 6], torch.full((2,), expected))


def test_heading_follow_classes_must_be_detected_classes():
    assert ModelConfig(heading_follow_classes=("pedestrian",)).heading_follow_classes == ("pedestrian",)
    with pytest.raises(ConfigError, match=r"heading_follow_classes \['walker'\]"):
        ModelConfig(heading_follow_classes=("walker",))
