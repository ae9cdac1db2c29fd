"""Raindrop and snowflake distributions: closed on the rate, their extinction, their samplers.

Every expected value is computed here from the published formulas, by its own quadrature or in
closed form, not through the module's integrator."""
from __future__ import annotations

import math

import numpy as np
import pytest

from simgen.weather import particles as P

D = np.linspace(0.0, 6.0, 600_001)          # mm, a fine uniform grid for the trapezoid rule


def _trapz(y: np.ndarray) -> float:
    return float(np.sum((y[1:] + y[:-1]) * 0.5 * np.diff(D)))


def _flux_mm_h(n0: float, slope: float, speed: np.ndarray) -> float:
    """Water flux (mm/h): drops' volume (pi/6 D^3 mm^3 = pi/6 D^3 1e-9 m^3) x number x speed (m/s), in
    m/s of water, to mm/h."""
    n = n0 * np.exp(-slope * D)
    return _trapz(np.pi / 6 * D**3 * 1e-9 * n * speed) * 1e3 * 3600


@pytest.mark.parametrize("rate", [1.0, 10.0, 25.0, 50.0, 100.0])
def test_rain_distribution_carries_its_rate(rate):
    d = P.rain_distribution(rate)
    assert d.n0 == 8000.0 and d.d_max == 6.0
    atlas = np.maximum(9.65 - 10.3 * np.exp(-0.6 * D), 0.0)
    assert _flux_mm_h(d.n0, d.slope, atlas) == pytest.approx(rate, rel=0.05)
    # The closure is a small correction of Marshall and Palmer's slope, not a new distribution.
    assert d.slope == pytest.approx(4.1 * rate**-0.21, rel=0.05)


@pytest.mark.parametrize("rate", [0.5, 1.0, 2.5])
def test_snow_distribution_carries_its_rate(rate):
    d = P.snow_distribution(rate)
    assert d.n0 == pytest.approx(3800 * rate**-0.87, rel=1e-12)
    assert _flux_mm_h(d.n0, d.slope, np.full_like(D, 1.0)) == pytest.approx(rate, rel=0.05)
    assert d.slope == pytest.approx(2.55 * rate**-0.48, rel=0.05)     # 25.5 R^-0.48 per cm


def test_the_published_rain_slope_does_not_close_the_flux():
    """Why the slope is closed: Marshall-Palmer with Atlas' speeds carries 16% too much water at
    10 mm/h (the docstring's figure)."""
    atlas = np.maximum(9.65 - 10.3 * np.exp(-0.6 * D), 0.0)
    assert _flux_mm_h(8000.0, 4.1 * 10**-0.21, atlas) / 10 == pytest.approx(1.164, abs=0.005)


@pytest.mark.parametrize("rate", [2.0, 25.0])
def test_rain_extinction_is_twice_the_drops_cross_section(rate):
    d = P.rain_distribution(rate)
    x = d.slope * 6.0
    # int_0^6 D^2 exp(-s D) dD in closed form
    m2 = 2 / d.slope**3 * (1 - math.exp(-x) * (1 + x + x * x / 2))
    assert P.rain_extinction(rate) == pytest.approx(2 * math.pi / 4 * 1e-6 * d.n0 * m2, rel=1e-9)
    assert P.rain_number_density(rate) == pytest.approx(_trapz(d.n0 * np.exp(-d.slope * D)), rel=1e-6)


def test_snow_extinction_is_twice_the_flakes_cross_section():
    d = P.snow_distribution(1.0)
    # A flake of melted diameter Dm has mass pi/6 Dm^3 mg; at density 0.178 Df^-0.922 g/cm^3
    # (= mg/mm^3) its diameter solves pi/6 0.178 Df^2.078 = pi/6 Dm^3; ice at most.
    df = np.maximum((D**3 / 0.178) ** (1 / 2.078), D / 0.917 ** (1 / 3))
    expected = 2 * 1e-6 * _trapz(np.pi / 4 * df**2 * d.n0 * np.exp(-d.slope * D))
    assert P.snow_extinction(1.0) == pytest.approx(expected, rel=1e-5)
    # The flakes are larger than their melted drops: several times the extinction of the water.
    water = 2 * 1e-6 * _trapz(np.pi / 4 * D**2 * d.n0 * np.exp(-d.slope * D))
    assert P.snow_extinction(1.0) > 3 * water
    assert P.rain_extinction(0.0) == 0.0 and P.snow_extinction(0.0) == 0.0


def test_extinction_grows_with_the_rate():
    assert np.all(np.diff([P.rain_extinction(r) for r in (1, 5, 10, 25, 50, 100)]) > 0)
    assert np.all(np.diff([P.snow_extinction(r) for r in (0.1, 0.5, 1, 2.5, 5)]) > 0)


def test_samplers_draw_the_distribution():
    rng = np.random.default_rng(0)
    d = P.rain_distribution(10.0)
    drops = P.sample_rain_diameters(10.0, 200_000, rng)
    n = d.n0 * np.exp(-d.slope * D)
    mean = _trapz(D * n) / _trapz(n)
    assert drops.min() >= 0 and drops.max() <= 6.0
    assert drops.mean() == pytest.approx(mean, rel=0.01)
    # Above a per-draw lower bound: the distribution conditioned on D >= lo.
    lo = np.full(200_000, 1.5)
    big = d.sample(rng.random(200_000), lo)
    cond = np.where(D >= 1.5, n, 0.0)
    assert big.min() >= 1.5 and big.mean() == pytest.approx(_trapz(D * cond) / _trapz(cond), rel=0.01)
    assert d.number_density(1.5) == pytest.approx(_trapz(cond), rel=1e-4)   # the step costs the trapezoid half a cell
    flakes = P.sample_snow_diameters(1.0, 1000, np.random.default_rng(1))
    melted = P.snow_distribution(1.0).sample(np.random.default_rng(1).random(1000))
    np.testing.assert_allclose(flakes, np.maximum((melted**3 / 0.178) ** (1 / 2.078), melted / 0.917 ** (1 / 3)))
