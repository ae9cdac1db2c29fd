"""GT-paste puts database objects, with exactly their points of every sweep, where nothing else is."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from clfbev.config import tiny
from clfbev.data import NuScenesDetection, Sample
from clfbev.gt_paste import GTDatabase, SortedPoints, draw_objects, gt_paste, object_points
from clfbev.ops.boxes import bev_iou

pytestmark = pytest.mark.usefixtures("one_thread")


def test_object_points_follow_the_object_back_in_time():
    """A car at 10 m/s along +x: its point of 0.3 s ago is 3 m behind the key-frame box and
    belongs to it; a key-frame point there does not, nor an old point where the car is now."""
    box = np.array([0.0, 0.0, 0.0, 4.0, 2.0, 1.5, 0.0, 10.0, 0.0], np.float32)
    pts = np.array([[-3.5, 0, 0, 0, 0.3],     # 0.3 s ago the car spanned x in [-5, -1]
                    [-3.5, 0, 0, 0, 0.0],     # at the key frame it spans [-2, 2]
                    [1.5, 0, 0, 0, 0.3],      # where the car is now, but 0.3 s ago: empty then
                    [1.5, 0, 0, 0, 0.0]], np.float32)
    np.testing.assert_array_equal(object_points(pts, box), [True, False, False, True])
    parked = box.copy()
    parked[7] = np.nan                        # unknown velocity: the key-frame box for every sweep
    np.testing.assert_array_equal(object_points(pts, parked), [False, False, True, True])
    db = GTDatabase.from_arrays([(pts, box[None], np.array([0]))], min_points=1)
    np.testing.assert_array_equal(db.points[0], pts[[0, 3]])       # the trail is cut with the car


def test_sorted_points_find_exactly_the_object_points():
    """The x-slab search gives what the test on every point gives, for moving boxes of any yaw
    and direction, boxes at the cloud's edge and beyond it."""
    g = np.random.default_rng(0)
    pts = np.concatenate([g.uniform(-20, 20, (20000, 3)), g.random((20000, 1)),
                          g.integers(0, 10, (20000, 1)) * 0.05], axis=1).astype(np.float32)
    pts[:, 2] *= 0.1
    cloud = SortedPoints(pts)
    hits = 0
    for _ in range(200):
        box = np.concatenate([g.uniform(-22, 22, 2), [0.0], g.uniform(0.3, 6, 2), [2.0], g.uniform(-np.pi, np.pi, 1),
                              g.uniform(-15, 15, 2)]).astype(np.float32)
        expected = np.flatnonzero(object_points(pts, box))
        np.testing.assert_array_equal(cloud.object_index(box), expected)
        hits += len(expected) > 0
    assert hits > 100
    assert len(SortedPoints(pts[:0]).object_index(box)) == 0


def test_paste_keeps_clear_of_sweep_trails():
    """A sample car parked 4.5 m behind where a database car at 10 m/s is now: the key-frame
    boxes do not touch, but the database car drove through the parked one 0.4 s ago."""
    moving = np.array([[0.0, 0.0, 0.0, 4.0, 2.0, 1.5, 0.0, 10.0, 0.0]], np.float32)
    db = GTDatabase(moving, np.array([0]), [np.array([[0, 0, 0, 0, 0.0], [-4, 0, 0, 0, 0.4]], np.float32)])
    parked = np.array([[-4.5, 0.0, 0.0, 4.0, 2.0, 1.5, 0.0, 0.0, 0.0]], np.float32)
    pts = np.array([[-4.5, 0.0, 0.0, 0.0, 0.0], [-4.5, 0.0, 0.0, 0.0, 0.45]], np.float32)
    s = Sample(images=np.zeros(0), intrinsics=np.zeros(0), T_lidar_from_cam=np.zeros(0),
               img_aug=np.zeros(0), points=pts, gt_boxes=parked, gt_labels=np.array([0]),
               T_global_from_lidar=np.eye(4), sample_token="t")
    assert len(gt_paste(s, db, 1, np.random.default_rng(0)).gt_boxes) == 1      # not pasted
    far = replace(s, gt_boxes=parked + np.array([[-6.0, 0, 0, 0, 0, 0, 0, 0, 0]], np.float32))
    assert len(gt_paste(far, db, 1, np.random.default_rng(0)).gt_boxes) == 2    # clear of it: pasted


def test_paste_adds_objects_with_their_points(tiny_dataset):
    train = NuScenesDetection(tiny_dataset, "v1.0-sim", "sim-train", tiny().data_config())
    val = NuScenesDetection(tiny_dataset, "v1.0-sim", "sim-val", tiny().data_config())
    db = GTDatabase.from_dataset(train)                        # without the images
    assert len(db) > 10 and all(len(p) >= 5 for p in db.points)
    full = GTDatabase.from_arrays((s.points, s.gt_boxes, s.gt_labels)
                                  for s in (train[i] for i in range(len(train))))
    assert np.array_equal(full.boxes, db.boxes) and np.array_equal(full.labels, db.labels)  # as the full samples
    assert all(np.array_equal(a, b) for a, b in zip(full.points, db.points))
    s = val[0]
    out = gt_paste(s, db, 8, np.random.default_rng(0))
    n0, n1 = len(s.gt_boxes), len(out.gt_boxes)
    assert n1 > n0
    assert np.array_equal(out.gt_boxes[:n0], s.gt_boxes) and np.array_equal(out.gt_labels[:n0], s.gt_labels)
    new = torch.from_numpy(out.gt_boxes[n0:]).double()
    assert (bev_iou(new[:, :7], torch.from_numpy(out.gt_boxes[:n0, :7]).double()) == 0).all()   # no collision with the sample
    iou = bev_iou(new[:, :7], new[:, :7]) - torch.eye(len(new), dtype=torch.float64)
    assert (iou <= 1e-9).all()                                                      # nor with each other
    pts, n_pasted = out.points, 0
    for box in new.numpy():                          # each pasted object holds its database points exactly
        k = int(np.flatnonzero((np.abs(db.boxes - box.astype(np.float32)).max(1) == 0))[0])
        inside = pts[object_points(pts, box)]
        assert sorted(map(tuple, inside)) == sorted(map(tuple, db.points[k]))
        n_pasted += len(db.points[k])
    assert out.pasted.sum() == n_pasted                  # exactly the pasted points are flagged
    again = gt_paste(s, db, 8, np.random.default_rng(0))
    assert np.array_equal(again.points, out.points)


def test_balanced_draw_gives_every_class_the_same_share():
    """900 objects of class 0, 100 of class 1, 10 of class 2: a uniform draw follows the counts,
    a class-balanced one gives each class a third; draws are distinct indices either way."""
    labels = np.repeat([0, 1, 2], [900, 100, 10])
    db = GTDatabase(np.zeros((len(labels), 9), np.float32), labels, [np.zeros((5, 5), np.float32)] * len(labels))
    firsts = {True: [], False: []}
    for seed in range(3000):
        for balanced in (True, False):
            order = draw_objects(db, 8, np.random.default_rng(seed), balanced)
            assert len(set(order.tolist())) == 8
            firsts[balanced].append(labels[order[0]])
    share = {b: np.bincount(firsts[b], minlength=3) / 3000 for b in firsts}
    np.testing.assert_allclose(share[True], [1 / 3] * 3, atol=0.03)
    np.testing.assert_allclose(share[False], [900 / 1010, 100 / 1010, 10 / 1010], atol=0.02)
    assert len(draw_objects(db, 5000, np.random.default_rng(0), True)) == len(db)   # all, when asked for more
