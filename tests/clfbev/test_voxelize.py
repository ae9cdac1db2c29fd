"""Dynamic voxelization vs a brute-force numpy reference."""

import numpy as np
import pytest
import torch

from clfbev.ops.voxelize import voxelize

PC_RANGE = (-4.0, -3.0, -1.0, 4.0, 3.0, 1.0)
VOXEL = (1.0, 0.75, 0.5)  # grid (nz, ny, nx) = (4, 8, 8)
GRID = (4, 8, 8)


def random_points(n=1500, batch_size=2, seed=0, margin=0.5):
    """(n, 4) float32 points partly outside PC_RANGE, and their (n,) batch index."""
    rng = np.random.default_rng(seed)
    lo = np.array(PC_RANGE[:3]) - margin
    hi = np.array(PC_RANGE[3:]) + margin
    xyz = rng.uniform(lo, hi, size=(n, 3))
    pts = np.concatenate([xyz, rng.normal(size=(n, 1))], axis=1).astype(np.float32)
    b = rng.integers(0, batch_size, size=n)
    return torch.from_numpy(pts), torch.from_numpy(b)


def reference(points, batch_idx):
    """Per point: voxel key (b, z, y, x) as a tuple, or None when outside. Same float32 ops."""
    p = points.numpy()
    lo = np.array(PC_RANGE[:3], dtype=np.float32)
    vs = np.array(VOXEL, dtype=np.float32)
    ijk = np.floor((p[:, :3] - lo) / vs).astype(np.int64)
    inside = np.all((ijk >= 0) & (ijk < np.array(GRID[::-1])), axis=1)
    b = batch_idx.numpy()
    return [
        (int(b[i]), int(ijk[i, 2]), int(ijk[i, 1]), int(ijk[i, 0])) if inside[i] else None
        for i in range(len(p))
    ]


def reference_voxels(points, batch_idx):
    """Dict key -> input indices of its points, in input order; dict order = first appearance."""
    vox = {}
    for i, k in enumerate(reference(points, batch_idx)):
        if k is not None:
            vox.setdefault(k, []).append(i)
    return vox


def check_against_reference(points, batch_idx, max_voxels):
    v = voxelize(points, batch_idx, PC_RANGE, VOXEL, max_voxels)
    assert v.grid_shape == GRID
    ref = reference_voxels(points, batch_idx)
    # Kept: per sample the max_voxels that appear first; rows sorted by (b, z, y, x).
    expected = []
    for b in sorted({k[0] for k in ref}):
        expected += sorted([k for k in ref if k[0] == b][:max_voxels])
    assert [tuple(c) for c in v.coords.tolist()] == expected
    # Every point of a kept voxel, grouped voxel by voxel, in input order inside each voxel.
    assert v.point_index.tolist() == [i for key in expected for i in ref[key]]
    assert v.voxel_id.tolist() == [row for row, key in enumerate(expected) for _ in ref[key]]
    assert v.num_points.tolist() == [len(ref[key]) for key in expected]
    return v, ref


def test_every_point_in_range_is_kept():
    points, batch_idx = random_points(n=6000)
    v, ref = check_against_reference(points, batch_idx, max_voxels=10_000)
    assert v.point_index.numel() == sum(len(i) for i in ref.values())
    assert max(len(i) for i in ref.values()) > 10  # voxels above the old 10-point cap
    assert v.coords.dtype == torch.long and v.num_points.dtype == torch.long
    assert (torch.diff(v.voxel_id) >= 0).all()


def test_max_voxels_cap_is_per_sample():
    points, batch_idx = random_points(seed=2)
    v, ref = check_against_reference(points, batch_idx, max_voxels=7)
    assert torch.equal(torch.bincount(v.coords[:, 0]), torch.tensor([7, 7]))


def test_out_of_range_dropped_and_coords_order():
    # Range x in [-4, 4), y in [-3, 3), z in [-1, 1); voxel (1, 0.75, 0.5).
    pts = torch.tensor(
        [
            [-4.0, -3.0, -1.0, 1.0],  # lower corner: kept, voxel (z, y, x) = (0, 0, 0)
            [3.5, 2.9, 0.9, 2.0],  # kept, voxel (3, 7, 7)
            [0.2, 0.8, 0.3, 3.0],  # kept, voxel (2, 5, 4)
            [4.0, 0.0, 0.0, 4.0],  # x at the upper bound: dropped
            [0.0, -3.01, 0.0, 5.0],  # y below: dropped
            [0.0, 0.0, 1.0, 6.0],  # z at the upper bound: dropped
        ]
    )
    v = voxelize(pts, torch.tensor([1, 0, 1, 0, 0, 1]), PC_RANGE, VOXEL, 100)
    # Sorted by (b, z, y, x).
    assert v.coords.tolist() == [[0, 3, 7, 7], [1, 0, 0, 0], [1, 2, 5, 4]]
    assert v.num_points.tolist() == [1, 1, 1]
    assert pts[v.point_index, 3].tolist() == [2.0, 1.0, 3.0]


def test_empty_and_all_outside():
    pts = torch.tensor([[10.0, 0.0, 0.0, 1.0]])
    v = voxelize(pts, torch.zeros(1, dtype=torch.long), PC_RANGE, VOXEL, 100)
    assert v.point_index.shape == (0,) and v.coords.shape == (0, 4) and v.num_points.shape == (0,)


def test_deterministic_and_order_invariant_voxels():
    points, batch_idx = random_points(seed=3)
    a = voxelize(points, batch_idx, PC_RANGE, VOXEL, 20)
    b = voxelize(points.clone(), batch_idx.clone(), PC_RANGE, VOXEL, 20)
    for x, y in [(a.point_index, b.point_index), (a.coords, b.coords), (a.num_points, b.num_points)]:
        assert torch.equal(x, y)
    # Without the cap, shuffling the points changes neither the voxels nor their order or counts.
    perm = torch.randperm(len(points), generator=torch.Generator().manual_seed(0))
    c = voxelize(points, batch_idx, PC_RANGE, VOXEL, 10_000)
    d = voxelize(points[perm], batch_idx[perm], PC_RANGE, VOXEL, 10_000)
    assert torch.equal(c.coords, d.coords) and torch.equal(c.num_points, d.num_points)
    assert torch.equal(perm[d.point_index].sort().values, c.point_index.sort().values)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_matches_cpu():
    points, batch_idx = random_points(seed=4)
    a = voxelize(points, batch_idx, PC_RANGE, VOXEL, 20)
    g = voxelize(points.to("cuda"), batch_idx.to("cuda"), PC_RANGE, VOXEL, 20)
    assert torch.equal(a.point_index, g.point_index.cpu()) and torch.equal(a.coords, g.coords.cpu())
    assert torch.equal(a.num_points, g.num_points.cpu())
