"""The camera's depth supervision: targets through the image augmentation, the loss, the resize and
crop of the loader, and how many lidar points reach the VFE."""

import math
from dataclasses import replace

import numpy as np
import pytest
import torch

from clfbev.augment import image_matrix
from clfbev.camera_encoder import CameraEncoder, lift_geometry, oracle_depth, splat
from clfbev.config import tiny
from clfbev.data import NuScenesDetection, collate, resize_and_crop
from clfbev.errors import ConfigError
from clfbev.geometry import CameraGeometry, nearest_depth_bins
from clfbev.model import CLFusionBEV
from clfbev.supervision.depth import depth_loss
from clfbev.supervision.targets import build_targets

pytestmark = pytest.mark.usefixtures("one_thread")

K_1600 = torch.tensor([[1266.0, 0.0, 800.0], [0.0, 1266.0, 450.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
BINS = (1.0, 52.0, 1.0)


def front_camera() -> torch.Tensor:
    """(4, 4) T_lidar_from_cam of a camera at the lidar origin looking along lidar x."""
    T = torch.eye(4, dtype=torch.float64)
    T[:3, :3] = torch.tensor([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]], dtype=torch.float64)
    return T


def test_resize_and_crop_keeps_the_aspect_and_the_bottom():
    img = np.zeros((396, 704, 3), np.uint8)
    img[380:390, 100:110] = 255        # a block near the bottom
    img[0:4] = 90                      # sky rows that the crop removes
    out, A = resize_and_crop(img, (192, 352))
    assert out.shape == (192, 352, 3)
    np.testing.assert_allclose(A, [[0.5, 0, 0], [0, 0.5, -6.0], [0, 0, 1]])
    centre = A @ np.array([105.0, 385.0, 1.0])    # the block's centre, original pixels
    r, c = int(centre[1]), int(centre[0])
    assert out[r, c].min() == 255 and (out[:2] < 90).all()
    padded, A2 = resize_and_crop(np.full((100, 400, 3), 7, np.uint8), (192, 352))   # too short: pad on top
    assert padded.shape == (192, 352, 3) and (padded[:104] == 0).all() and (padded[104:] == 7).all()
    assert A2[1, 2] == 104


@pytest.mark.parametrize("flip", [False, True])
def test_a_point_lands_in_its_bin_and_feature_cell_through_resize_crop_and_flip(flip):
    H, W, s = 192, 352, 8
    _, A = resize_and_crop(np.zeros((900, 1600, 3), np.uint8), (H, W))
    M = image_matrix(1.1, (9.0, 13.0), (H, W), flip) @ A           # the training image augmentation
    img_aug = torch.from_numpy(M)[None, None]
    # Lidar point 20.3 m ahead: camera (x, y, z) = (1.0, -0.5, 20.3).
    p = torch.tensor([[20.3, -1.0, 0.5, 0.5, 0.0]], dtype=torch.float64)
    u0, v0 = 1266.0 * 1.0 / 20.3 + 800.0, 1266.0 * -0.5 / 20.3 + 450.0
    u1, v1 = 0.22 * u0, (198 / 900) * v0 - 6.0                    # resize 1600 -> 352, crop 6 rows
    u2, v2 = 1.1 * u1 - 13.0, 1.1 * v1 - 9.0                      # augmentation: resize, crop
    if flip:
        u2 = W - u2
    row, col = math.floor(v2 / s), math.floor(u2 / s)
    behind = torch.tensor([[40.6, -2.0, 1.0, 0.5, 0.0]], dtype=torch.float64)   # same ray, twice as far
    older = torch.tensor([[10.15, -0.5, 0.25, 0.5, 0.05]], dtype=torch.float64)  # same ray, an earlier sweep
    pasted = torch.tensor([[15.225, -0.75, 0.375, 0.5, 0.0]], dtype=torch.float64)  # same ray, pasted
    points = torch.cat([behind, p, older, pasted])
    cams = CameraGeometry(K_1600[None, None], front_camera()[None, None], img_aug, (H, W), s, BINS)
    t = nearest_depth_bins([points], cams, ignore=[torch.tensor([False, False, False, True])])
    assert t.shape == (1, 1, H // s, W // s)
    assert t[0, 0, row, col] == math.floor((20.3 - 1.0) / 1.0)      # the nearest kept point wins
    assert (t >= 0).sum() == 1


def test_the_oracle_lift_puts_a_cells_context_on_its_lidar_point():
    H, W, s = 192, 352, 8
    _, A = resize_and_crop(np.zeros((900, 1600, 3), np.uint8), (H, W))
    cams = CameraGeometry(K_1600[None, None], front_camera()[None, None], torch.from_numpy(A)[None, None],
                          (H, W), s, BINS)
    point = torch.tensor([[20.3, -1.0, 0.5, 0.5, 0.0]], dtype=torch.float64)
    bins = nearest_depth_bins([point], cams)                                # (1, 1, h, w), one known cell
    row, col = (int(i) for i in torch.nonzero(bins[0, 0] >= 0)[0])
    torch.manual_seed(0)
    D = 51
    predicted = torch.softmax(torch.randn(1, 1, D, H // s, W // s), dim=2)
    lifted = oracle_depth(predicted, bins)
    known = bins[0, 0] >= 0
    assert torch.equal(lifted[0, 0][:, ~known], predicted[0, 0][:, ~known])   # the rest keep the prediction
    assert torch.equal(lifted[0, 0, :, row, col], torch.nn.functional.one_hot(bins[0, 0, row, col], D).float())

    # The cell's frustum point at its oracle bin lies on the lidar point: within half a bin
    # along the ray, within half a feature cell (8 px at 20 m: 0.29 m) across it.
    geom = lift_geometry(cams)                                         # (1, 1, D, h, w, 3) lidar xyz
    x, y, _ = geom[0, 0, bins[0, 0, row, col], row, col].tolist()
    assert abs(x - 20.3) <= 0.5 and abs(y + 1.0) <= 0.3
    # Lifted alone (the prediction zeroed), the cell's context lands in that BEV cell and no other.
    pc_range, voxel = (-51.2, -51.2, -5.0, 51.2, 51.2, 3.0), (0.8, 0.8, 8.0)
    alone = oracle_depth(torch.zeros_like(predicted), bins)
    bev = splat(alone, torch.ones(1, 1, 1, H // s, W // s), geom, pc_range, voxel)[0, 0, 0]
    assert torch.nonzero(bev).tolist() == [[int((y + 51.2) // 0.8), int((x + 51.2) // 0.8)]]
    assert float(bev.sum()) == 1.0


def test_the_model_lifts_with_the_cells_the_depth_loss_trains(tiny_dataset):
    cfg = replace(tiny(), cam_oracle_depth=True)
    ds = NuScenesDetection(tiny_dataset, "v1.0-sim", "all", cfg.data_config())
    batch = collate([ds[0]], cfg)                     # the oracle's bins are projected here
    model = CLFusionBEV(cfg, "camera").eval()
    bins = model._oracle_bins(batch)
    assert torch.equal(bins, build_targets(batch, cfg, model.anchors).depth)
    assert (bins >= 0).float().mean() > 0.3                            # most cells see a lidar point
    with torch.no_grad():
        oracle_bev = model.bev_features(batch)
        model.cfg = replace(cfg, cam_oracle_depth=False)
        predicted_bev = model.bev_features(batch)
    assert not torch.allclose(oracle_bev, predicted_bev)


def expected_cell(p: torch.Tensor, k: int) -> torch.Tensor:
    """BEVDepth's BCE of one cell's (D,) distribution against the one-hot bin k, summed over bins."""
    return -(torch.log(p[k]) + torch.log(1 - p).sum() - torch.log(1 - p[k]))


def test_depth_loss_is_bevdepths_bce_and_decreases_in_training():
    torch.manual_seed(0)
    probs = torch.softmax(torch.randn(1, 2, 5, 3, 4), dim=2)
    t = torch.full((1, 2, 3, 4), -1)
    t[0, 0, 1, 2], t[0, 1, 0, 0] = 3, 0
    expected = -(torch.log(probs[0, 0, 3, 1, 2]) + torch.log(1 - probs[0, 0, :, 1, 2]).sum()
                 - torch.log(1 - probs[0, 0, 3, 1, 2]) + torch.log(probs[0, 1, 0, 0, 0])
                 + torch.log(1 - probs[0, 1, :, 0, 0]).sum() - torch.log(1 - probs[0, 1, 0, 0, 0])) / 2
    torch.testing.assert_close(depth_loss(probs, t), expected)
    assert depth_loss(probs, torch.full_like(t, -1)) == 0

    # Weighted by the target's depth (bins of 1 m from 1 m: centres 4.5 m and 1.5 m), normalised
    # to a mean weight of 1; each cell's summed BCE as above.
    cell = torch.stack([expected_cell(probs[0, 0, :, 1, 2], 3), expected_cell(probs[0, 1, :, 0, 0], 0)])
    weight = torch.tensor([4.5, 1.5]) ** 2
    torch.testing.assert_close(depth_loss(probs, t, (1.0, 6.0, 1.0), 2.0),
                               (cell * weight / weight.mean()).sum() / 2)
    torch.testing.assert_close(depth_loss(probs, t, (1.0, 6.0, 1.0), 0.0), expected)

    # A small camera encoder fitting the depth of two images: the loss falls.
    enc = CameraEncoder(18, 8, 16, BINS, 8, (64, 176), 8, (-51.2, -51.2, -5.0, 51.2, 51.2, 3.0), (0.8, 0.8, 8.0))
    images = torch.randn(1, 2, 3, 64, 176)
    targets = torch.randint(0, 51, (1, 2, 8, 22))
    targets[:, :, :2] = -1
    opt = torch.optim.AdamW(enc.parameters(), lr=3e-3)
    losses = []
    for _ in range(25):
        depth, _, _ = enc.image_features(images)
        loss = depth_loss(depth, targets)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(float(loss.detach()))
    assert losses[-1] < 0.8 * losses[0]


@pytest.mark.parametrize("n_sweeps", [3, tiny().n_sweeps])
def test_the_vfe_gets_at_least_95_percent_of_a_multi_sweep_sample(tiny_dataset, n_sweeps):
    cfg = replace(tiny(), n_sweeps=n_sweeps)
    ds = NuScenesDetection(tiny_dataset, "v1.0-sim", "all", cfg.data_config())
    sample = ds[len(ds) - 1]                                   # the last key frame has earlier sweeps
    lags = np.unique(sample.points[:, 4]).size
    assert lags == 3 if n_sweeps == 3 else lags >= 3
    model = CLFusionBEV(cfg, "lidar").eval()
    seen = []
    model.lidar_encoder.vfe.register_forward_hook(lambda m, inputs, out: seen.append(inputs[0].shape[0]))
    with torch.no_grad():
        model.lidar_encoder([torch.from_numpy(sample.points)])
    assert seen[0] >= 0.95 * len(sample.points)
    assert seen[0] == len(sample.points)          # in range (the loader crops) and under max_voxels


def test_depth_range_power_must_not_be_negative():
    with pytest.raises(ConfigError, match="loss.depth_range_power"):
        replace(tiny(), loss=replace(tiny().loss, depth_range_power=-1.0))
