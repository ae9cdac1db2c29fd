"""Snowfall in a camera image (derivations: docs/weather.md): the snowfall's extinction, then the
flakes near the lens.

1. Extinction: Koschmieder's law with the snowfall's extinction coefficient (simgen.weather.
   particles.snow_extinction, from the flakes' own cross-sections: 4.2e-3 /m at 1 mm/h of water,
   a visibility of 0.7 km) and the overcast airlight (simgen.weather.veil).
2. Flakes (simgen.weather.streaks): Gunn-Marshall flakes within the camera's near volume whose
   image is at least a pixel wide (a flake's diameter from its melted one with Brandes et al.'s
   density), each swept over the exposure at its fall speed (about 1 m/s: Locatelli and Hobbs
   1974) less the camera's own velocity: mostly soft discs, short streaks near the lens or from a
   moving car; out of focus near the lens; occluded by the scene. A flake is an opaque white
   diffuser: seen from the side, a Lambertian sphere of albedo rho lit by the sky above (A) and
   the scene below (G) has the mean radiance ``rho (A + G) / 2`` (the hemispheres' irradiances
   ``pi A (1 + n_z) / 2`` and ``pi G (1 - n_z) / 2`` at a surface of normal n, averaged over the
   visible disc, where n_z averages to 0). rho = 0.9, fresh snow's visible albedo. Against the
   sky a flake is grey, against the road or a car white.

References: as in simgen.weather.streaks; S. G. Warren, W. J. Wiscombe, "A model for the spectral
albedo of snow", J. Atmos. Sci. 37, 1980 (fresh snow reflects 0.9 and more of visible light).
"""
from __future__ import annotations

import numpy as np

from ..camera import CAMERA_ZNEAR, depth_to_range
from .particles import snow_distribution, snow_extinction
from .streaks import DAY_OPTICS, CameraOptics, coverage, project, sample_particles
from .veil import CLEAR_SKY_RGB, compose, environment_radiance, overcast_airlight, transmittance

SNOW_ALBEDO = 0.9


def snow_veil(rgb: np.ndarray, range_m: np.ndarray, rate_mm_h: float, airlight: np.ndarray) -> np.ndarray:
    """Koschmieder's law with the snowfall's extinction: rgb (H, W, 3) uint8, range_m (H, W) metres
    along each pixel's ray (0: the sky). ``round(J t + A (1 - t))``, ``t = exp(-alpha d)``."""
    if rate_mm_h <= 0:
        return rgb
    return compose(rgb, transmittance(range_m, snow_extinction(rate_mm_h)), airlight)


def snow_image(rgb: np.ndarray, depth: np.ndarray, K: np.ndarray, rate_mm_h: float, rng: np.random.Generator,
               down_cam: np.ndarray, v_cam: np.ndarray, sky_rgb=CLEAR_SKY_RGB,
               optics: CameraOptics = DAY_OPTICS) -> np.ndarray:
    """The camera image in snowfall of ``rate_mm_h`` of water (module docstring), composed in one
    pass (simgen.weather.veil.compose); rate 0 returns ``rgb`` itself.

    rgb : (H, W, 3) uint8.  depth : (H, W) float32 camera z (m), 0 for the sky.  K : (3, 3).
    rng : the camera's snow stream (the flakes).  down_cam : (3,) unit gravity, camera frame.
    v_cam : (3,) the camera's velocity, camera frame (m/s).  sky_rgb : (3,) the rendered sky.
    """
    if rate_mm_h <= 0:
        return rgb
    H, W = depth.shape
    airlight = overcast_airlight(sky_rgb)
    t = transmittance(depth_to_range(depth, K), snow_extinction(rate_mm_h))
    flakes = sample_particles(snow_distribution(rate_mm_h), K, (W, H), optics, down_cam, v_cam, rng, CAMERA_ZNEAR)
    cover = coverage(project(flakes, K, (W, H), optics, CAMERA_ZNEAR), (W, H), depth)
    return compose(rgb, t, airlight, cover, SNOW_ALBEDO * environment_radiance(rgb, t, K, airlight))
