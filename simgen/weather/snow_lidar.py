"""Snowfall on the LIDAR_TOP: discrete flakes in the beams, in the manner of Hahner et al.
("LiDAR Snowfall Simulation for Robust 3D Object Detection", CVPR 2022), derived from the paper's
description: for each ray the flakes inside the beam's cone up to the surface it hit (or the
sensor's range), each blocking a share of the beam's cross-section at its range; each flake's echo
and the attenuated surface's by the lidar equation; the strongest reported if it reaches the
threshold (:mod:`simgen.weather.lidar_particles`). So clutter appears near the sensor and far
returns are lost.

Flakes: Gunn and Marshall's size distribution closed on the water-equivalent rate, each flake's
diameter from its mass with the density of Brandes et al. (2007) (:mod:`simgen.weather.particles`).
A flake's Lambertian-equivalent reflectivity is ``2 pi / S`` with the lidar ratio S = 29 sr
measured on ice crystals of cirrus (Chen, Chiang and Nee 2002, mean 29 +- 12 sr at 532 nm; ice
absorbs little more at 905 nm), i.e. 0.217. The road is left as it is (a snow-covered road is
another scene).

References: M. Hahner, C. Sakaridis, M. Bijelic, F. Heide, F. Yu, D. Dai, L. Van Gool, "LiDAR
Snowfall Simulation for Robust 3D Object Detection", CVPR 2022. W.-N. Chen, C.-W. Chiang,
J.-B. Nee, "Lidar ratio and depolarization ratio for cirrus clouds", Appl. Opt. 41, 2002.
"""
from __future__ import annotations

import numpy as np

from ..config import LidarConfig
from . import particles
from .lidar_particles import ParticleField, particle_field
from .lidar_sweep import SweepRays, apply_particles

LIDAR_RATIO_ICE = 29.0            # sr
FLAKE_REFLECTIVITY = 2 * np.pi / LIDAR_RATIO_ICE


def snow_field(rate_mm_h: float, lidar: LidarConfig) -> ParticleField:
    """The flakes the sweep's beams meet in snowfall of ``rate_mm_h`` water equivalent (cached)."""
    return particle_field(particles.snow_distribution(float(rate_mm_h)), FLAKE_REFLECTIVITY, lidar.min_return,
                          lidar.max_range)


def snow_sweep(points: np.ndarray, rays: SweepRays, rate_mm_h: float, lidar: LidarConfig,
               rng: np.random.Generator) -> tuple[np.ndarray, SweepRays]:
    """Snowfall of ``rate_mm_h`` on a sweep's points (n, >=7; see :func:`lidar_particles.sweep_rays`).
    Rate 0 returns the points unchanged (the same array)."""
    if rate_mm_h <= 0:
        return points, rays
    return apply_particles(points, rays, snow_field(rate_mm_h, lidar), np.ones(len(points)), lidar.min_return,
                           lidar.intensity_ref_range, rng)
