"""Rain on the LIDAR_TOP: discrete drops in the beams, and the wet road.

Drops, not a soft target. The fog's soft-target echo (degrade.py) is the limit of very many
particles in the pulse's volume, none of them dominant: fog has some 1e8 droplets per m^3. A
lidar beam is a few centimetres wide, and rain holds a few thousand drops per m^3 whose echo
grows as D^2: at 10 mm/h the beam's pulse volume at 5 m (3 m of range, 5.6e-4 m^2) holds about 5
drops and less than one of the millimetre drops that carry its backscatter, so the echo is one
drop's or none, as for snowflakes. Rain therefore uses the discrete particles of
:mod:`simgen.weather.lidar_particles` with Marshall-Palmer drops (:mod:`simgen.weather.particles`).

A drop's echo. In lidar.py's units a particle of geometric cross-section pi a^2 that scatters
``dsigma/dOmega`` (m^2/sr) back to the receiver echoes as a Lambertian disc of reflectivity
``rho_p = (dsigma/dOmega) / a^2``. Geometric optics of a water sphere (van de Hulst 1957, ch. 12)
near exact backscatter has two terms: the front face's mirror, ``a^2 R / 4`` with the Fresnel
reflectance R = ((n - 1) / (n + 1))^2 = 0.020 at normal incidence; and the axial ray reflected
once inside, which leaves at ``|2 - 4 / n| b / a`` from the backward direction for an impact
parameter b, so it returns ``a^2 (1 - R)^2 R / (2 - 4 / n)^2`` = 0.019 a^2 (the drop focuses it
almost like a mirror: 2 - 4 / 1.328 = -1.01). Together rho_p = 0.024, i.e. a lidar ratio of 266 sr
(``2 pi / rho_p``). The glory that makes small cloud droplets backscatter 14 times more (18.8 sr,
O'Connor et al. 2004) is a lobe of angular width about 1 / x (0.3 mrad for a 1 mm drop at 905 nm);
the HDL-32E's receiver sits beside its laser (30 mm), 3-10 mrad off the backward direction for a
drop at 3-10 m, so it sees the geometric terms only.

The wet road. A water film on the pavement (lidarseg driveable surface, sidewalk, other flat)
changes its echo by

    g(theta) = (1 - R_F(theta))^2 / (n^2 (1 - rho r_int))

the light enters and leaves through the film's flat surface (Fresnel transmission 1 - R_F at the
incidence theta, the rest mirrored away from the sensor: the specular part), the radiance leaving
the water is 1/n^2 of the radiance inside (n = 1.328), and the light the pavement scatters back
into the water is partly reflected down again at the surface (r_int = 1 - (1 - <R_F>) / n^2 of
it, <R_F> the cosine-weighted hemispherical mean) and re-scattered, which is why wet things look
darker (Lekner and Dorf 1988). On asphalt (rho 0.12) g = 0.58 at normal incidence; on the road
seen from the HDL-32E's 1.84 m, 0.47 at 5 m (68 deg from the normal), 0.27 at 10 m, 0.11 at 20 m
and 0.05 at 35 m: the wet road's far returns fall below the threshold.

References: H. C. van de Hulst, Light Scattering by Small Particles, Wiley 1957. E. J. O'Connor,
A. J. Illingworth, R. J. Hogan, "A technique for autocalibration of cloud lidar", J. Atmos.
Oceanic Technol. 21, 2004. J. Lekner, M. C. Dorf, "Why some things are
darker when wet", Appl. Opt. 27, 1988. G. M. Hale, M. R. Querry, "Optical constants of water in
the 200-nm to 200-um wavelength region", Appl. Opt. 12, 1973 (n = 1.328 at 905 nm).
"""
from __future__ import annotations

import functools

import numpy as np

from .. import lidarseg
from ..config import LidarConfig
from . import particles
from .lidar_particles import ParticleField, particle_field
from .lidar_sweep import LABEL_COLUMN, SweepRays, apply_particles

WATER_INDEX = 1.328                # liquid water at 905 nm (Hale and Querry 1973)


def drop_reflectivity(n: float = WATER_INDEX) -> float:
    """Lambertian-equivalent reflectivity of a large water drop seen near exact backscatter: the
    front face's mirror R / 4 and the once-reflected axial ray (1 - R)^2 R / (2 - 4 / n)^2, R the
    normal-incidence Fresnel reflectance (module docstring)."""
    r = ((n - 1) / (n + 1)) ** 2
    return r / 4 + (1 - r) ** 2 * r / (2 - 4 / n) ** 2


DROP_REFLECTIVITY = drop_reflectivity()
WET_SURFACES = (lidarseg.ROAD, lidarseg.SIDEWALK, lidarseg.PLAZA)


def fresnel_reflectance(cos_i: np.ndarray, n: float = WATER_INDEX) -> np.ndarray:
    """Unpolarised Fresnel reflectance of light arriving from air at a flat surface of index n,
    at incidence with cosine ``cos_i``: the mean of the s and p reflectances."""
    c = np.clip(np.asarray(cos_i, np.float64), 0.0, 1.0)
    ct = np.sqrt(1.0 - (1.0 - c**2) / n**2)
    rs = ((c - n * ct) / (c + n * ct)) ** 2
    rp = ((n * c - ct) / (n * c + ct)) ** 2
    return 0.5 * (rs + rp)


@functools.lru_cache(maxsize=1)
def internal_reflectance(n: float = WATER_INDEX) -> float:
    """Share of Lambertian light inside the film that the water-air surface sends back down:
    ``1 - (1 - <R_F>) / n^2``, <R_F> the cosine-weighted mean external reflectance (Lekner and Dorf)."""
    theta = np.linspace(0.0, np.pi / 2, 20001)
    w = 2 * np.sin(theta) * np.cos(theta)
    mean = np.sum(0.5 * (fresnel_reflectance(np.cos(theta[1:]), n) * w[1:] + fresnel_reflectance(np.cos(theta[:-1]), n)
                         * w[:-1])) * (theta[1] - theta[0])
    return float(1.0 - (1.0 - mean) / n**2)


def wet_road_gain(cos_inc: np.ndarray, rho: np.ndarray, n: float = WATER_INDEX) -> np.ndarray:
    """The factor (same shape) by which a water film changes the echo of a pavement of reflectivity
    ``rho`` seen at incidence cosine ``cos_inc`` (module docstring)."""
    t = 1.0 - fresnel_reflectance(cos_inc, n)
    return t**2 / (n**2 * (1.0 - np.asarray(rho) * internal_reflectance(n)))


def rain_field(rate_mm_h: float, lidar: LidarConfig) -> ParticleField:
    """The drops the sweep's beams meet in rain of ``rate_mm_h`` (cached per rate and sensor)."""
    return particle_field(particles.rain_distribution(float(rate_mm_h)), DROP_REFLECTIVITY, lidar.min_return,
                          lidar.max_range)


def rain_sweep(points: np.ndarray, rays: SweepRays, rate_mm_h: float, lidar: LidarConfig,
               rng: np.random.Generator) -> tuple[np.ndarray, SweepRays]:
    """Rain of ``rate_mm_h`` on a sweep's points (n, >=7; see :func:`lidar_particles.sweep_rays`):
    the wet road's echoes changed, every echo attenuated by the drops, the drops' own echoes where
    stronger. Rate 0 returns the points unchanged (the same array)."""
    if rate_mm_h <= 0:
        return points, rays
    wet = np.isin(points[:, LABEL_COLUMN].astype(np.int64), WET_SURFACES)
    ray = rays.row_ray
    gain = np.where(wet, wet_road_gain(rays.cos_inc[ray], rays.rho[ray]), 1.0)
    return apply_particles(points, rays, rain_field(rate_mm_h, lidar), gain, lidar.min_return,
                           lidar.intensity_ref_range, rng)
