"""Pure-torch sparse conv vs dense nn.Conv3d: values, active sites and gradients.

Everything runs in float64 so that equality to 1e-10 (values) / 1e-8 (grads) is meaningful; the
two paths sum the same products in a different order, nothing else.
"""

import pytest
import torch
import torch.nn.functional as F
from torch import nn

from clfbev.ops.sparse_conv import (
    SparseConv3d,
    SparseTensor,
    SubMConv3d,
    subm_rulebook,
    use_spconv,
)

SHAPE = (6, 9, 10)  # (nz, ny, nx)
CIN, COUT = 3, 4
TOL = dict(rtol=0, atol=1e-8)


def random_grid(batch_size=2, shape=SHAPE, density=0.15, seed=0, device="cpu"):
    """Dense zero-filled input (B, C, nz, ny, nx) and the same data as a SparseTensor.

    The dense tensor is built first and the sparse one is read out of it, so the reference does
    not depend on SparseTensor.dense().
    """
    g = torch.Generator().manual_seed(seed)
    mask = torch.rand((batch_size, *shape), generator=g) < density
    dense = torch.randn((batch_size, CIN, *shape), generator=g, dtype=torch.float64) * mask[:, None]
    coords = torch.nonzero(mask)  # (N, 4) (b, z, y, x), row-major = lexicographic order
    feats = dense[coords[:, 0], :, coords[:, 1], coords[:, 2], coords[:, 3]]
    dense, coords, feats = dense.to(device), coords.to(device), feats.to(device)
    return dense, SparseTensor(feats.clone(), coords, shape, batch_size), mask.to(device)


def dense_twin(sparse_conv, padding, stride=1):
    ref = nn.Conv3d(CIN, COUT, sparse_conv.kernel_size, stride=stride, padding=padding).double()
    ref = ref.to(sparse_conv.weight.device)
    with torch.no_grad():
        ref.weight.copy_(sparse_conv.weight)
        ref.bias.copy_(sparse_conv.bias)
    return ref


def at(dense, coords):
    """(B, C, nz, ny, nx) -> (N, C) rows at (b, z, y, x)."""
    return dense[coords[:, 0], :, coords[:, 1], coords[:, 2], coords[:, 3]]


def test_init_matches_conv3d():
    torch.manual_seed(3)
    a = SubMConv3d(CIN, COUT, 3)
    torch.manual_seed(3)
    b = nn.Conv3d(CIN, COUT, 3, padding=1)
    assert a.weight.shape == b.weight.shape == (COUT, CIN, 3, 3, 3)
    assert torch.equal(a.weight, b.weight) and torch.equal(a.bias, b.bias)


@pytest.mark.parametrize("kernel", [3, (1, 3, 3), 5])
def test_subm_matches_dense_values_and_grads(kernel):
    torch.manual_seed(0)
    dense, x, _ = random_grid()
    conv = SubMConv3d(CIN, COUT, kernel).double()
    ref = dense_twin(conv, padding=tuple(k // 2 for k in conv.kernel_size))
    x.features.requires_grad_(True)
    dense.requires_grad_(True)

    out = conv(x)
    assert torch.equal(out.coords, x.coords) and out.spatial_shape == SHAPE
    # The loss depends on active-site outputs only: there, and only there, submanifold conv
    # equals the dense conv of the zero-filled input.
    r = torch.randn(out.features.shape, dtype=torch.float64)
    y_active = at(ref(dense), x.coords)
    torch.testing.assert_close(out.features, y_active, **TOL)

    (out.features * r).sum().backward()
    (y_active * r).sum().backward()
    torch.testing.assert_close(x.features.grad, at(dense.grad, x.coords), **TOL)
    torch.testing.assert_close(conv.weight.grad, ref.weight.grad, **TOL)
    torch.testing.assert_close(conv.bias.grad, ref.bias.grad, **TOL)


@pytest.mark.parametrize(
    "kernel, stride, padding",
    [(3, 2, 1), (2, 2, 0), ((3, 1, 1), (2, 1, 1), 0), (3, 1, 1), (3, 2, 0)],
)
def test_strided_matches_dense_everywhere(kernel, stride, padding):
    torch.manual_seed(1)
    dense, x, mask = random_grid()
    conv = SparseConv3d(CIN, COUT, kernel, stride, padding).double()
    ref = dense_twin(conv, padding=conv.padding, stride=conv.stride)
    x.features.requires_grad_(True)
    dense.requires_grad_(True)

    out = conv(x)
    y = ref(dense)
    assert out.spatial_shape == tuple(y.shape[2:])

    # Output sites are exactly the positions that receive at least one active input.
    ones = torch.ones((1, 1, *conv.kernel_size), dtype=torch.float64)
    hit = F.conv3d(mask[:, None].double(), ones, stride=conv.stride, padding=conv.padding)[:, 0] > 0
    assert torch.equal(out.coords, torch.nonzero(hit))

    # Everywhere: dense conv == sparse output at active sites, == bias alone elsewhere.
    bias_elsewhere = conv.bias.view(1, -1, 1, 1, 1) * (~hit)[:, None]
    full = out.dense() + bias_elsewhere
    torch.testing.assert_close(full, y, **TOL)

    r = torch.randn(y.shape, dtype=torch.float64)
    (full * r).sum().backward()
    (y * r).sum().backward()
    torch.testing.assert_close(x.features.grad, at(dense.grad, x.coords), **TOL)
    torch.testing.assert_close(conv.weight.grad, ref.weight.grad, **TOL)
    torch.testing.assert_close(conv.bias.grad, ref.bias.grad, **TOL)


def test_batch_samples_do_not_mix():
    """Sample 1 has the same sites as sample 0 but other features; each must see only itself."""
    torch.manual_seed(2)
    _, x0, _ = random_grid(batch_size=1, seed=5)
    n = x0.coords.shape[0]
    c1 = x0.coords.clone()
    c1[:, 0] = 1
    f1 = torch.randn(n, CIN, dtype=torch.float64)
    both = SparseTensor(torch.cat([x0.features, f1]), torch.cat([x0.coords, c1]), SHAPE, 2)
    alone1 = SparseTensor(f1, x0.coords, SHAPE, 1)
    for conv in [SubMConv3d(CIN, COUT, 3).double(), SparseConv3d(CIN, COUT, 3, 2, 1).double()]:
        ob, o0, o1 = conv(both), conv(x0), conv(alone1)
        is0 = ob.coords[:, 0] == 0
        torch.testing.assert_close(ob.features[is0], o0.features, **TOL)
        torch.testing.assert_close(ob.features[~is0], o1.features, **TOL)
        assert torch.equal(ob.coords[~is0, 1:], o1.coords[:, 1:])


def test_shared_rulebook_and_dense_roundtrip():
    torch.manual_seed(4)
    dense, x, _ = random_grid()
    assert torch.equal(x.dense(), dense)
    conv = SubMConv3d(CIN, COUT, 3).double()
    rb = subm_rulebook(x.coords, x.spatial_shape, 3)
    assert torch.equal(conv(x, rb).features, conv(x).features)


def test_empty_input():
    x = SparseTensor(torch.zeros(0, CIN), torch.zeros(0, 4, dtype=torch.long), SHAPE, 2)
    assert SubMConv3d(CIN, COUT).forward(x).features.shape == (0, COUT)
    out = SparseConv3d(CIN, COUT, 3, 2, 1)(x)
    assert out.features.shape == (0, COUT) and out.spatial_shape == (3, 5, 5)
    assert out.dense().shape == (2, COUT, 3, 5, 5)


def test_spconv_never_chosen_on_cpu():
    assert use_spconv("cpu") is False


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_matches_cpu():
    torch.manual_seed(0)
    for conv in [SubMConv3d(CIN, COUT, 3).double(), SparseConv3d(CIN, COUT, 3, 2, 1).double()]:
        _, xc, _ = random_grid()
        _, xg, _ = random_grid(device="cuda")
        oc = conv(xc)
        og = conv.to("cuda")(xg)
        assert torch.equal(oc.coords, og.coords.cpu())
        torch.testing.assert_close(oc.features, og.features.cpu(), **TOL)
