"""The still state (clfbev.attributes): the loader reads each box's from its nuScenes attribute
and keeps it with its box through the augmentation; a positive anchor learns its matched box's;
the loss counts only the anchors with one; the head decodes it per box; and a micro model
learns it."""
from __future__ import annotations

import math
from collections import Counter
from dataclasses import replace

import numpy as np
import pytest
import torch
from nuscenes.eval.detection.utils import category_to_detection_name

from clfbev.anchors import make_anchors, match_thresholds
from clfbev.attributes import still_state
from clfbev.augment import crop_to_range
from clfbev.config_file import load_config
from clfbev.data import NuScenesDetection, collate
from clfbev.gt_paste import GTDatabase, gt_paste
from clfbev.head import HeadOutput, decode, per_anchor
from clfbev.model import CLFusionBEV
from clfbev.settings import DataConfig
from clfbev.supervision.assign import assign_targets, stack_targets
from clfbev.supervision.attribute import still_loss, still_targets
from clfbev.supervision.targets import batch_loss, build_targets

pytestmark = pytest.mark.usefixtures("one_thread")

VERSION = "v1.0-sim"
NO_CROP = (-1e4, -1e4, -1e3, 1e4, 1e4, 1e3)


def test_the_state_names_and_the_boxes_without_one():
    assert still_state("car", "vehicle.stopped") == 0 and still_state("bus", "vehicle.parked") == 1
    assert still_state("car", "vehicle.moving") == -1 and still_state("pedestrian", "pedestrian.moving") == -1
    assert still_state("pedestrian", "pedestrian.standing") == 0
    assert still_state("bicycle", "cycle.with_rider") == 0 and still_state("motorcycle", "cycle.without_rider") == 1
    assert still_state("barrier", "") == -1 and still_state("car", "cycle.with_rider") == -1


def test_the_loader_reads_each_box_state_and_the_augmentation_keeps_it_with_its_box(tiny_dataset):
    ds = NuScenesDetection(tiny_dataset, VERSION, "sim-train", DataConfig(min_points=1, point_range=NO_CROP))
    nusc, states = ds.nusc, Counter()
    for i, token in enumerate(ds.sample_tokens):
        sample = ds[i]
        want = Counter()
        for ann in (nusc.get("sample_annotation", t) for t in nusc.get("sample", token)["anns"]):
            name = category_to_detection_name(ann["category_name"])
            if name is None or ann["num_lidar_pts"] < 1:
                continue
            attrs = [nusc.get("attribute", t)["name"] for t in ann["attribute_tokens"]]
            want[(ds.cfg.class_names.index(name), max((still_state(name, a) for a in attrs), default=-1))] += 1
        assert Counter(zip(sample.gt_labels.tolist(), sample.gt_still.tolist())) == want
        states.update(sample.gt_still.tolist())
    assert states[0] > 0 and states[1] > 0 and states[-1] > 0       # the set has all three

    s = ds[0]
    boxes_and_states = {tuple(b): st for b, st in zip(s.gt_boxes.tolist(), s.gt_still.tolist())}
    cropped = crop_to_range(s, (-20.0, -20.0, -5.0, 20.0, 20.0, 3.0))
    assert 0 < len(cropped.gt_boxes) < len(s.gt_boxes)
    assert [boxes_and_states[tuple(b)] for b in cropped.gt_boxes.tolist()] == cropped.gt_still.tolist()
    db = GTDatabase.from_dataset(ds)
    pasted = gt_paste(s, db, 6, np.random.default_rng(0))
    n = len(s.gt_boxes)
    assert len(pasted.gt_boxes) > n and len(pasted.gt_still) == len(pasted.gt_boxes)
    assert np.array_equal(pasted.gt_still[:n], s.gt_still) and (pasted.gt_still[n:] == -1).all()
    assert collate([replace(s, gt_still=None)]).gt_still[0].tolist() == [-1] * n


def _car(x, y, yaw=0.0):
    return [x, y, -1.0, 4.5, 1.9, 1.6, yaw, 0.0, 0.0]


def test_a_positive_anchor_takes_its_boxes_state_and_decodes_with_it():
    names = ("car", "pedestrian")
    ny, nx = 4, 16
    anchors = make_anchors(names, (ny, nx), (0.0, 0.0, -5.0, 16.0, 16.0, 3.0))
    gt = torch.tensor([_car(3.7, 6.0), _car(10.5, 2.0, math.pi / 2), [13.5, 14.0, -1.0, 0.7, 0.7, 1.7, 0.0, 0.0, 0.0]])
    labels, states = torch.tensor([0, 0, 1]), torch.tensor([1, 0, -1])
    anchor = stack_targets([assign_targets(anchors, gt, labels, match_thresholds(names))])
    target = still_targets(anchor, [states])
    pos = anchor.positives[0]
    assert int(pos.sum()) >= 3
    assert torch.equal(target[0, pos], states[anchor.matched_gt[0, pos]]) and (target[0, ~pos] == -1).all()

    # Decoded: each box keeps its anchor's still logit.
    n_anchors = len(names) * 2

    def to_map(x):                                              # (N, k) -> (1, A * k, ny, nx)
        k = x.shape[1]
        return x.reshape(1, ny, nx, n_anchors, k).permute(0, 3, 4, 1, 2).reshape(1, n_anchors * k, ny, nx)

    still_map = to_map(torch.where(target[0] == 1, 5.0, -5.0)[:, None])
    out = HeadOutput(to_map(torch.where(pos, 8.0, -8.0)[:, None]), to_map(anchor.box_targets[0]),
                     to_map(torch.nn.functional.one_hot(anchor.dir_targets[0], 2).float() * 8.0))
    dets = decode(out.cls_logits, out.box_deltas, out.dir_logits, anchors, 0.3, 0.2, 50, 100,
                  still_logits=still_map)[0]
    assert len(dets.boxes) == 3
    order = torch.argsort(dets.boxes[:, 0])
    assert dets.still[order].tolist() == [5.0, -5.0, -5.0]
    plain = decode(out.cls_logits, out.box_deltas, out.dir_logits, anchors, 0.3, 0.2, 50, 100)[0]
    assert plain.still is None and torch.equal(plain.boxes, dets.boxes)


def test_the_loss_counts_only_the_anchors_with_a_state():
    torch.manual_seed(0)
    logits = torch.randn(2, 50, requires_grad=True)
    target = torch.randint(-1, 2, (2, 50))
    loss = still_loss(logits, target)
    known = target >= 0
    p = torch.sigmoid(logits.detach()[known])
    t = target[known].float()
    assert loss.detach().item() == pytest.approx(float(-(t * p.log() + (1 - t) * (1 - p).log()).mean()), rel=1e-6)
    loss.backward()
    assert (logits.grad[~known] == 0).all() and (logits.grad[known] != 0).all()
    none = still_loss(logits, torch.full_like(target, -1))
    assert none.item() == 0.0 and none.requires_grad


def test_a_micro_model_learns_the_states_of_its_boxes(tiny_dataset, micro):
    micro_cfg = load_config(micro)
    cfg = replace(micro_cfg, loss=replace(micro_cfg.loss, attribute=1.0))
    ds = NuScenesDetection(tiny_dataset, VERSION, "sim-train", cfg.data_config())
    batch = collate([ds[0], ds[1]])
    torch.manual_seed(0)
    model = CLFusionBEV(cfg, "lidar")
    opt = torch.optim.Adam(model.parameters(), lr=3e-3)
    first = None
    for _ in range(20):
        losses = batch_loss(model, batch)
        first = losses["loss_still"].item() if first is None else first
        opt.zero_grad()
        losses["loss"].backward()
        opt.step()
    assert "loss_still" in losses and losses["loss_still"].item() < 0.3 * first, (first, losses["loss_still"].item())
    # Its still logits name the states of the boxes it matched.
    model.eval()
    with torch.no_grad():
        head = model(batch).head
    targets = build_targets(batch, cfg, model.anchors, cameras=False)
    logits = per_anchor(head.still_logits, head.cls_logits.shape[1])
    known = targets.still >= 0
    assert int(known.sum()) > 20
    assert ((logits[known] >= 0).long() == targets.still[known]).float().mean() > 0.9

