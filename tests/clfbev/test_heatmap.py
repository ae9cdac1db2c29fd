"""The camera BEV's class-centre heatmap (clfbev/supervision/heatmap.py) and its aux head's loss:
the radius against CornerNet's IoU bound computed from the rectangles themselves, the target
against a drawing of each box by hand, the focal loss against its formula."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from clfbev.supervision.heatmap import bev_heatmap, centre_radius, gaussian_radius, heatmap_loss

pytestmark = pytest.mark.usefixtures("one_thread")


def iou(a: tuple, b: tuple) -> float:
    """IoU of two axis-aligned rectangles (x0, y0, x1, y1)."""
    ix = max(0.0, min(a[2], b[2]) - max(a[0], b[0]))
    iy = max(0.0, min(a[3], b[3]) - max(a[1], b[1]))
    inter = ix * iy
    area = lambda r: (r[2] - r[0]) * (r[3] - r[1])   # noqa: E731
    return inter / (area(a) + area(b) - inter)


@pytest.mark.parametrize("overlap", [0.1, 0.5, 0.7])
def test_the_radius_is_the_worst_case_corner_shift_at_the_overlap(overlap):
    """At the radius, each of CornerNet's three corner shifts keeps IoU >= the overlap and the
    worst of them meets it exactly; a shift a little larger breaks it."""
    rng = np.random.default_rng(0)
    sizes = rng.uniform(0.5, 20.0, size=(50, 2))
    r = gaussian_radius(torch.from_numpy(sizes[:, 0]), torch.from_numpy(sizes[:, 1]), overlap).numpy()
    for (l, w), rad in zip(sizes, r):
        box = (0.0, 0.0, l, w)

        def cases(d):
            return [iou(box, (d, d, l + d, w + d)),            # translated
                    iou(box, (d, d, l - d, w - d)),            # both corners inward
                    iou(box, (-d, -d, l + d, w + d))]          # both corners outward
        at = cases(rad)
        assert min(at) == pytest.approx(overlap, abs=1e-9)
        assert all(v >= overlap - 1e-9 for v in at)
        assert min(cases(rad * 1.01)) < overlap


def test_centre_radius_truncates_and_has_centerpoints_floor():
    r = gaussian_radius(torch.tensor([40.0, 5.625]), torch.tensor([30.0, 2.375]))
    got = centre_radius(torch.tensor([40.0, 5.625]), torch.tensor([30.0, 2.375]))
    assert r[0] > 3 and got[0] == int(r[0])                   # a large box: its own radius
    assert got[1] == 2                                        # a car at 0.8 m cells: the floor of 2


def _drawn(boxes, labels, n_classes, pc_range, cell):
    """The heatmap drawn box by box, in plain numpy (the test's own reading of the rule)."""
    xmin, ymin, _, xmax, ymax, _ = pc_range
    nx, ny = round((xmax - xmin) / cell), round((ymax - ymin) / cell)
    out = np.zeros((len(boxes), n_classes, ny, nx))
    for b, (bx, lab) in enumerate(zip(boxes, labels)):
        for box, c in zip(bx.numpy(), lab.numpy()):
            ix, iy = math.floor((box[0] - xmin) / cell), math.floor((box[1] - ymin) / cell)
            if not (0 <= ix < nx and 0 <= iy < ny):
                continue
            r = int(centre_radius(torch.tensor([box[3] / cell]), torch.tensor([box[4] / cell]))[0])
            sigma = (2 * r + 1) / 6
            for dy in range(-r, r + 1):
                for dx in range(-r, r + 1):
                    if 0 <= iy + dy < ny and 0 <= ix + dx < nx:
                        v = math.exp(-(dx * dx + dy * dy) / (2 * sigma * sigma))
                        out[b, c, iy + dy, ix + dx] = max(out[b, c, iy + dy, ix + dx], v)
    return out


def test_the_heatmap_peaks_at_each_centre_with_its_gaussian_and_keeps_the_max():
    pc_range, cell = (-12.8, -12.8, -5.0, 12.8, 12.8, 3.0), 0.8
    boxes = [torch.tensor([[0.1, 0.2, 0.0, 4.5, 1.9, 1.6, 0.3],       # car
                           [1.3, 0.9, 0.0, 4.6, 2.0, 1.6, 1.0],       # a car overlapping it
                           [-12.7, 5.0, 0.0, 30.0, 25.0, 3.0, 0.0],   # a huge box at the edge: radius > 2, clipped
                           [5.0, -3.0, 0.0, 0.7, 0.7, 1.8, 0.0],      # a walker
                           [20.0, 0.0, 0.0, 4.5, 1.9, 1.6, 0.0]]),    # outside the grid: nothing
             torch.tensor([[3.0, 3.0, 0.0, 4.5, 1.9, 1.6, 0.0]])]
    labels = [torch.tensor([0, 0, 1, 2, 0]), torch.tensor([0])]
    heat = bev_heatmap(boxes, labels, 3, pc_range, (cell, cell))
    want = _drawn(boxes, labels, 3, pc_range, cell)
    assert heat.shape == (2, 3, 32, 32) and heat.dtype == torch.float32
    np.testing.assert_allclose(heat.numpy(), want, rtol=0, atol=1e-7)
    # Exactly 1 at each in-grid centre cell, in its class's channel; nowhere else.
    centres = [(0, 0, 16, 16), (0, 0, 17, 17), (0, 1, 22, 0), (0, 2, 12, 22), (1, 0, 19, 19)]
    assert sorted(map(tuple, (heat == 1).nonzero().tolist())) == sorted(centres)
    # The two cars overlap: the cells between them hold the larger of their two Gaussians.
    sigma = 5 / 6
    g = lambda d2: math.exp(-d2 / (2 * sigma**2))              # noqa: E731
    assert heat[0, 0, 16, 17].item() == pytest.approx(max(g(1), g(1)), abs=1e-7)
    assert heat[0, 0, 18, 16].item() == pytest.approx(max(g(4), g(2)), abs=1e-7)
    assert heat[0, 0, 16, 20].item() == 0.0                   # beyond both cars' windows (r 2)
    assert heat[0, 2].count_nonzero() == 25                   # the walker: a 5 x 5 window


def test_the_focal_loss_is_zero_for_a_perfect_prediction_and_its_formula_otherwise():
    pc_range = (-12.8, -12.8, -5.0, 12.8, 12.8, 3.0)
    heat = bev_heatmap([torch.tensor([[0.1, 0.2, 0.0, 4.5, 1.9, 1.6, 0.3], [5.0, -3.0, 0.0, 0.7, 0.7, 1.8, 0.0]])],
                       [torch.tensor([0, 2])], 3, pc_range, (0.8, 0.8))
    perfect = torch.where(heat == 1, 30.0, -30.0)
    assert heatmap_loss(perfect, heat).item() < 1e-6
    logits = torch.randn(heat.shape, generator=torch.Generator().manual_seed(0))
    got = heatmap_loss(logits, heat).item()
    p = np.clip(1 / (1 + np.exp(-logits.double().numpy())), 1e-4, 1 - 1e-4)
    y = heat.double().numpy()
    pos = y == 1
    want = -(np.sum((1 - p[pos]) ** 2 * np.log(p[pos])) + np.sum((1 - y[~pos]) ** 4 * p[~pos] ** 2
                                                                 * np.log(1 - p[~pos]))) / pos.sum()
    assert got > 0.1 and got == pytest.approx(want, rel=1e-5)
    # A miss costs more than a hit: one centre predicted at 0.5 instead of ~1.
    worse = perfect.clone()
    worse[0, 0, 16, 16] = 0.0
    assert heatmap_loss(worse, heat).item() == pytest.approx(-0.25 * math.log(0.5) / 2, rel=1e-4)
