"""Tests for clfbev.resnet (ResNet, FPN) and clfbev.camera_encoder (lift-splat).

The geometry tests run through the real nuScenes v1.0-mini rig (numbers copied from the
reference, not imported from simgen) and check the strongest predicates: every frustum point
projects back to its feature-cell centre at its bin depth, and a one-hot feature lands in exactly
the voxel its back-projection predicts, within one cell of the true 3D point.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from clfbev.camera_encoder import CameraEncoder, compress_z, lift_geometry, splat
from clfbev.geometry import CameraGeometry, depth_bin_centres
from clfbev.resnet import FPN, ResNet

pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(autouse=True)
def _seed():
    torch.manual_seed(0)



def _assert_all_grads(module: torch.nn.Module) -> None:
    missing = [n for n, p in module.named_parameters() if p.grad is None or not torch.any(p.grad != 0)]
    assert not missing, f"no gradient reaches: {missing}"


# ----------------------------------------------------------------------------- ResNet / FPN


@pytest.mark.parametrize("depth, expansion", [(18, 1), (50, 4)])
def test_resnet_strides_channels_and_grads(depth, expansion):
    width = 8
    net = ResNet(depth, in_ch=3, width=width)
    x = torch.randn(2, 3, 64, 96)
    feats = net(x)
    expected_ch = tuple(width * m * expansion for m in (2, 4, 8))
    assert net.out_channels == expected_ch
    for f, s, c in zip(feats, net.strides, expected_ch):
        assert tuple(f.shape) == (2, c, 64 // s, 96 // s)
    sum((f * torch.randn_like(f)).sum() for f in feats).backward()
    _assert_all_grads(net)


def test_resnet_matches_torchvision_parameter_counts():
    # torchvision resnet18 / resnet50 minus their 1000-class fc layer: the same architecture.
    assert sum(p.numel() for p in ResNet(18).parameters()) == 11_689_512 - 513_000
    assert sum(p.numel() for p in ResNet(50).parameters()) == 25_557_032 - 2_049_000


def test_resnet_rejects_unknown_depth():
    with pytest.raises(ValueError, match="depth"):
        ResNet(42)


def test_fpn_fuses_to_finest_level_with_odd_sizes():
    # 64 x 176 gives C3 8x22, C4 4x11, C5 2x6: the 6 -> 11 upsample must land on the exact size.
    net = ResNet(18, width=8)
    feats = net(torch.randn(1, 3, 64, 176))
    fpn8 = FPN(list(net.out_channels), 12)
    fpn16 = FPN(list(net.out_channels[1:]), 12)
    y8, y16 = fpn8(feats), fpn16(feats[1:])
    assert tuple(y8.shape) == (1, 12, 8, 22) and tuple(y16.shape) == (1, 12, 4, 11)
    ((y8 * torch.randn_like(y8)).sum() + (y16 * torch.randn_like(y16)).sum()).backward()
    _assert_all_grads(fpn8)
    _assert_all_grads(fpn16)


# ----------------------------------------------------------------------------- nuScenes rig

NATIVE_W, NATIVE_H = 1600, 900
# channel: (translation, rotation wxyz, fx = fy, cx, cy), ego frame; v1.0-mini calibration.
RIG = {
    "CAM_FRONT": ((1.7008, 0.0159, 1.5110), (0.49980, -0.50303, 0.49978, -0.49737), 1266.42, 816.27, 491.51),
    "CAM_FRONT_RIGHT": ((1.5508, -0.4934, 1.4957), (0.20603, -0.20269, 0.68245, -0.67136), 1260.85, 807.97, 495.33),
    "CAM_BACK_RIGHT": ((1.0149, -0.4806, 1.5624), (0.12281, -0.13240, -0.70043, 0.69050), 1259.51, 807.25, 501.20),
    "CAM_BACK": ((0.0283, 0.0035, 1.5791), (0.50379, -0.49740, -0.49419, 0.50455), 809.22, 829.22, 481.78),
    "CAM_BACK_LEFT": ((1.0357, 0.4848, 1.5910), (0.69242, -0.70316, -0.11648, 0.11203), 1256.74, 792.11, 492.78),
    "CAM_FRONT_LEFT": ((1.5239, 0.4946, 1.5093), (0.67573, -0.67363, 0.21214, -0.21123), 1272.60, 826.62, 479.75),
}
LIDAR_TOP = ((0.943713, 0.0, 1.84023), (0.70780, -0.00649, 0.01065, -0.70631))


def quat_wxyz_to_matrix(q) -> np.ndarray:
    w, x, y, z = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def transform(translation, rotation_wxyz) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = quat_wxyz_to_matrix(rotation_wxyz)
    T[:3, 3] = translation
    return T


T_EGO_FROM_LIDAR = transform(*LIDAR_TOP)
T_LIDAR_FROM_EGO = np.linalg.inv(T_EGO_FROM_LIDAR)


def camera(name: str, scale: float) -> tuple[np.ndarray, np.ndarray]:
    """K (3, 3) for a 1600x900 image resized by ``scale``, and T_lidar_from_cam (4, 4)."""
    t, q, f, cx, cy = RIG[name]
    # Pixel-edge convention: resizing by s scales the first two rows of K by s exactly.
    K = np.diag([scale, scale, 1.0]) @ np.array([[f, 0, cx], [0, f, cy], [0, 0, 1.0]])
    return K, T_LIDAR_FROM_EGO @ transform(t, q)


def test_lidar_frame_sanity():
    # REFERENCE: the LIDAR_TOP rotation maps sensor x to ego -y and sensor y to ego +x.
    R = T_EGO_FROM_LIDAR[:3, :3]
    np.testing.assert_allclose(R @ [1, 0, 0], [0, -1, 0], atol=0.03)
    np.testing.assert_allclose(R @ [0, 1, 0], [1, 0, 0], atol=0.03)
    # CAM_FRONT looks along ego +x = lidar +y.
    _, T = camera("CAM_FRONT", 1.0)
    np.testing.assert_allclose(T[:3, 2], [0, 1, 0], atol=0.03)


# ----------------------------------------------------------------------------- geometry + splat

STRIDE = 8
BINS = (1.0, 41.0, 0.5)
PC_RANGE = (-40.0, -40.0, -5.0, 40.0, 40.0, 3.0)
VOXEL = (0.5, 0.5, 1.0)
# (camera, point in the EGO frame) pairs, all in view and inside PC_RANGE.
TARGETS = [
    ("CAM_FRONT", (12.0, 1.5, 0.8)),
    ("CAM_BACK", (-10.0, -1.0, 0.5)),
    ("CAM_FRONT", (25.0, -3.0, 0.0)),
    ("CAM_BACK", (-7.0, 2.5, 1.5)),
]


def voxel_of(p_lidar: np.ndarray) -> np.ndarray:
    """(3,) lidar-frame point -> (iz, iy, ix) voxel index."""
    ixyz = np.floor((p_lidar - np.array(PC_RANGE[:3])) / np.array(VOXEL)).astype(int)
    return ixyz[::-1]


def one_hot_setup(scale: float, A: np.ndarray | None, image_size):
    """Build (B=2, N=2) inputs with one one-hot feature per camera for the TARGETS.

    Sample b holds TARGETS[2b], TARGETS[2b + 1]. Camera n writes context channel n only, at
    the feature cell containing its point's (augmented) pixel, with a one-hot depth at the
    point's bin. Returns the torch inputs plus, per (b, n), the voxel predicted by the numpy
    back-projection of the cell centre and the voxel of the true point.
    """
    H, W = image_size
    h, w = H // STRIDE, W // STRIDE
    d_min, _, step = BINS
    D = len(depth_bin_centres(BINS))
    Ks, Ts = np.zeros((2, 2, 3, 3)), np.zeros((2, 2, 4, 4))
    depth = torch.zeros(2, 2, D, h, w)
    context = torch.zeros(2, 2, 2, h, w)
    expected, true, cells = {}, {}, {}
    for b in range(2):
        for n in range(2):
            name, p_ego = TARGETS[2 * b + n]
            K, T = camera(name, scale)
            Ks[b, n], Ts[b, n] = K, T
            p_lidar = (T_LIDAR_FROM_EGO @ np.append(p_ego, 1.0))[:3]
            p_cam = (np.linalg.inv(T) @ np.append(p_lidar, 1.0))[:3]
            z = p_cam[2]
            pix = K @ p_cam / z                                   # original-image pixel
            pix_aug = pix if A is None else (A @ pix) / (A @ pix)[2]
            i, j, k = int(pix_aug[1] // STRIDE), int(pix_aug[0] // STRIDE), int((z - d_min) // step)
            assert 0 <= i < h and 0 <= j < w and 0 <= k < D, (name, p_ego, pix_aug, z)
            depth[b, n, k, i, j] = 1.0
            cells[b, n] = (i, j)
            context[b, n, n, i, j] = 1.0
            # Independent back-projection of the feature-cell centre at the bin-centre depth.
            centre = np.array([(j + 0.5) * STRIDE, (i + 0.5) * STRIDE, 1.0])
            centre_orig = centre if A is None else np.linalg.solve(A, centre)
            ray = np.linalg.solve(K, centre_orig / centre_orig[2])
            q_cam = (d_min + (k + 0.5) * step) * ray / ray[2]
            expected[b, n] = voxel_of((T @ np.append(q_cam, 1.0))[:3])
            true[b, n] = voxel_of(p_lidar)
    f32 = lambda a: torch.as_tensor(a, dtype=torch.float32)  # noqa: E731
    A_t = None if A is None else f32(np.broadcast_to(A, (2, 2, 3, 3)).copy())
    return f32(Ks), f32(Ts), A_t, depth, context, expected, true, cells


def check_landing(bev_voxels: torch.Tensor, expected: dict, true: dict) -> dict:
    """Each (b, n) one-hot lands in one voxel: the predicted one, within one cell of the truth."""
    landed = {}
    for (b, n), exp in expected.items():
        hits = torch.nonzero(bev_voxels[b, n]).numpy()           # (k, 3) iz, iy, ix
        assert len(hits) == 1, f"sample {b} camera {n}: {len(hits)} voxels hit"
        np.testing.assert_array_equal(hits[0], exp)
        assert np.abs(hits[0] - true[b, n]).max() <= 1, (hits[0], true[b, n])
        assert bev_voxels[b, n][tuple(hits[0])].item() == pytest.approx(1.0)
        landed[b, n] = hits[0]
    return landed


def test_lift_geometry_projects_back_to_cell_centres():
    """Every frustum point re-projects to its feature-cell centre at its bin depth."""
    image_size = (144, 256)
    names = list(RIG)
    K, T = zip(*(camera(n, 0.16) for n in names))
    geom = lift_geometry(CameraGeometry(
        torch.tensor(np.stack(K), dtype=torch.float32)[None],
        torch.tensor(np.stack(T), dtype=torch.float32)[None],
        None, image_size, STRIDE, BINS,
    ))[0].double().numpy()                                         # (N, D, h, w, 3)
    N, D, h, w, _ = geom.shape
    assert (N, D, h, w) == (6, 80, 18, 32)
    depths = depth_bin_centres(BINS).double().numpy()
    np.testing.assert_allclose(depths[[0, -1]], [1.25, 40.75])
    for n in range(N):
        T_cam_from_lidar = np.linalg.inv(T[n])
        p_cam = geom[n] @ T_cam_from_lidar[:3, :3].T + T_cam_from_lidar[:3, 3]
        np.testing.assert_allclose(p_cam[..., 2], np.broadcast_to(depths[:, None, None], (D, h, w)), rtol=1e-5)
        uv = (p_cam @ K[n].T)[..., :2] / p_cam[..., 2:3]
        u_centres = np.broadcast_to(((np.arange(w) + 0.5) * STRIDE)[None, None, :], (D, h, w))
        v_centres = np.broadcast_to(((np.arange(h) + 0.5) * STRIDE)[None, :, None], (D, h, w))
        np.testing.assert_allclose(uv[..., 0], u_centres, atol=2e-3)
        np.testing.assert_allclose(uv[..., 1], v_centres, atol=2e-3)


def test_splat_lands_in_the_point_voxel_on_nuscenes_rig():
    image_size = (144, 256)                                       # 1600x900 * 0.16
    K, T, _, depth, context, expected, true, cells = one_hot_setup(0.16, None, image_size)
    geom = lift_geometry(CameraGeometry(K, T, None, image_size, STRIDE, BINS))
    vox = splat(depth, context, geom, PC_RANGE, VOXEL)            # (B, C=2, nz, ny, nx)
    assert tuple(vox.shape) == (2, 2, 8, 160, 160)
    landed = check_landing(vox, expected, true)

    # Same scene through an augmentation: an original image twice as large (1600x900 * 0.32),
    # resized by 0.5, cropped 8 px left and 16 px top, then flipped horizontally. Crops and the
    # flip width are multiples of the stride, so the augmented feature cells back-project onto
    # exactly the un-augmented ones: the feature must land in the very same voxel.
    W_aug, H_aug = 248, 128
    resize = np.diag([0.5, 0.5, 1.0])
    crop = np.array([[1.0, 0, -8], [0, 1, -16], [0, 0, 1]])
    flip = np.array([[-1.0, 0, W_aug], [0, 1, 0], [0, 0, 1]])
    A = flip @ crop @ resize
    K2, T2, A2, depth2, context2, expected2, true2, cells2 = one_hot_setup(0.32, A, (H_aug, W_aug))
    geom2 = lift_geometry(CameraGeometry(K2, T2, A2, (H_aug, W_aug), STRIDE, BINS))
    vox2 = splat(depth2, context2, geom2, PC_RANGE, VOXEL)
    landed2 = check_landing(vox2, expected2, true2)
    for key in landed:
        np.testing.assert_array_equal(landed2[key], landed[key])
    # The features really sat elsewhere: 2 cell rows cropped off the top; 1 cell column cropped
    # off the left, then the 31 remaining columns mirrored.
    for key, (i, j) in cells.items():
        assert cells2[key] == (i - 2, W_aug // STRIDE - 1 - (j - 1))


def test_splat_conserves_mass_and_matches_reference():
    names = list(RIG)
    K, T = zip(*(camera(n, 0.08) for n in names))                # 128 x 72 images
    image_size, bins = (72, 128), (1.0, 30.0, 2.0)
    pc_range, voxel = (-12.0, -16.0, -3.0, 20.0, 16.0, 3.0), (1.0, 2.0, 2.0)
    Kt = torch.tensor(np.stack(K), dtype=torch.float32).expand(2, -1, -1, -1)
    Tt = torch.tensor(np.stack(T), dtype=torch.float32).expand(2, -1, -1, -1)
    geom = lift_geometry(CameraGeometry(Kt, Tt, None, image_size, STRIDE, bins))  # (2, 6, D, 9, 16, 3)
    B, N, D, h, w, _ = geom.shape
    depth = torch.rand(B, N, D, h, w).softmax(dim=2)
    context = torch.randn(B, N, 5, h, w)
    vox = splat(depth, context, geom, pc_range, voxel)
    nz, ny, nx = vox.shape[2:]
    assert (nz, ny, nx) == (3, 16, 32)

    # Reference with numpy's unbuffered scatter-add over explicitly kept points.
    g = geom.numpy().reshape(B, -1, 3)
    feats = (depth[:, :, :, None] * context[:, :, None]).permute(0, 1, 2, 4, 5, 3).numpy().reshape(B, -1, 5)
    idx = np.floor((g - np.array(pc_range[:3])) / np.array(voxel)).astype(int)
    inside = np.all((idx >= 0) & (idx < [nx, ny, nz]), axis=-1)
    assert 0.05 < inside.mean() < 0.95                            # some points kept, some dropped
    ref = np.zeros((B, nz, ny, nx, 5))
    bb = np.broadcast_to(np.arange(B)[:, None], inside.shape)
    np.add.at(ref, (bb[inside], idx[..., 2][inside], idx[..., 1][inside], idx[..., 0][inside]), feats[inside])
    np.testing.assert_allclose(vox.permute(0, 2, 3, 4, 1).numpy(), ref, atol=1e-4)
    # Mass: the BEV sums to the in-range frustum features, per sample and channel.
    mass_in = (feats * inside[..., None]).sum(axis=1)             # (B, 5)
    np.testing.assert_allclose(vox.sum(dim=(2, 3, 4)).numpy(), mass_in, rtol=1e-4, atol=1e-3)

    bev = compress_z(vox)
    assert tuple(bev.shape) == (B, nz * 5, ny, nx)
    for iz in range(nz):                                          # slice iz -> channels [5 iz, 5 iz + 5)
        torch.testing.assert_close(bev[:, 5 * iz:5 * iz + 5], vox[:, :, iz])
    torch.testing.assert_close(bev.sum(), vox.sum())

    # Gradients: those of the outer product scatter-added into the voxels.
    depth.requires_grad_(), context.requires_grad_()
    g_out = torch.randn(B, 5, nz, ny, nx)
    grads = torch.autograd.grad(splat(depth, context, geom, pc_range, voxel), (depth, context), g_out)
    flat = torch.from_numpy(((bb * nz + idx[..., 2]) * ny + idx[..., 1]) * nx + idx[..., 0])
    flat = torch.where(torch.from_numpy(inside), flat, B * nz * ny * nx)   # a dump row
    outer = (depth[:, :, :, None] * context[:, :, None]).permute(0, 1, 2, 4, 5, 3).reshape(B, -1, 5)
    ref_vox = torch.zeros(B * nz * ny * nx + 1, 5).index_add(0, flat.reshape(-1), outer.reshape(-1, 5))
    ref_vox = ref_vox[:-1].view(B, nz, ny, nx, 5).permute(0, 4, 1, 2, 3)
    ref_grads = torch.autograd.grad(ref_vox, (depth, context), g_out)
    for got, want in zip(grads, ref_grads):
        torch.testing.assert_close(got, want, atol=1e-4, rtol=1e-4)


def test_depth_bins_and_bad_arguments():
    torch.testing.assert_close(depth_bin_centres((2.0, 4.0, 0.5)), torch.tensor([2.25, 2.75, 3.25, 3.75]))
    with pytest.raises(ValueError):
        depth_bin_centres((4.0, 2.0, 0.5))
    with pytest.raises(ValueError, match="multiple"):
        lift_geometry(CameraGeometry(torch.eye(3)[None, None], torch.eye(4)[None, None], None, (60, 176), 8, (1.0, 9.0, 1.0)))


# ----------------------------------------------------------------------------- full encoder


def tiny_encoder(feature_stride: int = 8) -> CameraEncoder:
    return CameraEncoder(
        depth=18, width=16, fpn_ch=32, depth_bins=(1.0, 33.0, 8.0), context_ch=8,
        image_size=(64, 176), feature_stride=feature_stride,
        pc_range=(-32.0, -32.0, -3.0, 32.0, 32.0, 5.0), bev_voxel=(2.0, 2.0, 4.0),
    )


def rig_inputs(B: int):
    K, T = zip(*(camera(n, 0.11) for n in RIG))                   # 176 x 99 -> 64 rows via crop
    Kt = torch.tensor(np.stack(K), dtype=torch.float32).expand(B, -1, -1, -1)
    Tt = torch.tensor(np.stack(T), dtype=torch.float32).expand(B, -1, -1, -1)
    crop = torch.tensor([[1.0, 0, 0], [0, 1, -30], [0, 0, 1]]).expand(B, 6, 3, 3)
    return Kt, Tt, crop


def test_camera_encoder_forward_backward():
    enc = tiny_encoder()
    assert enc.out_channels == 8 * 2 and enc.bev_shape == (32, 32) and enc.num_depth_bins == 4
    K, T, A = rig_inputs(1)
    images = torch.randn(1, 6, 3, 64, 176)
    bev = enc(images, K, T, A)
    assert tuple(bev.shape) == (1, enc.out_channels, 32, 32)
    assert torch.isfinite(bev).all() and bev.abs().sum() > 0
    (bev * torch.randn_like(bev)).sum().backward()
    _assert_all_grads(enc)

    with pytest.raises(ValueError, match="image_size"):
        enc(torch.randn(1, 6, 3, 64, 160), K, T, A)


def test_camera_encoder_stride16_and_no_aug():
    enc = tiny_encoder(feature_stride=16)
    K, T, _ = rig_inputs(2)
    depth, context, _ = enc.image_features(torch.randn(2, 6, 3, 64, 176))
    assert tuple(depth.shape) == (2, 6, 4, 4, 11) and tuple(context.shape) == (2, 6, 8, 4, 11)
    torch.testing.assert_close(depth.sum(dim=2), torch.ones(2, 6, 4, 11))
    bev = enc(torch.randn(2, 6, 3, 64, 176), K, T)
    assert tuple(bev.shape) == (2, 16, 32, 32)
