"""Particles in a lidar's beams: raindrops or snowflakes drawn one by one inside each beam, each
echoing by the lidar equation, the strongest echo reported (in the manner of Hahner et al., CVPR
2022, derived from the paper's description; docs/weather.md has the derivation with units).

A beam is a cone of radius ``a(r) = r_T + theta_T r`` (:data:`simgen.degrade.HDL32E`: the
HDL-32E manual's spot, 1.67 mrad half-angle). A particle at range r with optical diameter d
blocks the share ``s = min(1, (d / 2)^2 / a(r)^2)`` of the beam's cross-section. In lidar.py's
units (a Lambertian surface filling the beam at range R returns ``rho cos / R^2``) its echo is

    p_i = rho_p s_i xi(r_i) / r_i^2 T(r_i)

with ``rho_p`` the particle's Lambertian-equivalent reflectivity (``2 pi / S`` for a particle of
extinction efficiency 2 and lidar ratio S sr), ``xi`` the overlap of beam and receiver field
(:func:`simgen.degrade.overlap`, as for the fog's echo) and ``T(r)`` the two-way transmission in
front of it: ``exp(-depth(r)) prod_{k in front} (1 - s_k)^2``. The surface the ray hit (or the
echo already reported for it) is attenuated by the same T at its range. The sensor reports the
strongest of these echoes if it reaches the clear-weather threshold ``min_return``.

Only the particles that can matter are drawn: those whose echo could reach, at their range and
with T = 1, the ray's level ``q`` (``min_return``, or a tenth of the ray's own echo attenuated by
the mean extinction if that is higher: MARGIN), and those that block at least S_MIN of the beam.
Their number along a ray is Poisson with mean ``M_q(L) = int_0^L pi a(r)^2 N(D >= D_q(r)) dr`` up
to the ray's surface L; the others' mean extinction enters ``depth_q(r) = 2 int_0^r (alpha -
alpha_q(r')) dr'``, so that the mean two-way transmission is ``exp(-2 alpha r)`` with the whole
extinction alpha of the distribution (efficiency 2: the drawn particles' shadows make part of
it, the rest is continuous). A particle left out could only be reported where the drawn ones in
front shadow the ray's echo by more than 1 / MARGIN.
"""
from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from ..degrade import HDL32E, Optics, overlap
from .particles import SizeDistribution

S_MIN = 0.1                  # a particle blocking this share of the beam is drawn even when it cannot echo
MARGIN = 0.1                 # particles that could echo a tenth of the ray's own echo are drawn
LEVEL_STEP = 0.25            # decades between the tabulated levels of the drawing threshold
N_LEVELS = 24                # min_return .. min_return x 10^5.75
TABLE_STEP = 0.02            # m
COUNT_TABLE = 8193           # points of the inverse of the expected count, per level
_KEY = 1.0e4                 # m: above any range, so that ray * _KEY + range orders by ray, then range


@dataclass(frozen=True)
class ParticleField:
    """What the beams of a sweep meet in one precipitation, tabulated per drawing level (L levels,
    ``levels`` (L,) 1/m^2) on the uniform range grid ``r`` (g,) m (step TABLE_STEP, from 0):
    ``d_min`` (L, g) the smallest melted diameter (mm) drawn, ``count`` (L, g) the expected number
    of drawn particles in a beam from 0 to r, ``depth`` (L, g) the two-way optical depth of the
    particles not drawn, ``count_to_range`` (L, h) the range at which ``count`` reaches
    ``j count[:, -1] / (h - 1)``; ``xi`` (g,) the overlap. ``reflectivity``: a particle's
    Lambertian-equivalent reflectivity; ``alpha``: the distribution's extinction (1/m)."""
    dist: SizeDistribution
    reflectivity: float
    alpha: float
    levels: np.ndarray
    r: np.ndarray
    d_min: np.ndarray
    count: np.ndarray
    depth: np.ndarray
    count_to_range: np.ndarray
    xi: np.ndarray
    optics: Optics = HDL32E

    def at(self, table: np.ndarray, level: np.ndarray, r: np.ndarray) -> np.ndarray:
        """A (L, g) table at the given levels and ranges (m; clipped to the grid), linearly in range."""
        return lookup(table, level, r, TABLE_STEP)

    def level_of(self, power: np.ndarray) -> np.ndarray:
        """The drawing level (int64, same shape) of rays whose echo, attenuated by the mean
        extinction, is ``power`` (1/m^2): the highest level at most MARGIN times it."""
        ratio = np.maximum(MARGIN * np.asarray(power), self.levels[0]) / self.levels[0]
        return np.minimum((np.log10(ratio) / LEVEL_STEP).astype(np.int64), len(self.levels) - 1)

    def range_of_count(self, level: np.ndarray, c: np.ndarray) -> np.ndarray:
        """The range (m) at which the expected count of ``level`` reaches ``c``."""
        steps = np.maximum(self.count[:, -1], 1e-300) / (self.count_to_range.shape[1] - 1)
        return lookup(self.count_to_range, level, c / steps[level], 1.0)

    def share(self, d_melted_mm: np.ndarray, r: np.ndarray) -> np.ndarray:
        """Share of the beam's cross-section at range r (m) that particles of melted diameter
        ``d_melted_mm`` block (at most 1)."""
        radius = 0.5e-3 * self.dist.optical_diameter(d_melted_mm)
        return np.minimum((radius / (self.optics.tx_radius + self.optics.tx_divergence * r)) ** 2, 1.0)


def lookup(table: np.ndarray, row: np.ndarray, x: np.ndarray, step: float) -> np.ndarray:
    """Rows of ``table`` (L, g), each sampled at 0, step, 2 step, ..., linearly interpolated at
    ``x`` (clipped to its ends): index arithmetic, no search (the particles' ranges are not sorted
    across rays)."""
    g = table.shape[1]
    t = np.minimum(np.maximum(np.asarray(x, np.float64) * (1.0 / step), 0.0), g - 1.0)   # clip, without its overhead
    i = np.minimum(t.astype(np.int64), g - 2)
    flat = table.ravel()
    j = np.asarray(row) * g + i
    return flat[j] + (t - i) * (flat[j + 1] - flat[j])


def _cumulative(y: np.ndarray, step: float) -> np.ndarray:
    """Trapezoid integral of ``y`` along its last axis, uniform grid, from the first point (same shape)."""
    out = np.zeros_like(y)
    out[..., 1:] = np.cumsum(0.5 * (y[..., 1:] + y[..., :-1]), axis=-1) * step
    return out


@functools.lru_cache(maxsize=32)
def particle_field(dist: SizeDistribution, reflectivity: float, min_return: float, max_range: float,
                   optics: Optics = HDL32E) -> ParticleField:
    """The field's tables for a size distribution, the particles' reflectivity, the detection
    threshold (1/m^2) and the sensor's maximum range (m)."""
    r = np.arange(0.0, max_range + TABLE_STEP, TABLE_STEP)
    levels = min_return * 10.0 ** (LEVEL_STEP * np.arange(N_LEVELS))
    a = optics.tx_radius + optics.tx_divergence * r
    xi = overlap(r, optics)
    with np.errstate(divide="ignore", invalid="ignore"):
        d_echo = np.where(xi > 0, 2e3 * a * r * np.sqrt(levels[:, None] / (reflectivity * xi)), np.inf)
    d_opt = np.minimum(d_echo, 2e3 * a * np.sqrt(S_MIN))               # (L, g) mm
    # Melted diameter of that optical diameter (the optical diameter grows with it).
    grid = np.linspace(0.0, dist.d_max, 20001)
    optical = dist.optical_diameter(grid)
    d_min = np.interp(d_opt, optical, grid)                          # d_max where no particle can matter
    n_above = np.where(d_min < dist.d_max, dist.number_density(d_min), 0.0)
    # Geometric cross-section (1/m) of the drawn particles: from the top of the distribution down.
    sigma_n = np.pi / 4 * optical**2 * 1e-6 * dist.density(grid)
    alpha_drawn = np.interp(d_min, grid, _cumulative(sigma_n[::-1], grid[1] - grid[0])[::-1])
    alpha = dist.extinction()
    count = _cumulative(np.pi * a**2 * n_above, TABLE_STEP)
    inverse = np.stack([np.interp(np.linspace(0.0, c[-1], COUNT_TABLE), c, r) for c in count])   # per level
    depth = _cumulative(2 * np.maximum(alpha - alpha_drawn, 0.0), TABLE_STEP)
    return ParticleField(dist, float(reflectivity), alpha, levels, r, d_min, count, depth, inverse, xi, optics)


class Particles(NamedTuple):
    """Particles in a sweep's beams, ordered by ray, then by range: ``ray`` (K,) int64 ray index,
    ``range`` (K,) m along it, ``share`` (K,) of the beam's cross-section each blocks."""
    ray: np.ndarray
    range: np.ndarray
    share: np.ndarray


def draw_particles(field: ParticleField, limit: np.ndarray, level: np.ndarray, rng: np.random.Generator) -> Particles:
    """The particles in each of m beams up to ``limit`` (m,) m (its surface; inf: the field's
    maximum range), at each ray's drawing ``level`` (m,).

    Each beam's particles are a Poisson process in its expected-count coordinate ``c = count(r)``
    (unit rate, c from 0 to count(L)). The beams' intervals laid end to end make one interval,
    on which one unit-rate process is drawn at once: a Poisson total, then that many sorted
    uniform points (the order statistics, from exponential spacings); each point falls in its
    beam's interval at its own c, whose range is ``count^-1(c)``. So every beam gets an
    independent Poisson number of particles, already in order of range. Their diameters come from
    the size distribution above ``d_min`` at their range."""
    mu = field.at(field.count, level, limit)
    edges = np.concatenate([[0.0], np.cumsum(mu)])
    n = int(rng.poisson(edges[-1]))
    c = np.cumsum(rng.exponential(size=n + 1))
    x = c[:n] * (edges[-1] / c[n])
    ray = np.minimum(np.searchsorted(edges, x, side="right") - 1, len(limit) - 1)
    lv = level[ray]
    r = field.range_of_count(lv, x - edges[ray])
    d = field.dist.sample(rng.random(n), field.at(field.d_min, lv, r))
    return Particles(ray, r, field.share(d, r))


class Echoes(NamedTuple):
    """Per ray (m,): the hard (or previously reported) echo attenuated by the particles
    ``p_hard``, the strongest particle echo ``p_particle`` (0 where none) at ``r_particle``,
    whether the particle wins (``p_particle > p_hard``), the reported power and range, and whether
    the ray reports (``power >= min_return``)."""
    p_hard: np.ndarray
    p_particle: np.ndarray
    r_particle: np.ndarray
    from_particle: np.ndarray
    power: np.ndarray
    range: np.ndarray
    kept: np.ndarray


def strongest_returns(p_hard: np.ndarray, r_hard: np.ndarray, depth_hard: np.ndarray, particles: Particles,
                      depth: np.ndarray, xi: np.ndarray, reflectivity: float, min_return: float) -> Echoes:
    """The strongest-return bookkeeping of m rays with particles in them.

    p_hard, r_hard : (m,) each ray's echo before the particles (1/m^2; 0 for none) and its range
    (m; inf for none). depth_hard : (m,) the continuous two-way optical depth at r_hard.
    particles : ordered by ray, then range; depth, xi : (K,) the continuous two-way optical depth
    at each particle and the overlap there. Each particle's share ``s`` passes ``(1 - s)^2`` of
    the beam on to what lies behind it (there and back)."""
    m, K = len(p_hard), len(particles.ray)
    log_pass = 2 * np.log1p(-np.minimum(particles.share, 1 - 1e-12))
    cum = np.concatenate([[0.0], np.cumsum(log_pass)])                 # cum[i]: sum of log_pass[:i]
    counts = np.bincount(particles.ray, minlength=m)
    starts = np.cumsum(counts) - counts
    offset = cum[starts]                                               # per ray: the sum before its first
    shadow = cum[:K] - offset[particles.ray]                           # exclusive, within the ray
    with np.errstate(divide="ignore", invalid="ignore"):             # xi is 0 wherever r is
        p = np.where(xi > 0, reflectivity * particles.share * xi / particles.range**2 * np.exp(shadow - depth), 0.0)
    # The particles in front of each ray's echo shadow it: all of the ray's, unless the echo lies
    # before its last particle (an echo already moved to a particle or the fog); those searched.
    front = starts + counts
    last = np.full(m, -np.inf)
    last[counts > 0] = particles.range[front[counts > 0] - 1]
    inside = np.flatnonzero(r_hard < last)
    if len(inside):
        key = particles.ray * _KEY + particles.range
        front[inside] = np.searchsorted(key, inside * _KEY + r_hard[inside])
    p_h = np.where(p_hard > 0, p_hard * np.exp(cum[front] - offset - depth_hard), 0.0)
    best = np.zeros(m)
    r_best = np.full(m, np.inf)
    if K:
        has = np.flatnonzero(counts)
        best[has] = np.maximum.reduceat(p, starts[has])
        top = np.flatnonzero(p == best[particles.ray])
        first = top[np.concatenate([[True], particles.ray[top][1:] != particles.ray[top][:-1]])]
        r_best[particles.ray[first]] = particles.range[first]
    wins = best > p_h
    power = np.where(wins, best, p_h)
    return Echoes(p_h, best, r_best, wins, power, np.where(wins, r_best, r_hard), power >= min_return)
