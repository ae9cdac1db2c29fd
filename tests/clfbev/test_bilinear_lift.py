"""The bilinear lift (clfbev/bilinear_lift.py): a known point to a known feature cell exactly,
zero outside every frustum, the same values as torch's grid_sample over all cameras, and the
encoder's switch (cam_lift) keeps the splat's shapes and tensors."""
from __future__ import annotations

import dataclasses
import math

import pytest
import torch
import torch.nn.functional as F

from clfbev.bilinear_lift import bilinear_lift, column_points
from clfbev.camera_encoder import CameraEncoder
from clfbev.config import tiny
from clfbev.errors import ConfigError
from clfbev.geometry import CameraGeometry

pytestmark = pytest.mark.usefixtures("one_thread")


def looking(yaw: float, at: tuple = (0.0, 0.0, 0.0)) -> torch.Tensor:
    """(4, 4) float64 T_lidar_from_cam of a level camera at ``at`` looking along lidar yaw ``yaw``
    (camera x right, y down, z forward)."""
    c, s = math.cos(yaw), math.sin(yaw)
    R = torch.tensor([[s, 0.0, c], [-c, 0.0, s], [0.0, -1.0, 0.0]], dtype=torch.float64)   # columns: x, y, z
    T = torch.eye(4, dtype=torch.float64)
    T[:3, :3], T[:3, 3] = R, torch.tensor(at, dtype=torch.float64)
    return T


def test_a_known_point_takes_exactly_its_cells_feature_and_nothing_outside_the_frustum():
    """One camera at the origin looking along +x; the grid's cells are 1 m with centres on whole
    metres plus 0.5, one 2 m slab with one height at z = 0. The column of cell (iy, ix) = (0, 0) is
    the point (8, 0, 0): on the optical axis at 8 m, it projects to (cx, cy), which K puts at the
    centre of feature cell (i, j) = (2, 5). Its BEV cell holds exactly that cell's feature."""
    s, h, w, C = 8, 4, 10, 3
    K = torch.tensor([[16.0, 0.0, (5 + 0.5) * s], [0.0, 16.0, (2 + 0.5) * s], [0.0, 0.0, 1.0]], dtype=torch.float64)
    cams = CameraGeometry(K.view(1, 1, 3, 3), looking(0.0).view(1, 1, 4, 4), torch.eye(3).view(1, 1, 3, 3),
                          (h * s, w * s), s, (1.0, 60.0, 1.0))
    pc_range, voxel = (7.5, -3.5, -1.0, 17.5, 3.5, 1.0), (1.0, 1.0, 2.0)
    assert column_points(pc_range, voxel, (0.0,))[0][0, 3, 0].tolist() == [8.0, 0.0, 0.0]   # cell (iy 3, ix 0)
    context = torch.randn(1, 1, C, h, w, generator=torch.Generator().manual_seed(0))
    bev = bilinear_lift(context, cams, pc_range, voxel, (0.0,))                          # (1, C, 7, 10)
    assert bev.shape == (1, C, 7, 10)
    assert torch.equal(bev[0, :, 3, 0], context[0, 0, :, 2, 5])

    # Behind the camera nothing is seen: a grid reaching behind it is exactly 0 there.
    behind = bilinear_lift(context, cams, (-9.5, -3.5, -1.0, 10.5, 3.5, 1.0), voxel, (0.0,))   # x -9 .. 10
    assert torch.count_nonzero(behind[..., :10]) == 0                                   # x < 1 m (d_min)
    assert torch.count_nonzero(behind[..., 11:]) > 0


def _grid_sample_reference(context, cams, pc_range, voxel, heights):
    """The lift by F.grid_sample over every camera and point, averaged over the valid ones;
    ``heights`` ascending, the same number in each slab."""
    B, N, C, h, w = context.shape
    H, W = cams.image_size
    nz, ny, nx = (round((pc_range[i + 3] - pc_range[i]) / voxel[i]) for i in (2, 1, 0))
    per = len(heights) // nz
    pts = torch.stack(torch.meshgrid(torch.tensor(heights, dtype=torch.float64),
                                     pc_range[1] + (torch.arange(ny, dtype=torch.float64) + 0.5) * voxel[1],
                                     pc_range[0] + (torch.arange(nx, dtype=torch.float64) + 0.5) * voxel[0],
                                     indexing="ij")[::-1], dim=-1).reshape(-1, 3)
    T = torch.linalg.inv(cams.T_lidar_from_cam.double())
    p_cam = (T[..., None, :3, :3] @ pts[:, :, None])[..., 0] + T[..., None, :3, 3]        # (B, N, P, 3)
    uvw = ((cams.img_aug.double() @ cams.intrinsics.double())[:, :, None] @ p_cam[..., None])[..., 0]
    u, v = uvw[..., 0] / uvw[..., 2], uvw[..., 1] / uvw[..., 2]
    valid = (p_cam[..., 2] >= cams.depth_bins[0]) & (u >= 0) & (u < W) & (v >= 0) & (v < H)
    grid = torch.stack([2 * u / W - 1, 2 * v / H - 1], dim=-1).flatten(0, 1)[:, None]    # (B N, 1, P, 2)
    sampled = F.grid_sample(context.flatten(0, 1).double(), grid, align_corners=False, padding_mode="border")
    sampled = sampled.view(B, N, C, nz, per, ny, nx) * valid.view(B, N, 1, nz, per, ny, nx)
    count = valid.view(B, N, nz, per, ny, nx).sum(dim=(1, 3)).clamp(min=1)              # (B, nz, ny, nx)
    mean = sampled.sum(dim=(1, 4)) / count[:, None]                                      # (B, C, nz, ny, nx)
    return mean.permute(0, 2, 1, 3, 4).reshape(B, nz * C, ny, nx)


def test_the_lift_equals_grid_sample_over_six_cameras_with_flips_and_slabs():
    B, N, C, s, h, w = 2, 6, 4, 8, 6, 11
    H, W = h * s, w * s
    gen = torch.Generator().manual_seed(1)
    context = torch.randn(B, N, C, h, w, generator=gen)
    T = torch.stack([torch.stack([looking(0.2 * b + n * math.pi / 3, (0.5, 0.1 * b, 1.2)) for n in range(N)])
                     for b in range(B)])
    K = torch.tensor([[30.0, 0.0, W / 2 + 3.0], [0.0, 30.0, H / 2 - 2.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    # Augmentation: a resize by 0.9 about the origin, and in sample 1 a horizontal flip.
    aug = torch.tensor([[0.9, 0.0, 0.0], [0.0, 0.9, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64).repeat(B, N, 1, 1)
    aug[1, :, 0] = torch.tensor([-0.9, 0.0, W], dtype=torch.float64)
    cams = CameraGeometry(K.repeat(B, N, 1, 1), T, aug, (H, W), s, (1.0, 40.0, 1.0))
    pc_range, voxel = (-20.0, -20.0, -4.0, 20.0, 20.0, 4.0), (1.0, 1.0, 4.0)
    heights = (-3.0, -1.5, -0.5, 0.5, 1.0, 3.5)                  # three in each 4 m slab
    got = bilinear_lift(context, cams, pc_range, voxel, heights[::-1])                  # any order
    want = _grid_sample_reference(context, cams, pc_range, voxel, heights)
    assert got.shape == (B, 2 * C, 40, 40)
    assert 0.3 < (got != 0).float().mean() < 1.0                # partly seen: the test sees both sides
    torch.testing.assert_close(got.double(), want, rtol=0, atol=1e-5)
    # The gradient reaches the context, and only the seen cells' taps.
    ctx = context.clone().requires_grad_(True)
    bilinear_lift(ctx, cams, pc_range, voxel, heights).sum().backward()
    assert ctx.grad is not None and ctx.grad.abs().sum() > 0


def test_the_encoder_switch_keeps_the_splats_shapes_and_tensors():
    cfg = dataclasses.replace(tiny(), image_size=(64, 176), cam_width=8, fpn_ch=16, context_ch=8)
    torch.manual_seed(0)
    splat = CameraEncoder.from_config(cfg)
    torch.manual_seed(0)
    bilinear = CameraEncoder.from_config(dataclasses.replace(cfg, cam_lift="bilinear"))
    # An encoder checkpoint of the splat (the shipped one) loads into the bilinear lift as is.
    assert {k: v.shape for k, v in splat.state_dict().items()} == {k: v.shape for k, v in bilinear.state_dict().items()}
    B, N = 1, 6
    images = torch.randn(B, N, 3, 64, 176, generator=torch.Generator().manual_seed(2))
    K = torch.tensor([[60.0, 0.0, 88.0], [0.0, 60.0, 32.0], [0.0, 0.0, 1.0]]).repeat(B, N, 1, 1)
    T = torch.stack([looking(n * math.pi / 3, (0.0, 0.0, 0.0)) for n in range(N)]).float()[None]
    aug = torch.eye(3).repeat(B, N, 1, 1)
    with torch.no_grad():
        a, depth_a, _ = splat.lift_splat(images, K, T, aug)
        b, depth_b, _ = bilinear.lift_splat(images, K, T, aug)
    assert a.shape == b.shape == (B, cfg.cam_bev_channels, *cfg.cam_bev_shape)
    assert torch.equal(depth_a, depth_b)                        # the same depth head, still predicted
    assert (b != 0).float().mean() > (a != 0).float().mean()    # the bilinear lift fills more cells


def test_the_config_refuses_an_unknown_lift_and_the_oracle_with_it():
    with pytest.raises(ConfigError, match="cam_lift"):
        dataclasses.replace(tiny(), cam_lift="nearest")
    for heights in ((), (3.0,), (-1.0, 5.0)):                    # none; outside [-5, 3)
        with pytest.raises(ConfigError, match="cam_lift_heights"):
            dataclasses.replace(tiny(), cam_lift="bilinear", cam_lift_heights=heights)
    with pytest.raises(ConfigError, match="each of the 2 cam_z_slabs"):
        dataclasses.replace(tiny(), cam_lift="bilinear", cam_z_slabs=2, cam_lift_heights=(-1.4, -1.2))
    dataclasses.replace(tiny(), cam_z_slabs=2, cam_lift_heights=(-1.4, -1.2))     # the splat ignores them
    with pytest.raises(ConfigError, match="cam_oracle_depth"):
        dataclasses.replace(tiny(), cam_lift="bilinear", cam_oracle_depth=True)
