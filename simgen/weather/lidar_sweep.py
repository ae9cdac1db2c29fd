"""A sweep's rays through the weather: which ray each row of the points is, what it still
reports, and one precipitation applied to the points (:mod:`simgen.weather.lidar_particles`).

The points are those ``simgen.sensor_effects.degrade_sweep`` carries: x, y, z, intensity, ring (the
sweep's columns), then the lidarseg label (LABEL_COLUMN) and the index of the row's ray
(RAY_COLUMN). The rays are the sweep's n0 returns, then its k missed rays (``Sweep.miss_*``): a
particle can echo in a ray that met nothing.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .. import lidarseg
from ..degrade import fog_returns
from .lidar_particles import TABLE_STEP, Echoes, ParticleField, Particles, draw_particles, lookup, strongest_returns

LABEL_COLUMN, RAY_COLUMN = 5, 6


@dataclass
class SweepRays:
    """The m rays of one sweep and what each still reports.

    origin, direction : (m, 3) sensor frame at the sweep's end; ring : (m,); limit : (m,) distance
    (m) to the surface the ray met (inf for none); rho, cos_inc : (m,) that surface's reflectivity
    and cos(incidence) (0 for none); extra_alpha : the extinction (1/m) of what degraded the sweep
    before (fog, rain), which the next particles' echoes also cross. Per row of the points:
    row_ray (n,) its ray, row_power (n,) its echo (1/m^2), row_range (n,) m along the ray."""
    origin: np.ndarray
    direction: np.ndarray
    ring: np.ndarray
    limit: np.ndarray
    rho: np.ndarray
    cos_inc: np.ndarray
    extra_alpha: float
    row_ray: np.ndarray
    row_power: np.ndarray
    row_range: np.ndarray


def with_ray_column(points: np.ndarray) -> np.ndarray:
    """A sweep's points (n, C) with each row's ray index appended as a float32 column (exact to 2^24)."""
    return np.concatenate([points, np.arange(len(points), dtype=np.float32)[:, None]], axis=1)


def sweep_rays(points: np.ndarray, sweep, min_return: float, fog_alpha: float) -> SweepRays:
    """The rays of ``sweep`` (a :class:`simgen.lidar.Sweep`) and the rows of ``points`` (n, >=7),
    whose column RAY_COLUMN holds each row's ray (the index of its clean return). After fog
    ``fog_alpha`` (1/m) a row's echo is the fog's attenuated hard return or the fog's own echo
    (:func:`simgen.degrade.fog_returns` says which); its range is where the row lies on its ray."""
    if sweep.miss_dir is None:
        raise ValueError("rain and snow need the sweep's missed rays: LidarScanner.scan(..., missed_rays=True)")
    origin = np.concatenate([sweep.points_lidar[:, :3] - sweep.dir_lidar * sweep.range[:, None], sweep.miss_origin])
    direction = np.concatenate([sweep.dir_lidar, sweep.miss_dir])
    rho_cos = sweep.rho * sweep.cos_inc
    power = rho_cos / sweep.range**2
    if fog_alpha > 0:
        f = fog_returns(rho_cos, sweep.range, fog_alpha, min_return)
        power = np.where(f.fog_wins, f.p_soft, f.p_hard)
    ray = points[:, RAY_COLUMN].astype(np.int64)
    limit = np.concatenate([sweep.range, sweep.miss_range])
    row_range = limit[ray]
    if fog_alpha > 0:                                   # the fog moved some rows along their rays
        row_range = np.einsum("nd,nd->n", points[:, :3] - origin[ray], direction[ray])
    none = np.zeros(len(sweep.miss_range))
    return SweepRays(origin, direction, np.concatenate([sweep.points_lidar[:, 4], sweep.miss_ring]).astype(np.int64),
                     limit, np.concatenate([sweep.rho, none]), np.concatenate([sweep.cos_inc, none]), float(fog_alpha),
                     ray, power[ray], np.minimum(row_range, limit[ray]))


def intensity(power: np.ndarray, ref_range: float) -> np.ndarray:
    """lidar.py's intensity scale: ``round(255 clip(p ref_range^2, 0, 1))``."""
    return np.round(255.0 * np.clip(power * ref_range**2, 0.0, 1.0))


def precipitation_echoes(rays: SweepRays, field: ParticleField, row_gain: np.ndarray, min_return: float,
                         rng: np.random.Generator) -> tuple[Particles, Echoes]:
    """The particles drawn in every ray and the strongest-return bookkeeping of each ray (m,): its
    rows' echoes times ``row_gain`` (n,) (the surface's own change, e.g. a wet road), attenuated
    by the particles' field, against the particles' echoes."""
    m = len(rays.limit)
    p_hard, r_hard = np.zeros(m), np.full(m, np.inf)
    p_hard[rays.row_ray] = rays.row_power * row_gain
    r_hard[rays.row_ray] = rays.row_range
    r_table = np.minimum(r_hard, field.r[-1])
    level = field.level_of(p_hard * np.exp(-2 * field.alpha * r_table))
    particles = draw_particles(field, rays.limit, level, rng)
    extra = 2 * rays.extra_alpha
    depth = field.at(field.depth, level[particles.ray], particles.range) + extra * particles.range
    depth_hard = field.at(field.depth, level, r_hard) + extra * r_table
    xi = lookup(field.xi[None], 0, particles.range, TABLE_STEP)
    return particles, strongest_returns(p_hard, r_hard, depth_hard, particles, depth, xi, field.reflectivity, min_return)


def echo_points(points: np.ndarray, rays: SweepRays, e: Echoes, alpha: float,
                ref_range: float) -> tuple[np.ndarray, SweepRays]:
    """The points (float32) the rays report after a precipitation of extinction ``alpha`` (1/m)
    whose bookkeeping is ``e``: a row whose ray still reports its echo keeps its position and
    label with the attenuated intensity; one won by a particle moves along its ray to the
    particle and is labelled noise; one whose ray reports nothing is dropped; a ray that had no
    row and now reports a particle adds one at the end (in ray order). Also the updated rays."""
    m = len(rays.limit)
    has_row = np.zeros(m, bool)
    has_row[rays.row_ray] = True
    new = np.flatnonzero(e.kept & ~has_row)
    kept_rows = e.kept[rays.row_ray]
    ray = np.concatenate([rays.row_ray[kept_rows], new])
    out = np.zeros((len(ray), points.shape[1]), np.float32)
    out[: int(kept_rows.sum())] = points[kept_rows]
    out[len(ray) - len(new):, 4] = rays.ring[new]
    out[len(ray) - len(new):, RAY_COLUMN] = new
    moved = np.flatnonzero(e.from_particle[ray])
    out[moved, :3] = rays.origin[ray[moved]] + rays.direction[ray[moved]] * e.range[ray[moved], None]
    out[moved, LABEL_COLUMN] = lidarseg.NOISE
    out[:, 3] = intensity(e.power[ray], ref_range)
    return out, SweepRays(rays.origin, rays.direction, rays.ring, rays.limit, rays.rho, rays.cos_inc,
                          rays.extra_alpha + alpha, ray, e.power[ray], e.range[ray])


def apply_particles(points: np.ndarray, rays: SweepRays, field: ParticleField, row_gain: np.ndarray, min_return: float,
                    ref_range: float, rng: np.random.Generator) -> tuple[np.ndarray, SweepRays]:
    """One precipitation on the points (n, >=7) of a sweep (:func:`precipitation_echoes`, then
    :func:`echo_points`). Returns the points (float32) and the updated rays."""
    _, e = precipitation_echoes(rays, field, row_gain, min_return, rng)
    return echo_points(points, rays, e, field.alpha, ref_range)
