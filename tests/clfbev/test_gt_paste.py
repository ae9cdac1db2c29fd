"""GT-paste puts database objects, with exactly their points, where nothing else is."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from clfbev.config import tiny
from clfbev.data import NuScenesDetection
from clfbev.gt_paste import GTDatabase, gt_paste, points_in_box
from clfbev.ops.boxes import bev_iou

pytestmark = pytest.mark.usefixtures("one_thread")


def test_points_in_box_rotated():
    box = np.array([1.0, 2.0, 0.0, 4.0, 2.0, 2.0, np.pi / 2])   # length along y after the rotation
    pts = np.array([[1.0, 3.9, 0.0], [1.0, 4.1, 0.0], [1.9, 2.0, 0.5], [2.1, 2.0, 0.0], [1.0, 2.0, 1.1]])
    np.testing.assert_array_equal(points_in_box(pts, box), [True, False, True, False, False])


def test_paste_adds_objects_with_their_points(tiny_dataset):
    train = NuScenesDetection(tiny_dataset, "v1.0-sim", "sim-train", tiny().data_config())
    val = NuScenesDetection(tiny_dataset, "v1.0-sim", "sim-val", tiny().data_config())
    db = GTDatabase.build(train[i] for i in range(len(train)))
    assert len(db) > 10 and all(len(p) >= 5 for p in db.points)
    s = val[0]
    out = gt_paste(s, db, 8, np.random.default_rng(0))
    n0, n1 = len(s.gt_boxes), len(out.gt_boxes)
    assert n1 > n0
    torch.testing.assert_close(out.gt_boxes[:n0], s.gt_boxes)
    new = out.gt_boxes[n0:].double()
    assert (bev_iou(new[:, :7], out.gt_boxes[:n0, :7].double()) == 0).all()      # no collision with the sample
    iou = bev_iou(new[:, :7], new[:, :7]) - torch.eye(len(new), dtype=torch.float64)
    assert (iou <= 1e-9).all()                                                      # nor with each other
    pts = out.points.numpy()
    for box in new.numpy():                          # each pasted box holds its database points exactly
        k = int(np.flatnonzero((np.abs(db.boxes - box.astype(np.float32)).max(1) == 0))[0])
        inside = pts[points_in_box(pts, box)]
        assert sorted(map(tuple, inside)) == sorted(map(tuple, db.points[k]))
    again = gt_paste(s, db, 8, np.random.default_rng(0))
    torch.testing.assert_close(again.points, out.points)
