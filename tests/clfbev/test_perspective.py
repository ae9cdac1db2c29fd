"""The camera's perspective class supervision: point-in-box classes, the nearest point of a cell
deciding its class (occlusion), the focal loss and the model wiring."""

import math
from dataclasses import replace

import numpy as np
import pytest
import torch

from clfbev.camera_encoder import CameraEncoder
from clfbev.config import tiny
from clfbev.data import NuScenesDetection, collate, resize_and_crop
from clfbev.errors import ConfigError
from clfbev.geometry import CameraGeometry, nearest_lidar_points
from clfbev.model import CLFusionBEV
from clfbev.supervision.losses import sigmoid_focal_loss
from clfbev.supervision.perspective import cell_classes, point_classes, semantic_loss
from clfbev.supervision.targets import batch_loss

pytestmark = pytest.mark.usefixtures("one_thread")

K_1600 = torch.tensor([[1266.0, 0.0, 800.0], [0.0, 1266.0, 450.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
BINS = (1.0, 52.0, 1.0)
H, W, S = 192, 352, 8


def front_camera() -> torch.Tensor:
    """(4, 4) T_lidar_from_cam of a camera at the lidar origin looking along lidar x."""
    T = torch.eye(4, dtype=torch.float64)
    T[:3, :3] = torch.tensor([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]], dtype=torch.float64)
    return T


def cell_of(point: torch.Tensor, A: np.ndarray) -> tuple[int, int]:
    """Feature cell (row, col) of a lidar point seen by :func:`front_camera` through K_1600 and A."""
    x, y, z = (float(v) for v in point[:3])
    uv1 = A @ np.array([1266.0 * -y / x + 800.0, 1266.0 * -z / x + 450.0, 1.0])
    return math.floor(uv1[1] / S), math.floor(uv1[0] / S)


def test_point_classes_follow_the_rotated_box():
    # A 4 x 2 x 1.5 m box at (10, 5, 0) turned by 90 degrees: it is 2 m along x and 4 m along y.
    boxes = torch.tensor([[10.0, 5.0, 0.0, 4.0, 2.0, 1.5, math.pi / 2]])
    points = torch.tensor([
        [10.0, 6.9, 0.0],     # inside: 1.9 m along the box's length
        [10.9, 5.0, 0.7],     # inside: 0.9 m across, 0.7 m up
        [11.1, 5.0, 0.0],     # outside: 1.1 m across
        [10.0, 5.0, 0.8],     # outside: above the top
        [12.0, 5.0, 0.0],     # outside: would be inside an unrotated box
    ])
    torch.testing.assert_close(point_classes(points, boxes, torch.tensor([3])), torch.tensor([3, 3, -1, -1, -1]))
    assert (point_classes(points, boxes[:0], torch.tensor([], dtype=torch.long)) == -1).all()


def test_the_nearest_point_decides_the_cells_class():
    """A cell takes the class of the box around its nearest point: a car in front of a wall is a
    car; a car hidden behind a wall labels nothing; a cell seeing only the road is background."""
    _, A = resize_and_crop(np.zeros((900, 1600, 3), np.uint8), (H, W))
    img_aug = torch.from_numpy(A)[None, None]
    car = torch.tensor([[20.0, 0.0, 0.0, 4.5, 1.9, 1.6, 0.0, 0.0, 0.0]], dtype=torch.float64)
    hidden = torch.tensor([[30.0, -6.0, 0.0, 0.8, 0.8, 1.7, 0.0, 0.0, 0.0]], dtype=torch.float64)
    on_car = torch.tensor([17.8, 0.2, 0.1, 0.5, 0.0], dtype=torch.float64)         # the car's rear
    wall_behind_car = on_car * torch.tensor([2.0, 2.0, 2.0, 1.0, 1.0])              # same ray, 35.6 m
    wall = torch.tensor([15.0, -3.0, 0.0, 0.5, 0.0], dtype=torch.float64)           # in front of `hidden`
    in_hidden = wall * torch.tensor([2.0, 2.0, 2.0, 1.0, 1.0])                      # same ray, inside it
    road = torch.tensor([12.0, 4.0, -1.8, 0.5, 0.0], dtype=torch.float64)
    points = torch.stack([wall_behind_car, on_car, in_hidden, wall, road])
    labels = torch.tensor([0, 8])                                                   # car, pedestrian
    cams = CameraGeometry(K_1600[None, None], front_camera()[None, None], img_aug, (H, W), S, BINS)
    _, nearest = nearest_lidar_points([points], cams)
    classes = cell_classes(nearest, [points], [torch.cat([car, hidden])], [labels], 10)
    assert classes.shape == (1, 1, H // S, W // S)
    assert cell_of(on_car, A) == cell_of(wall_behind_car, A) and cell_of(wall, A) == cell_of(in_hidden, A)
    assert classes[0, 0][cell_of(on_car, A)] == 0
    assert classes[0, 0][cell_of(wall, A)] == 10             # background: the pedestrian is hidden
    assert classes[0, 0][cell_of(road, A)] == 10
    assert (classes >= 0).sum() == 3                         # every other cell: no target


def test_semantic_loss_is_the_focal_loss_over_labelled_cells_per_object_cell():
    torch.manual_seed(0)
    logits = torch.randn(1, 2, 3, 2, 2)
    t = torch.full((1, 2, 2, 2), -1)
    t[0, 0, 0, 0], t[0, 0, 1, 1], t[0, 1, 0, 1] = 1, 3, 2       # two object cells, one background
    onehots = {(0, 0, 0): [0, 1, 0], (0, 1, 1): [0, 0, 0], (1, 0, 1): [0, 0, 1]}
    expected = sum(sigmoid_focal_loss(logits[0, n, :, r, c], torch.tensor(v, dtype=torch.float32)).sum()
                   for (n, r, c), v in onehots.items()) / 2
    torch.testing.assert_close(semantic_loss(logits, t), expected)
    assert semantic_loss(logits, torch.full_like(t, -1)) == 0


def test_a_perspective_head_learns_the_classes_of_two_images():
    enc = CameraEncoder(18, 8, 16, BINS, 8, (64, 176), 8, (-51.2, -51.2, -5.0, 51.2, 51.2, 3.0), (0.8, 0.8, 8.0),
                        semantic_classes=4)
    torch.manual_seed(0)
    images = torch.randn(1, 2, 3, 64, 176)
    targets = torch.randint(0, 5, (1, 2, 8, 22))
    targets[:, :, :2] = -1
    opt = torch.optim.AdamW(enc.parameters(), lr=3e-3)
    losses = []
    for _ in range(25):
        _, _, logits = enc.image_features(images)
        loss = semantic_loss(logits, targets)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(float(loss.detach()))
    assert logits.shape == (1, 2, 4, 8, 22)
    assert losses[-1] < 0.5 * losses[0]


def test_the_model_builds_and_trains_the_head_only_with_a_weight(tiny_dataset):
    cfg = tiny()
    ds = NuScenesDetection(tiny_dataset, "v1.0-sim", "all", cfg.data_config())
    batch = collate([ds[0]])
    off = CLFusionBEV(cfg, "camera")
    assert off.camera_encoder.semantic_head is None and "loss_semantic" not in batch_loss(off, batch)
    on = CLFusionBEV(replace(cfg, loss=replace(cfg.loss, semantic=1.0)), "concat")
    losses = batch_loss(on, batch)
    assert losses["loss_semantic"] > 0
    losses["loss"].backward()
    assert on.camera_encoder.semantic_head.weight.grad.abs().sum() > 0
    # The head only trains the features: predictions do not depend on it.
    on.eval()
    before = on(batch).head.cls_logits
    with torch.no_grad():
        on.camera_encoder.semantic_head.weight.add_(1.0)
    torch.testing.assert_close(on(batch).head.cls_logits, before)


def test_semantic_lift_puts_the_class_probabilities_in_the_camera_bev():
    """With ``semantic_lift`` the camera BEV has one more channel per class: the depth-weighted
    splat of the head's sigmoid probabilities, next to the context's."""
    from clfbev.camera_encoder import compress_z, lift_geometry, splat

    pc_range, voxel = (-51.2, -51.2, -5.0, 51.2, 51.2, 3.0), (0.8, 0.8, 8.0)
    enc = CameraEncoder(18, 8, 16, BINS, 8, (64, 176), 8, pc_range, voxel, semantic_classes=3, semantic_lift=True)
    assert enc.out_channels == 8 + 3
    torch.manual_seed(0)
    images = torch.randn(1, 2, 3, 64, 176)
    K = torch.tensor([[100.0, 0.0, 88.0], [0.0, 100.0, 32.0], [0.0, 0.0, 1.0]]).expand(1, 2, 3, 3)
    T = front_camera().float().expand(1, 2, 4, 4)
    with torch.no_grad():
        bev, depth, logits = enc.lift_splat(images, K, T)
        geom = lift_geometry(CameraGeometry(K, T, None, (64, 176), 8, BINS))
        expected = compress_z(splat(depth, logits.sigmoid(), geom, pc_range, voxel))
    assert bev.shape[1] == 11 and bev[:, 8:].sum() > 0
    torch.testing.assert_close(bev[:, 8:], expected)
    with pytest.raises(ValueError, match="semantic_classes"):
        CameraEncoder(18, 8, 16, BINS, 8, (64, 176), 8, pc_range, voxel, semantic_lift=True)


def test_semantic_lift_needs_the_perspective_loss(tmp_path):
    from clfbev.config_file import load_config

    with pytest.raises(ConfigError, match="loss.semantic"):
        replace(tiny(), cam_semantic_lift=True)
    cfg = replace(tiny(), cam_semantic_lift=True, loss=replace(tiny().loss, semantic=1.0))
    assert cfg.cam_bev_channels == tiny().cam_bev_channels + len(cfg.class_names)
    bad = tmp_path / "lift.yaml"
    bad.write_text("preset: tiny\ncam_semantic_lift: true\n")
    with pytest.raises(ConfigError, match="lift.yaml"):
        load_config(bad)
