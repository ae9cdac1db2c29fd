"""``density`` (MultiCorrupt's "points reducing"): exactly round(n f) of the n loaded points
dropped, the others kept bit for bit and in order."""
from __future__ import annotations

import numpy as np
import pytest

from clfbev.config import tiny
from clfbev.corruptions import Corruption, corrupt_points, parse
from clfbev.data import NuScenesDetection

pytestmark = pytest.mark.usefixtures("one_thread")


def _kept_indices(clean: np.ndarray, kept: np.ndarray) -> np.ndarray:
    """The index in ``clean`` of every row of ``kept`` (rows are unique: float xyz, intensity, lag)."""
    where = {row.tobytes(): i for i, row in enumerate(clean)}
    assert len(where) == len(clean)
    return np.array([where[row.tobytes()] for row in kept], dtype=np.int64)


def test_density_drops_exactly_round_n_f_points(tiny_dataset):
    cfg = tiny().data_config()
    points = NuScenesDetection(tiny_dataset, "v1.0-sim", "sim-val", cfg)[0].points
    for fraction in (0.2, 0.4, 0.6, 0.123):          # MultiCorrupt's three levels, and an odd one
        kept = NuScenesDetection(tiny_dataset, "v1.0-sim", "sim-val", cfg, (parse(f"density:{fraction}"),))[0].points
        assert len(points) - len(kept) == round(len(points) * fraction)
        idx = _kept_indices(points, kept)
        assert (np.diff(idx) > 0).all()                      # in their order, each once
        np.testing.assert_array_equal(kept, points[idx])     # bit for bit


def test_density_bounds_and_composition():
    rng = np.random.default_rng(0)
    points = rng.normal(0, 20, (1001, 5)).astype(np.float32)
    rings = rng.integers(0, 32, 1001).astype(np.float32)
    forward = np.array([0.0, 1.0, 0.0])
    assert len(corrupt_points(points, rings, forward, [Corruption("density", 0.0)], "t")) == 1001
    assert len(corrupt_points(points, rings, forward, [Corruption("density", 1.0)], "t")) == 0
    # After fov, density drops its fraction of the points fov kept.
    in_fov = len(corrupt_points(points, rings, forward, [Corruption("fov", 90)], "t"))
    both = corrupt_points(points, rings, forward, [Corruption("fov", 90), Corruption("density", 0.5)], "t")
    assert len(both) == in_fov - round(in_fov * 0.5)
    # The draw depends on the sample token and is repeatable.
    a = corrupt_points(points, rings, forward, [Corruption("density", 0.5)], "a")
    np.testing.assert_array_equal(a, corrupt_points(points, rings, forward, [Corruption("density", 0.5)], "a"))
    assert not np.array_equal(a, corrupt_points(points, rings, forward, [Corruption("density", 0.5)], "b"))
