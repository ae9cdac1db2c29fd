"""GT-paste (SECOND's ground-truth sampling): objects cut out of other training samples, with their
lidar points, pasted into a sample at their original place in the lidar frame.

Lidar only: the pasted objects are not drawn into the images (a convincing image patch needs
the object's appearance from that camera, its occlusion and lighting). So a fusion model sees a
lidar object its cameras do not show, which teaches it to detect from the lidar when the
camera has no evidence, the behaviour a robust fusion wants anyway (BEVFusion pastes for its
fusion models too). The pasted points are flagged (``Sample.pasted``) so that the camera's
depth supervision ignores them, and the ``camera`` variant does not paste at all: it would be
asked to find objects with no pixels (:func:`clfbev.run.train_config.recipe`).

An object is cut with the points of every sweep, each sweep's points from where the object was
at that sweep's time (:func:`object_points`): a moving object keeps the trail of its older
sweeps that the velocity is learned from. A key-frame box alone would cut a moving car at 8 m/s
off from most of its oldest sweep (3.6 m behind it with 10 sweeps) and paste a car that looks
parked but is labelled moving.

A pasted box must not overlap (BEV IoU > 0) any box already in the sample or pasted before it;
the sample's own points that the pasted object would cover, sweep by sweep as for the cut, are
removed, so each pasted object holds exactly the points it was cut with.

Objects are drawn either uniformly (every object of the database as likely as any other, so the
pasted classes follow the data: half of them cars on the urban preset) or class-balanced (every
class as likely as any other, then an object of it uniformly), after the class-balanced
sampling of Zhu et al. 2019 (CBGS; mmdet3d's nuScenes GT sampler likewise fixes a count per
class): the rare classes (bus, barrier, truck) are pasted as often as the car.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import torch

from clfbev.data import Sample, velocity_or_still
from clfbev.ops.boxes import bev_iou, points_in_boxes


def object_points(points: np.ndarray, box: np.ndarray) -> np.ndarray:
    """(n,) bool: the points (n, >= 5) of the object ``box`` (9,) ``x, y, z, l, w, h, yaw, vx,
    vy`` (key-frame lidar frame, m/s), sweep by sweep.

    A point of time lag ``tau`` (column 4, seconds before the key frame) is tested against the
    box moved back to where the object was then, its centre ``- (vx, vy) tau``. The sweeps are
    motion-compensated into the key frame's lidar frame, so only the object's own motion is
    left; its yaw change over half a second is neglected. An unknown (NaN) velocity counts
    as 0 here (:func:`clfbev.data.velocity_or_still`); the box keeps it NaN.
    """
    velocity = velocity_or_still(box)
    shift = np.zeros((len(points), 3))
    shift[:, :2] = points[:, 4:5] * velocity            # (n, 2): the object's motion since each sweep
    return points_in_boxes(points[:, :3] + shift, box[None, :7])[:, 0]


class SortedPoints:
    """A point cloud (n, >= 5) ordered by x, so that an object's points are looked for only in
    the slab of x that its box reaches over the sweeps, not in the whole cloud: a database cuts
    every object of the training split."""

    def __init__(self, points: np.ndarray) -> None:
        self.points = points
        self.order = np.argsort(points[:, 0], kind="stable")
        self.x = points[self.order, 0]
        self.oldest = float(points[:, 4].max()) if len(points) else 0.0   # s, the oldest sweep's lag

    def object_index(self, box: np.ndarray) -> np.ndarray:
        """Increasing indices of the points :func:`object_points` gives ``box`` (9,)."""
        # A point inside the box has |x - centre_x| <= (l |cos| + w |sin|) / 2; the centre moves
        # back along vx over the sweeps. The 1 mm margin covers float32 rounding.
        half = 0.5 * (abs(box[3] * np.cos(box[6])) + abs(box[4] * np.sin(box[6]))) + 1e-3
        then = box[0] - velocity_or_still(box)[0] * self.oldest
        lo = min(box[0], then) - half
        hi = max(box[0], then) + half
        candidates = np.sort(self.order[np.searchsorted(self.x, lo, "left") : np.searchsorted(self.x, hi, "right")])
        return candidates[object_points(self.points[candidates], box)]


@dataclass(frozen=True)
class GTDatabase:
    """Objects cut from a dataset: per object its box (9,), label and points (k, C), lidar frame."""

    boxes: np.ndarray           # (m, 9)
    labels: np.ndarray          # (m,)
    points: list[np.ndarray]    # m arrays (k_i, C)

    @classmethod
    def from_dataset(cls, dataset, min_points: int = 5) -> "GTDatabase":
        """From every sample of a :class:`clfbev.data.NuScenesDetection`, without its images."""
        return cls.from_arrays((dataset.lidar_and_boxes(i) for i in range(len(dataset))), min_points)

    @classmethod
    def from_arrays(cls, samples, min_points: int = 5) -> "GTDatabase":
        """From an iterable of unaugmented (points (n, C), gt_boxes (M, 9), gt_labels (M,))
        arrays; objects with fewer than ``min_points`` points are skipped (nothing to learn
        from)."""
        boxes, labels, points = [], [], []
        for pts, gt, lab in samples:
            cloud = SortedPoints(pts)
            for box, label in zip(gt, lab):          # a loop over objects; each test is vectorised
                inside = cloud.object_index(box)
                if len(inside) >= min_points:
                    boxes.append(box)
                    labels.append(label)
                    points.append(pts[inside])
        return cls(np.array(boxes, np.float32).reshape(-1, 9), np.array(labels, np.int64), points)

    def __len__(self) -> int:
        return len(self.labels)


def _swept(boxes: np.ndarray, lag: float) -> torch.Tensor:
    """(3m, 7) float64: the boxes (m, 9) at the key frame, ``lag / 2`` and ``lag`` seconds
    before, so that two objects whose sweep trails cross count as overlapping (three places
    leave no gap along the trail for the speeds and sweep spans of road traffic: a car at
    14 m/s moves 3.2 m in half of 0.45 s, less than its length)."""
    key = torch.from_numpy(boxes[:, :7]).double()
    velocity = torch.from_numpy(velocity_or_still(boxes))
    places = []
    for t in (0.0, 0.5 * lag, lag):
        b = key.clone()
        b[:, :2] -= t * velocity
        places.append(b)
    return torch.cat(places)


def draw_objects(db: GTDatabase, k: int, rng: np.random.Generator, balanced: bool) -> np.ndarray:
    """(min(k, len(db)),) distinct database indices in draw order: uniform over the objects, or
    with ``balanced`` uniform over the classes and then over the objects of the class."""
    if not balanced:
        return rng.permutation(len(db))[:k]
    _, inverse, counts = np.unique(db.labels, return_inverse=True, return_counts=True)
    p = 1.0 / (len(counts) * counts[inverse])
    return rng.choice(len(db), size=min(k, len(db)), replace=False, p=p / p.sum())


def gt_paste(sample: Sample, db: GTDatabase, n: int, rng: np.random.Generator, balanced: bool = False) -> Sample:
    """Paste up to ``n`` database objects (drawn with ``rng``, see :func:`draw_objects`) into
    ``sample``: the first that overlap nothing already there, with their points in place of the
    sample's points they cover."""
    if n <= 0 or len(db) == 0:
        return sample
    cloud = SortedPoints(sample.points)
    chosen = _free_objects(db, draw_objects(db, 4 * n, rng, balanced), sample.gt_boxes, cloud.oldest, n)
    if not chosen:
        return sample
    pts = sample.points
    keep = np.ones(len(pts), bool)
    for i in chosen:
        keep[cloud.object_index(db.boxes[i])] = False
    new_pts = np.concatenate([pts[keep], *[db.points[i] for i in chosen]]).astype(pts.dtype)
    was_pasted = np.zeros(len(pts), bool) if sample.pasted is None else sample.pasted
    pasted = np.concatenate([was_pasted[keep], np.ones(len(new_pts) - int(keep.sum()), bool)])
    # A pasted object's still state is not kept in the database: it trains no attribute (-1).
    still = None if sample.gt_still is None else np.concatenate([sample.gt_still, np.full(len(chosen), -1)])
    return replace(sample, points=new_pts, pasted=pasted,
                   gt_boxes=np.concatenate([sample.gt_boxes, db.boxes[chosen]]).astype(sample.gt_boxes.dtype),
                   gt_labels=np.concatenate([sample.gt_labels, db.labels[chosen]]), gt_still=still)


def _free_objects(db: GTDatabase, order: np.ndarray, boxes: np.ndarray, lag: float, n: int) -> list[int]:
    """Up to ``n`` of the database objects ``order`` (in that order) whose swept boxes overlap
    neither a box of ``boxes`` (M, 9) nor an object taken before them."""
    taken = _swept(boxes, lag)
    chosen = []
    for i in order:                      # a few spares for those that collide
        if len(chosen) == n:
            break
        cand = _swept(db.boxes[i : i + 1], lag)
        if len(taken) and (bev_iou(cand, taken) > 0).any():
            continue
        chosen.append(int(i))
        taken = torch.cat([taken, cand])
    return chosen
