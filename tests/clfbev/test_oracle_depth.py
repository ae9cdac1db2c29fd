"""The oracle lift's depth (``cam_oracle_depth``) is projected once, in the loader, and carried in
``Batch.depth_bins``: the model lifts with it exactly as it did when it projected the lidar in its
forward, on every path that runs it (the training collate, with its depth targets; the
evaluation's collate; the BatchNorm re-estimate), and nothing is projected without the oracle.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from clfbev.config_file import load_config
from clfbev.data import NuScenesDetection, collate
from clfbev.geometry import CameraGeometry, nearest_depth_bins
from clfbev.model import CLFusionBEV
from clfbev.run.epochs import precise_batchnorm
from clfbev.run.evaluate import predict_split
from clfbev.run.train_config import TrainConfig
from clfbev.supervision.targets import TrainingCollate, batch_loss

pytestmark = pytest.mark.usefixtures("one_thread")


class ProjectingInForward(CLFusionBEV):
    """The reference: the oracle's bins projected in the forward from the batch's own points,
    pasted ones left out, whatever the batch carries."""

    def _oracle_bins(self, batch):
        return nearest_depth_bins(batch.points, CameraGeometry.of_batch(batch, self.cfg), batch.pasted or None)


@pytest.fixture(scope="module")
def oracle(tiny_dataset, micro):
    """The micro config with the oracle on, its training split, and two of its samples, the first
    with a third of its points marked pasted."""
    cfg = replace(load_config(micro), cam_oracle_depth=True)
    ds = NuScenesDetection(tiny_dataset, "v1.0-sim", "sim-train", cfg.data_config())
    s0, s1 = ds[0], ds[1]
    pasted = np.arange(len(s0.points)) % 3 == 0
    return cfg, ds, [replace(s0, pasted=pasted), s1]


def models(cfg) -> tuple[CLFusionBEV, CLFusionBEV]:
    """A camera model reading ``Batch.depth_bins`` and the reference with the same weights."""
    torch.manual_seed(0)
    model = CLFusionBEV(cfg, "camera")
    reference = ProjectingInForward(cfg, "camera")
    reference.load_state_dict(model.state_dict())
    return model, reference


def outputs(model, batch) -> list[torch.Tensor]:
    """Every tensor the forward gives, the camera BEV first."""
    with torch.no_grad():
        out = model(batch)
        bev = model.bev_features(batch)
    head = [t for t in vars(out.head).values() if t is not None]
    return [bev, *head, out.depth]


def test_the_loaders_bins_lift_bit_for_bit_as_the_projection_in_the_forward(oracle):
    cfg, _, samples = oracle
    model, reference = models(cfg)
    model.eval()
    reference.eval()
    train_batch, targets = TrainingCollate(cfg)(samples)
    eval_batch = collate(samples, cfg)
    # The training collate hands the model its depth targets themselves: one projection.
    assert train_batch.depth_bins is targets.depth
    for batch in (train_batch, eval_batch):
        cams = CameraGeometry.of_batch(batch, cfg)
        projected = nearest_depth_bins(batch.points, cams, batch.pasted)
        assert batch.depth_bins.dtype == torch.int64 and torch.equal(batch.depth_bins, projected)
        assert (projected >= 0).float().mean() > 0.3                  # most cells see a lidar point
        # Pasted points are left out: with them the nearest point of some cells changes.
        assert not torch.equal(projected, nearest_depth_bins(batch.points, cams))
        new, old = outputs(model, batch), outputs(reference, replace(batch, depth_bins=None))
        assert len(new) == len(old) and all(torch.equal(a, b) for a, b in zip(new, old))
        # ... and the bins do reach the lift: the predicted depth gives another camera BEV.
        model.cfg = replace(cfg, cam_oracle_depth=False)
        assert not torch.allclose(outputs(model, batch)[0], new[0])
        model.cfg = cfg
    # The training loss of a batch collated without them projects them with its targets.
    torch.manual_seed(1)
    plain = batch_loss(model.train(), collate(samples))
    reference.train()
    torch.manual_seed(1)
    expected = batch_loss(reference, collate(samples))
    assert plain.keys() == expected.keys() and all(torch.equal(plain[k], expected[k]) for k in plain)


def test_without_the_oracle_nothing_is_projected_and_without_its_bins_the_oracle_refuses(oracle):
    cfg, _, samples = oracle
    off = replace(cfg, cam_oracle_depth=False)
    assert collate(samples, off).depth_bins is None and collate(samples).depth_bins is None
    batch, targets = TrainingCollate(off)(samples)
    assert batch.depth_bins is None and targets.depth is not None
    moved = collate(samples, cfg).to("cpu")
    assert torch.equal(moved.depth_bins, collate(samples, cfg).depth_bins)
    model, _ = models(cfg)
    with pytest.raises(ValueError, match="Batch.depth_bins"):
        model(collate(samples))


def test_the_evaluation_and_the_batchnorm_reestimate_lift_with_the_loaders_bins(oracle):
    cfg, ds, _ = oracle
    model, reference = models(cfg)
    tc = TrainConfig(batch_size=2, precise_bn_batches=1)
    precise_batchnorm(model, ds, tc, None)
    precise_batchnorm(reference, ds, tc, None)
    state, expected = model.state_dict(), reference.state_dict()
    assert all(torch.equal(state[k], expected[k]) for k in expected)
    predicted = predict_split(model, ds, batch_size=2, score_thr=0.0)
    assert predicted == predict_split(reference, ds, batch_size=2, score_thr=0.0)
    assert sum(len(boxes) for boxes in predicted.values()) > 0
