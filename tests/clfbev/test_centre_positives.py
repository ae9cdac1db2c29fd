"""Centre sampling on top of SECOND's matching (``min_positives``): a small object trains the k
anchors of its class nearest its centre, checked against a brute-force reference over every
anchor; k = 1 is exactly the old matching."""
from __future__ import annotations

from dataclasses import fields

import pytest
import torch

from clfbev.anchors import make_anchors, match_thresholds
from clfbev.settings import ANCHOR_SIZES
from clfbev.supervision.assign import assign_targets

pytestmark = pytest.mark.usefixtures("one_thread")
NAMES = ("car", "traffic_cone", "bicycle")
CONE = NAMES.index("traffic_cone")


def grid(n: int = 8):
    """n x n cells of 1 m: centres 0.5 .. n - 0.5 on both axes."""
    return make_anchors(NAMES, (n, n), (0.0, 0.0, -5.0, float(n), float(n), 3.0))


def box(cls: str, x: float, y: float, yaw: float = 0.0) -> list[float]:
    l, w, h = ANCHOR_SIZES[cls]
    return [x, y, -1.0, l, w, h, yaw, 0.0, 0.0]


def nearest_rows(anchors, x: float, y: float, cls: int, rot: int, k: int) -> list[int]:
    """Brute force: the k anchors of (cls, rot) nearest (x, y), over the whole grid."""
    ny, nx, n_cls, n_rot, _ = anchors.shape
    centres = anchors[:, :, cls, rot, :2].reshape(-1, 2).double()
    d = torch.hypot(centres[:, 0] - x, centres[:, 1] - y)
    cells = torch.sort(d, stable=True).indices[:k]
    return sorted(int(c) * n_cls * n_rot + cls * n_rot + rot for c in cells)


def test_a_cone_trains_its_k_nearest_anchors():
    anchors = grid()
    thresholds = match_thresholds(NAMES)
    for k in (1, 2, 3, 4):
        t = assign_targets(anchors, torch.tensor([box("traffic_cone", 2.3, 2.2)]), torch.tensor([CONE]),
                           thresholds, min_positives=k)
        positives = torch.nonzero(t.labels > 0).flatten().tolist()
        assert positives == nearest_rows(anchors, 2.3, 2.2, CONE, 0, k), k
        assert (t.labels[positives] == CONE + 1).all() and (t.matched_gt[positives] == 0).all()
        assert (t.box_weights[positives] == 1).all()


def test_k_1_is_the_old_matching_and_cars_keep_their_matches():
    anchors = grid(16)
    thresholds = match_thresholds(NAMES)
    gt = torch.tensor([box("car", 5.2, 6.7, 0.3), box("traffic_cone", 9.4, 3.3), box("bicycle", 12.1, 11.8, 1.4)])
    labels = torch.tensor([0, CONE, 2])
    old = assign_targets(anchors, gt, labels, thresholds)
    same = assign_targets(anchors, gt, labels, thresholds, min_positives=1)
    assert all(torch.equal(getattr(old, f.name), getattr(same, f.name)) for f in fields(old))
    more = assign_targets(anchors, gt, labels, thresholds, min_positives=4)
    kept = old.labels > 0
    assert torch.equal(more.labels[kept], old.labels[kept]) and torch.equal(more.matched_gt[kept], old.matched_gt[kept])
    for g in range(3):
        assert int(((more.labels > 0) & (more.matched_gt == g)).sum()) >= 4, g


def test_an_anchor_two_objects_reach_goes_to_the_nearer():
    anchors = grid()
    thresholds = match_thresholds(NAMES)
    a, b = (3.2, 3.1), (3.9, 3.05)       # two cones 0.7 m apart share anchors around x = 3.5
    t = assign_targets(anchors, torch.tensor([box("traffic_cone", *a), box("traffic_cone", *b)]),
                       torch.tensor([CONE, CONE]), thresholds, min_positives=4)
    centres = anchors.reshape(-1, 7)[:, :2].double()
    for row in torch.nonzero(t.labels > 0).flatten().tolist():
        da, db = (float(torch.hypot(*(centres[row] - torch.tensor(p, dtype=torch.float64)))) for p in (a, b))
        owner = int(t.matched_gt[row])
        reach_a = row in nearest_rows(anchors, *a, CONE, 0, 4)
        reach_b = row in nearest_rows(anchors, *b, CONE, 0, 4)
        if reach_a and reach_b:
            assert owner == (0 if da <= db else 1), row
        else:
            assert owner == (0 if reach_a else 1), row


def test_out_of_range_is_refused():
    with pytest.raises(ValueError, match="min_positives"):
        assign_targets(grid(), torch.zeros((0, 9)), torch.zeros(0, dtype=torch.long), match_thresholds(NAMES),
                       min_positives=5)
