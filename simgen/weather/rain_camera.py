"""Rain in a camera image (derivations: docs/weather.md): a wet road, the rain's extinction, and
the streaks of the drops near the lens, composed in that order in one pass
(simgen.weather.veil.compose: the road's light crosses the rain to the camera; the near drops
are in front of everything).

1. Wet road (simgen.weather.wet_road): the paved ground darkens and mirrors, where the renderer
   tells which pixels are paved.
2. Extinction: Koschmieder's law on each pixel's range with the rain's extinction coefficient
   (simgen.weather.particles.rain_extinction: 2.6e-3 /m at 25 mm/h, a visibility of 1.2 km) and
   the overcast airlight (simgen.weather.veil); the sky turns overcast.
3. Streaks (simgen.weather.streaks): Marshall-Palmer drops within the camera's near volume whose
   image is at least a pixel wide, each swept over the exposure at its fall speed (Atlas et al.
   1973) less the camera's own velocity, occluded by the scene, with the radiance of their
   environment (Garg and Nayar 2004, 2007): against the bright sky a streak is darker, against a
   dark car brighter, as in rain video.
"""
from __future__ import annotations

import numpy as np

from .. import lidarseg
from ..camera import CAMERA_ZNEAR, depth_to_range
from .particles import rain_distribution, rain_extinction
from .streaks import DAY_OPTICS, CameraOptics, coverage, project, sample_particles
from .veil import CLEAR_SKY_RGB, compose, environment_radiance, overcast_airlight, transmittance
from .wet_road import wet_ground

PAVED = (lidarseg.ROAD, lidarseg.SIDEWALK, lidarseg.PLAZA)   # the ground a film of water covers


def rain_veil(rgb: np.ndarray, range_m: np.ndarray, rate_mm_h: float, airlight: np.ndarray) -> np.ndarray:
    """Koschmieder's law with the rain's extinction: rgb (H, W, 3) uint8, range_m (H, W) metres
    along each pixel's ray (0: the sky). ``round(J t + A (1 - t))``, ``t = exp(-alpha d)``."""
    if rate_mm_h <= 0:
        return rgb
    return compose(rgb, transmittance(range_m, rain_extinction(rate_mm_h)), airlight)


def rain_image(rgb: np.ndarray, depth: np.ndarray, K: np.ndarray, rate_mm_h: float, rng: np.random.Generator,
               down_cam: np.ndarray, v_cam: np.ndarray, paved: np.ndarray | None = None,
               sky_rgb=CLEAR_SKY_RGB, optics: CameraOptics = DAY_OPTICS) -> np.ndarray:
    """The camera image in rain of ``rate_mm_h`` (module docstring); rate 0 returns ``rgb`` itself.

    rgb : (H, W, 3) uint8 clean render.  depth : (H, W) float32 camera z (m), 0 for the sky.
    K : (3, 3) intrinsics.  rng : the camera's rain stream (the drops).
    down_cam : (3,) unit gravity, camera frame.  v_cam : (3,) the camera's velocity, camera frame (m/s).
    paved : (H, W) bool, the paved ground the rain wets (None: no wet road).
    sky_rgb : (3,) the rendered sky's colour, whose luminance the overcast airlight takes.
    """
    if rate_mm_h <= 0:
        return rgb
    H, W = depth.shape
    airlight = overcast_airlight(sky_rgb)
    ground = None if paved is None else wet_ground(rgb, depth, paved, K, -np.asarray(down_cam, np.float64), airlight)
    t = transmittance(depth_to_range(depth, K), rain_extinction(rate_mm_h))
    drops = sample_particles(rain_distribution(rate_mm_h), K, (W, H), optics, down_cam, v_cam, rng, CAMERA_ZNEAR)
    cover = coverage(project(drops, K, (W, H), optics, CAMERA_ZNEAR), (W, H), depth)
    return compose(rgb, t, airlight, cover, environment_radiance(rgb, t, K, airlight), ground)


def paved_pixels(face: np.ndarray, face_class: np.ndarray) -> np.ndarray:
    """(H, W) bool: the pixels of the paved ground (road with its markings, sidewalks, paved lots),
    which the rain wets, from the id pass's face indices ``face`` (H, W) and the lidarseg class of
    each face ``face_class`` (F,) (simgen.labels.face_classes)."""
    return np.take(np.isin(face_class, PAVED), face)
