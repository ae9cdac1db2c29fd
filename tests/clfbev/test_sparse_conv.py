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
    apply_rulebook,
    strided_rulebook,
    subm_rulebook,
    use_spconv,
)
from clfbev.ops.sparse_conv import rulebook as rulebook_module

pytestmark = pytest.mark.usefixtures("one_thread")

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


def dense_twin(conv, padding, stride=1):
    ref = nn.Conv3d(conv.in_channels, conv.out_channels, conv.kernel_size, stride=stride, padding=padding)
    ref = ref.double().to(conv.weight.device)
    with torch.no_grad():
        ref.weight.copy_(conv.weight)
        ref.bias.copy_(conv.bias)
    return ref


def at(dense, coords):
    """(B, C, nz, ny, nx) -> (N, C) rows at (b, z, y, x)."""
    return dense[coords[:, 0], :, coords[:, 1], coords[:, 2], coords[:, 3]]


def assert_same_grads(sparse_out, dense_out, x, dense, conv, ref):
    """Back-propagate one random cotangent through the sparse and the dense result and compare
    the input and weight (and bias) gradients."""
    r = torch.randn(dense_out.shape, dtype=torch.float64)
    (sparse_out * r).sum().backward()
    (dense_out * r).sum().backward()
    torch.testing.assert_close(x.features.grad, at(dense.grad, x.coords), **TOL)
    torch.testing.assert_close(conv.weight.grad, ref.weight.grad, **TOL)
    if conv.bias is not None:
        torch.testing.assert_close(conv.bias.grad, ref.bias.grad, **TOL)


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

    assert_same_grads(full, y, x, dense, conv, ref)


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


# ------------------------------------------------------------------ rulebooks and the conv's own backward


def with_channels(x, c_in, seed=0):
    """The same sites with c_in random float64 channels, and its zero-filled dense twin."""
    g = torch.Generator().manual_seed(seed)
    feats = torch.randn((x.coords.shape[0], c_in), generator=g, dtype=torch.float64)
    y = x.replace_features(feats)
    return y.dense(), y


def brute_force_pairs(coords, shape, kernel, stride, padding, out_coords):
    """{(tap, input row, output row)} straight from the conv3d definition, in plain Python."""
    row_in = {tuple(c): i for i, c in enumerate(coords.tolist())}
    pairs = set()
    for o, (b, *oc) in enumerate(out_coords.tolist()):
        for tap, k in enumerate(torch.cartesian_prod(*[torch.arange(n) for n in kernel]).tolist()):
            i = tuple([b] + [oc[a] * stride[a] - padding[a] + k[a] for a in range(3)])
            if i in row_in:
                pairs.add((tap, row_in[i], o))
    return pairs


def rulebook_pairs(rb):
    starts = torch.tensor([0] + rb.offset_counts).cumsum(0).tolist()
    return {(tap, i, o) for tap in range(len(rb.offset_counts))
            for i, o in zip(rb.in_rows[starts[tap]:starts[tap + 1]].tolist(),
                            rb.out_rows[starts[tap]:starts[tap + 1]].tolist())}


@pytest.mark.parametrize(
    "kernel, stride, padding",
    [
        ((3, 3, 3), None, None),  # None: submanifold
        ((1, 3, 5), None, None),
        ((3, 3, 3), (2, 2, 2), (1, 1, 1)),
        ((3, 3, 3), (2, 1, 1), (1, 1, 1)),
        ((2, 2, 2), (2, 2, 2), (0, 0, 0)),
        ((1, 3, 3), (2, 2, 1), (0, 1, 1)),  # kernel 1 < stride 2 along z: odd-z inputs feed nothing
    ],
)
def test_rulebook_pairs_match_brute_force(kernel, stride, padding):
    _, x, _ = random_grid(density=0.3, seed=7)
    if stride is None:
        rb = subm_rulebook(x.coords, SHAPE, kernel)
        stride, padding = (1, 1, 1), tuple(k // 2 for k in kernel)
    else:
        rb = strided_rulebook(x.coords, SHAPE, kernel, stride, padding)
    pairs = brute_force_pairs(x.coords, SHAPE, kernel, stride, padding, rb.out_coords)
    assert rulebook_pairs(rb) == pairs
    assert sum(rb.offset_counts) == len(pairs) == rb.in_rows.numel()


def test_subm_rulebook_is_symmetric():
    """o reads i through tap k exactly when i reads o through the mirrored tap K - 1 - k."""
    _, x, _ = random_grid(density=0.3, seed=8)
    nb = subm_rulebook(x.coords, SHAPE, 3).neighbours  # (N, K), N where none
    n, K = nb.shape
    o, k = torch.nonzero(nb < n, as_tuple=True)
    assert torch.equal(nb[nb[o, k], K - 1 - k], o)
    assert torch.equal(nb[:, K // 2], torch.arange(n))  # the centre tap reads the site itself
    assert ((nb < n).sum() - n) % 2 == 0


def test_dense_table_and_sorted_lookup_agree(monkeypatch):
    _, x, _ = random_grid(seed=9)
    dense = [subm_rulebook(x.coords, SHAPE, 3), strided_rulebook(x.coords, SHAPE, 3, 2, 1)]
    monkeypatch.setattr(rulebook_module, "DENSE_TABLE_MAX_CELLS", 0)
    # The patch reaches the builders: their lookups now take the sorted path.
    assert rulebook_module._SiteLookup(torch.arange(3), 8).table is None
    sorted_ = [subm_rulebook(x.coords, SHAPE, 3), strided_rulebook(x.coords, SHAPE, 3, 2, 1)]
    for a, b in zip(dense, sorted_):
        assert torch.equal(a.neighbours, b.neighbours) and torch.equal(a.out_coords, b.out_coords)


@pytest.mark.parametrize("c_in, c_out", [(2, 5), (5, 2)])  # gather first / multiply first
@pytest.mark.parametrize("kind", ["subm", "strided", "z_only"])
def test_gradcheck(kind, c_in, c_out):
    _, x, _ = random_grid(batch_size=2, shape=(3, 4, 5), density=0.3, seed=10)
    if kind == "subm":
        rb = subm_rulebook(x.coords, x.spatial_shape, 3)
    else:
        stride = (2, 2, 2) if kind == "strided" else (2, 1, 1)
        rb = strided_rulebook(x.coords, x.spatial_shape, 3, stride, 1)
    g = torch.Generator().manual_seed(11)
    f = torch.randn((x.coords.shape[0], c_in), generator=g, dtype=torch.float64, requires_grad=True)
    w = torch.randn((c_out, c_in, 3, 3, 3), generator=g, dtype=torch.float64, requires_grad=True)
    b = torch.randn(c_out, generator=g, dtype=torch.float64, requires_grad=True)
    # fast_mode checks random projections of the Jacobian: the full one costs a backward per
    # output value, minutes for this test.
    assert torch.autograd.gradcheck(lambda f, w, b: apply_rulebook(f, w, b, rb), (f, w, b), fast_mode=True)


@pytest.mark.parametrize("c_in, c_out", [(2, 5), (5, 2)])
def test_subm_both_channel_paths_match_dense(c_in, c_out):
    torch.manual_seed(12)
    _, x0, _ = random_grid(seed=12)
    dense, x = with_channels(x0, c_in)
    conv = SubMConv3d(c_in, c_out, 3).double()
    ref = dense_twin(conv, padding=1)
    x.features.requires_grad_(True)
    dense.requires_grad_(True)
    out, y = conv(x).features, at(ref(dense), x.coords)
    torch.testing.assert_close(out, y, **TOL)
    assert_same_grads(out, y, x, dense, conv, ref)


@pytest.mark.parametrize("c_in, c_out", [(2, 5), (5, 2)])
@pytest.mark.parametrize("kernel, stride, padding", [(3, 2, 1), (3, (2, 1, 1), 1), (2, 2, 0)])
def test_sites_at_the_grid_edges(kernel, stride, padding, c_in, c_out):
    """Corner and face sites (and, for k=2 s=2 on the odd x size, inputs no output reads)."""
    nz, ny, nx = SHAPE
    corners = [[b, z, y, x] for b in (0, 1) for z in (0, nz - 1) for y in (0, ny - 1) for x in (0, nx - 1)]
    faces = [[0, 2, 0, 4], [1, nz - 1, 3, 5], [0, 3, ny - 1, 2], [1, 1, 4, nx - 1]]
    coords = torch.tensor(sorted(corners + faces))
    _, x = with_channels(SparseTensor(torch.zeros(len(coords), 1), coords, SHAPE, 2), c_in, seed=13)
    dense = x.dense().detach().requires_grad_(True)
    x.features.requires_grad_(True)
    torch.manual_seed(13)
    for conv, ref in [
        (c := SubMConv3d(c_in, c_out, 3).double(), dense_twin(c, padding=1)),
        (c := SparseConv3d(c_in, c_out, kernel, stride, padding).double(), dense_twin(c, c.padding, c.stride)),
    ]:
        x.features.grad, dense.grad = None, None
        out, y = conv(x), ref(dense)
        if isinstance(conv, SubMConv3d):
            full, y = out.features, at(y, x.coords)
        else:
            full = out.dense() + conv.bias.view(1, -1, 1, 1, 1) * (out.dense() == 0).all(1, keepdim=True)
        torch.testing.assert_close(full, y, **TOL)
        assert_same_grads(full, y, x, dense, conv, ref)


def test_batch_with_an_empty_sample_in_the_middle():
    """Batch of 3, sample 1 without sites: samples 0 and 2 are computed as if alone."""
    _, x0, _ = random_grid(batch_size=1, seed=14)
    _, x2, _ = random_grid(batch_size=1, seed=15)
    c2 = x2.coords.clone()
    c2[:, 0] = 2
    both = SparseTensor(torch.cat([x0.features, x2.features]), torch.cat([x0.coords, c2]), SHAPE, 3)
    torch.manual_seed(14)
    for conv in [SubMConv3d(CIN, COUT, 3).double(), SparseConv3d(CIN, COUT, 3, (2, 1, 1), 1).double()]:
        ob, o0, o2 = conv(both), conv(x0), conv(x2)
        assert set(ob.coords[:, 0].tolist()) == {0, 2}
        is0 = ob.coords[:, 0] == 0
        torch.testing.assert_close(ob.features[is0], o0.features, **TOL)
        torch.testing.assert_close(ob.features[~is0], o2.features, **TOL)
        assert ob.dense().shape[0] == 3 and not ob.dense()[1].any()


def test_empty_input_backward():
    for conv in [SubMConv3d(CIN, COUT), SubMConv3d(COUT, CIN), SparseConv3d(CIN, COUT, 3, 2, 1)]:
        c_in = conv.in_channels
        f = torch.zeros(0, c_in, requires_grad=True)
        out = conv(SparseTensor(f, torch.zeros(0, 4, dtype=torch.long), SHAPE, 2))
        out.dense().sum().backward()
        assert f.grad.shape == (0, c_in)
        assert torch.equal(conv.weight.grad, torch.zeros_like(conv.weight))


def test_bit_identical_across_runs():
    """Training resumes bit-identically: no scatter with a run-dependent order anywhere."""
    _, x0, _ = random_grid(shape=(8, 16, 16), density=0.2, seed=16)
    results = []
    for _ in range(2):
        torch.manual_seed(16)
        a, b = SubMConv3d(CIN, 8, 3), SparseConv3d(8, 2, 3, 2, 1)
        f = x0.features.float().clone().requires_grad_(True)
        x = SparseTensor(f, x0.coords, x0.spatial_shape, x0.batch_size)
        y = b(a(x)).features
        (y.square()).sum().backward()
        results.append([y, f.grad, a.weight.grad, b.weight.grad])
    assert all(torch.equal(p, q) for p, q in zip(*results))
