"""Lidar branch: VFE invariances and exact values, BEV sizes, batch independence, locality, grads.

Points are (n, 5) in the lidar frame: x forward, y left, z up (metres), intensity, time lag.
The exactness tests run in float64 so that "same output" can be asserted to 1e-12.

Timing (2-core CPU, 1 thread): the whole file runs in about 4 s; one forward + backward of the
gradient test (2 samples x 3000 points, grid 10 x 32 x 32, BEV 16 x 8 x 8) takes about 0.15 s.
"""

import math

import pytest
import torch

from clfbev.lidar_encoder import VFE, LidarEncoder, SparseEncoder
from clfbev.ops.voxelize import voxelize

pytestmark = pytest.mark.usefixtures("one_thread")

# (pc_range, voxel_size): grid (nz, ny, nx) = (10, 32, 32); BEV 8 x 8 with 2 downsamplings.
RANGE_A, VOXEL_A = (-6.4, -6.4, -2.0, 6.4, 6.4, 2.0), (0.4, 0.4, 0.4)
# Non-square, odd grid (16, 24, 65); BEV 6 x 17 with 2 downsamplings.
RANGE_B, VOXEL_B = (-6.5, -4.8, -3.0, 6.5, 4.8, 1.0), (0.2, 0.4, 0.25)
# A larger grid (10, 64, 64) -> BEV 16 x 16, so that a receptive field is a small part of it.
RANGE_C, VOXEL_C = (-12.8, -12.8, -2.0, 12.8, 12.8, 2.0), (0.4, 0.4, 0.4)



def random_points(n, pc_range, seed, margin=0.0, dtype=torch.float32):
    """(n, 5) points uniform in pc_range (grown by margin): x, y, z, intensity, time lag."""
    g = torch.Generator().manual_seed(seed)
    lo = torch.tensor(pc_range[:3], dtype=torch.float64) - margin
    hi = torch.tensor(pc_range[3:], dtype=torch.float64) + margin
    xyz = lo + (hi - lo) * torch.rand((n, 3), generator=g, dtype=torch.float64)
    extra = torch.rand((n, 2), generator=g, dtype=torch.float64) * torch.tensor([1.0, 0.5], dtype=torch.float64)
    return torch.cat([xyz, extra], dim=1).to(dtype)


def encoder(pc_range, voxel, channels=(8, 16, 16), **kw):
    torch.manual_seed(0)
    return LidarEncoder(5, 16, channels, pc_range, voxel, max_voxels=100000, **kw)


def randomise_bn(module, seed=1):
    """Non-trivial eval-mode BatchNorm (running stats, affine) so that BN is no identity."""
    g = torch.Generator().manual_seed(seed)
    for m in module.modules():
        if isinstance(m, torch.nn.BatchNorm1d):
            c = m.num_features
            m.running_mean.copy_(torch.randn(c, generator=g) * 0.1)
            m.running_var.copy_(torch.rand(c, generator=g) + 0.5)
            m.weight.data.copy_(torch.rand(c, generator=g) + 0.5)
            m.bias.data.copy_(torch.randn(c, generator=g) * 0.1)


# ---------------------------------------------------------------------------------------- VFE


def dense_voxels(seed=0):
    """float64 points and their voxels, several points per voxel (small range, big voxels)."""
    pc_range, voxel = (-1.0, -1.0, -1.0, 1.0, 1.0, 1.0), (0.5, 0.5, 1.0)
    pts = random_points(300, pc_range, seed, dtype=torch.float64)
    vox = voxelize(pts, torch.zeros(300, dtype=torch.long), pc_range, voxel, 1000)
    assert (vox.num_points > 1).all()
    return pts, vox, pc_range, voxel


def run_vfe(vfe, pts, vox):
    return vfe(pts[vox.point_index], vox.voxel_id, vox.num_points, vox.coords)


@pytest.mark.parametrize("norm", ["batch", "layer"])
def test_vfe_invariant_to_point_order(norm):
    """Eval mode (BatchNorm by its running statistics): shuffling the input points gives the
    same voxel features (the voxels come in the same order, their points in another)."""
    pts, vox, pc_range, voxel = dense_voxels()
    torch.manual_seed(0)
    vfe = VFE(5, 32, voxel, pc_range, norm=norm).double().eval()
    randomise_bn(vfe)
    ref = dict(zip(map(tuple, vox.coords.tolist()), run_vfe(vfe, pts, vox)))
    perm = torch.randperm(len(pts), generator=torch.Generator().manual_seed(3))
    vox2 = voxelize(pts[perm], torch.zeros(len(pts), dtype=torch.long), pc_range, voxel, 1000)
    assert torch.equal(vox2.coords, vox.coords) and not torch.equal(perm[vox2.point_index], vox.point_index)
    out = run_vfe(vfe, pts[perm], vox2)
    for c, f in zip(map(tuple, vox2.coords.tolist()), out):
        torch.testing.assert_close(f, ref[c], rtol=0, atol=1e-12)


@pytest.mark.parametrize("norm", ["batch", "layer"])
def test_vfe_single_point_voxel_is_that_points_mlp_output(norm):
    """Eval mode, by hand: aug = [xyz scaled to [-1, 1] over the range, intensity, lag over its
    span, 0 (offset to the mean), (xyz - centre) / voxel] -> Linear, norm, ReLU."""
    pc_range, voxel = (-2.0, -3.0, -1.0, 2.0, 3.0, 1.0), (0.5, 0.75, 0.5)
    p = torch.tensor([[0.3, -1.1, 0.2, 0.7, 0.25], [-1.9, 2.9, -0.9, 0.1, 0.0]], dtype=torch.float64)
    vox = voxelize(p, torch.zeros(2, dtype=torch.long), pc_range, voxel, 10)
    assert vox.num_points.tolist() == [1, 1]
    # Voxel (ix, iy, iz) of point 0 = floor((0.3+2)/0.5), floor((-1.1+3)/0.75), floor((0.2+1)/0.5);
    # point 1's voxel (0, 7, 0) has the smaller key, so it is row 0.
    assert vox.point_index.tolist() == [1, 0] and vox.coords[1].tolist() == [0, 2, 2, 4]
    centre = torch.tensor([-2.0 + 4.5 * 0.5, -3.0 + 2.5 * 0.75, -1.0 + 2.5 * 0.5], dtype=torch.float64)

    torch.manual_seed(0)
    vfe = VFE(5, 24, voxel, pc_range, norm=norm, time_lag_span=0.1).double().eval()
    randomise_bn(vfe)
    out = run_vfe(vfe, p, vox)

    xyz_norm = p[0, :3] / torch.tensor([2.0, 3.0, 1.0], dtype=torch.float64)  # the range is centred on 0
    offset = (p[0, :3] - centre) / torch.tensor(voxel, dtype=torch.float64)
    lag_norm = p[0, 4:5] / 0.1
    aug = torch.cat([xyz_norm, p[0, 3:4], lag_norm, torch.zeros(3, dtype=torch.float64), offset])
    h = vfe.point_mlp[0].weight @ aug
    nrm = vfe.point_mlp[1]
    if norm == "batch":
        h = (h - nrm.running_mean) / torch.sqrt(nrm.running_var + nrm.eps) * nrm.weight + nrm.bias
    else:
        h = (h - h.mean()) / torch.sqrt(h.var(unbiased=False) + nrm.eps) * nrm.weight + nrm.bias
    expected = torch.relu(h)
    assert (expected > 0).any()
    torch.testing.assert_close(out[1], expected, rtol=0, atol=1e-12)


def test_vfe_is_max_over_all_points_of_the_point_mlp():
    """Train mode (BN over the points of the batch): each voxel = max of all its points' rows."""
    pts, vox, pc_range, voxel = dense_voxels(seed=5)
    torch.manual_seed(0)
    vfe = VFE(5, 32, voxel, pc_range).double().train()
    out = run_vfe(vfe, pts, vox)
    aug = vfe.augment(pts[vox.point_index], vox.voxel_id, vox.num_points, vox.coords)
    assert aug.shape == (len(pts), 5 + 6)
    h = vfe.point_mlp(aug)
    for v in range(0, out.shape[0], 7):
        torch.testing.assert_close(out[v], h[vox.voxel_id == v].max(dim=0).values, rtol=0, atol=0)
    # The offset to the voxel mean sums to zero over each voxel.
    sums = torch.zeros(out.shape[0], 3, dtype=torch.float64).index_add_(0, vox.voxel_id, aug[:, 5:8])
    torch.testing.assert_close(sums, torch.zeros_like(sums), rtol=0, atol=1e-12)


# ------------------------------------------------------------------------------- LidarEncoder


@pytest.mark.parametrize(
    "pc_range, voxel, kw, grid, out_channels, out_size",
    [
        (RANGE_A, VOXEL_A, {}, (10, 32, 32), 16 * 1, (8, 8)),  # z: 10 -> 5 -> 3 -> z_out 1
        # The second downsampling halves z only: x, y keep stride 2 (the tiny config's 0.8 m BEV).
        (RANGE_A, VOXEL_A, dict(xy_stride=2), (10, 32, 32), 16 * 1, (16, 16)),
        (RANGE_C, VOXEL_C, dict(xy_stride=1, z_out_conv=False), (10, 64, 64), 16 * 3, (64, 64)),
        (RANGE_B, VOXEL_B, dict(z_out_conv=False, blocks_per_stage=2), (16, 24, 65), 16 * 4, (6, 17)),
    ],
)
def test_bev_size_matches_derived_properties(pc_range, voxel, kw, grid, out_channels, out_size):
    enc = encoder(pc_range, voxel, **kw)
    assert enc.grid_shape == grid
    assert enc.out_channels == out_channels and enc.out_size == out_size
    assert enc.sparse.out_size(grid) == out_size
    bev = enc([random_points(2000, pc_range, 0), random_points(1500, pc_range, 1)])
    assert bev.shape == (2, out_channels, *out_size)


def test_z_only_downsampling_keeps_the_sites_in_x_and_y():
    """A z-only stage neither moves nor dilates the sites in x, y: its output sites are the
    input sites' (y, x) cells, with z halved."""
    enc = encoder(RANGE_A, VOXEL_A, xy_stride=2)
    down = enc.sparse.downs[1]
    assert down.kernel_size == (3, 1, 1) and down.stride == (2, 1, 1)
    from clfbev.ops.sparse_conv import SparseTensor
    coords = torch.tensor([[0, 0, 3, 4], [0, 1, 3, 4], [0, 4, 7, 1], [1, 2, 0, 0]])
    x = SparseTensor(torch.randn(4, 16), coords, (5, 16, 16), 2)
    y = down(x)
    # Output z' receives input z when 2 z' - 1 + k = z for a kernel tap k in {0, 1, 2}: z = 0 -> 0,
    # z = 1 -> 0 and 1, z = 2 -> 1, z = 4 -> 2 (the output grid has (5 + 2 - 3) // 2 + 1 = 3 z cells).
    assert y.spatial_shape == (3, 16, 16)
    assert {tuple(c) for c in y.coords.tolist()} == {(0, 0, 3, 4), (0, 1, 3, 4), (0, 2, 7, 1), (1, 1, 0, 0)}
    with pytest.raises(ValueError, match="xy_stride"):
        encoder(RANGE_A, VOXEL_A, xy_stride=3)


def test_too_small_grid_and_wrong_point_channels_raise():
    with pytest.raises(ValueError, match="too small"):
        SparseEncoder(16, (8, 16, 16, 16), (4, 16, 16))
    with pytest.raises(ValueError, match=r"\(N, 5\)"):
        encoder(RANGE_A, VOXEL_A)([torch.zeros(10, 4)])


def test_batch_samples_do_not_mix_and_input_forms_agree():
    enc = encoder(RANGE_A, VOXEL_A).eval()
    randomise_bn(enc)
    p0, p1 = random_points(2000, RANGE_A, 0, margin=1.0), random_points(2000, RANGE_A, 1, margin=1.0)
    p1b = random_points(3000, RANGE_A, 2, margin=1.0)
    with torch.no_grad():
        a = enc([p0, p1])
        b = enc([p0, p1b])
        alone = enc([p0])
        idx = torch.cat([torch.zeros(2000, dtype=torch.long), torch.ones(2000, dtype=torch.long)])
        flat = enc(torch.cat([p0, p1]), idx)
        with_empty = enc(torch.cat([p0, p1]), idx, batch_size=3)
    assert a.abs().sum() > 0 and not torch.allclose(a[1], b[1])
    torch.testing.assert_close(b[0], a[0], rtol=0, atol=1e-6)
    torch.testing.assert_close(alone[0], a[0], rtol=0, atol=1e-6)
    torch.testing.assert_close(flat, a, rtol=0, atol=1e-6)
    assert with_empty.shape[0] == 3 and torch.equal(with_empty[2], torch.zeros_like(a[0]))


def influence(enc, i_xy):
    """Centre and radius (output cells, per axis) of the BEV cells a change at input voxel i_xy
    can reach: each SubM k3 grows the radius by 1; a k3/s2/p1 conv maps i to o in
    [(i - 1) / 2, (i + 1) / 2], so centre c -> c / 2 and radius r -> (r + 1) / 2."""
    c, r = torch.tensor(i_xy, dtype=torch.float64), 0.0
    for stage, subms in enumerate(enc.sparse.subms):
        if stage > 0:
            c, r = c / 2, (r + 1) / 2
        r += len(subms)
    return c, r


def test_single_point_lights_only_cells_around_its_own():
    enc = encoder(RANGE_C, VOXEL_C).eval()
    randomise_bn(enc)
    x, y = 3.3, -7.9  # lidar frame: 3.3 m ahead, 7.9 m to the right
    ix, iy = math.floor((x - RANGE_C[0]) / VOXEL_C[0]), math.floor((y - RANGE_C[1]) / VOXEL_C[1])
    assert (ix, iy) == (40, 12)
    with torch.no_grad():
        empty = enc([torch.zeros(0, 5)])
        bev = enc([torch.tensor([[x, y, 0.3, 0.5, 0.0]])])
    assert torch.equal(empty, torch.zeros_like(empty))
    lit = torch.nonzero((bev - empty)[0].abs().sum(0) > 0)  # (k, 2) rows (y, x)
    assert len(lit) > 0
    # Without other sites, SubM convs do not spread: only the strided convs' +-1 reach remains,
    # i.e. |o - i / 4| < 1 on each axis (2 downsamplings), at most 2 x 2 cells.
    assert ((lit[:, 0] - iy / 4).abs() < 1).all() and ((lit[:, 1] - ix / 4).abs() < 1).all()
    assert [iy // 4, ix // 4] in lit.tolist()


def test_added_point_changes_only_its_receptive_field():
    enc = encoder(RANGE_C, VOXEL_C).eval()
    randomise_bn(enc)
    background = random_points(3000, RANGE_C, 7)
    x, y = -4.1, 6.5
    ix, iy = math.floor((x - RANGE_C[0]) / VOXEL_C[0]), math.floor((y - RANGE_C[1]) / VOXEL_C[1])
    extra = torch.tensor([[x, y, -0.2, 0.9, 0.0]])
    with torch.no_grad():
        diff = (enc([torch.cat([background, extra])]) - enc([background]))[0].abs().sum(0)
    changed = torch.nonzero(diff > 1e-6).double()  # (k, 2) rows (y, x)
    (cx, cy), r = influence(enc, (ix, iy))
    assert r == 2.5 and len(changed) > 0
    assert ((changed[:, 0] - cy).abs() <= r).all() and ((changed[:, 1] - cx).abs() <= r).all()
    assert diff.numel() > 4 * len(changed)  # the field is a small part of the 16 x 16 BEV


def test_forward_backward_finite_and_every_parameter_gets_a_gradient():
    enc = encoder(RANGE_A, VOXEL_A).train()
    pts = [random_points(3000, RANGE_A, s, margin=0.5) for s in (0, 1)]
    bev = enc(pts)
    weights = torch.randn(bev.shape, generator=torch.Generator().manual_seed(0))
    (bev * weights).sum().backward()
    assert torch.isfinite(bev).all()
    for name, p in enc.named_parameters():
        assert p.grad is not None, name
        assert torch.isfinite(p.grad).all(), name
        assert p.grad.abs().sum() > 0, name
