"""Rain in a camera image (derivations: docs/weather.md): a wet road, the rain's extinction, and
the streaks of the drops near the lens, in that order (the road's light crosses the rain to the
camera; the near drops are in front of everything).

1. Wet road (simgen.weather.wet_road): the paved ground darkens and mirrors, where the renderer
   tells which pixels are paved.
2. Extinction: Koschmieder's law on each pixel's range with the rain's extinction coefficient
   (simgen.weather.particles.rain_extinction: 2.6e-3 /m at 25 mm/h, a visibility of 1.2 km), the
   same law and OpenCV blend as the fog (simgen.degrade.fog_image). Its airlight is the horizon
   sky's radiance: under rain the sky is overcast, and clouds scatter every wavelength alike, so
   it is grey; at the camera's exposure it has the luminance (Rec. 709 weights) of the renderer's
   sky, 184 by day. The sky's pixels take it, so the sky turns overcast.
3. Streaks (simgen.weather.streaks): Marshall-Palmer drops within the camera's near volume whose
   image is at least a pixel wide, each swept over the exposure at its fall speed (Atlas et al.
   1973) less the camera's own velocity, occluded by the scene. A drop refracts light from a field
   of view of about 165 degrees behind it, so its radiance is a weighted mean of its whole
   environment and hardly depends on the background it crosses (Garg and Nayar 2004, 2007): here
   the mean of the two halves of that field, the sky above the horizon (the airlight) and the
   scene below it (the image's mean below the principal point's row, the horizon of a level
   camera), ``E = (A + G) / 2``. Against the bright sky a streak is darker, against a dark car
   brighter, as in rain video.

References: as in simgen.weather.streaks and simgen.weather.wet_road; H. Koschmieder, "Theorie der
horizontalen Sichtweite", Beitr. Phys. freien Atm. 12, 1924.
"""
from __future__ import annotations

import numpy as np

from .. import lidarseg
from ..camera import CAMERA_ZNEAR, SKY, depth_to_range
from ..degrade import fog_image
from .particles import rain_distribution, rain_extinction
from .streaks import DAY_OPTICS, CameraOptics, blend, coverage, project, sample_particles
from .wet_road import wet_road

CLEAR_SKY_RGB = tuple(int(255 * c) for c in SKY)    # the renderer's sky by day, as it draws it
REC709 = np.array([0.2126, 0.7152, 0.0722])
PAVED = (lidarseg.ROAD, lidarseg.SIDEWALK, lidarseg.PLAZA)   # the ground a film of water covers


def overcast_airlight(sky_rgb) -> np.ndarray:
    """(3,) float64: the grey with the Rec. 709 luminance of the rendered sky ``sky_rgb`` (3,)."""
    return np.full(3, float(REC709 @ np.asarray(sky_rgb, np.float64)))


def environment_radiance(rgb: np.ndarray, K: np.ndarray, airlight: np.ndarray) -> np.ndarray:
    """(3,) mean radiance around a particle, ``(A + G) / 2``: the sky's half ``A`` (the airlight)
    and the scene's ``G``, the mean of rgb (H, W, 3) below the principal point's row (every 4th
    pixel: a mean needs no more)."""
    below = rgb[int(min(max(K[1, 2], 0), rgb.shape[0] - 1)):][::4, ::4]
    return (np.asarray(airlight, np.float64) + below.reshape(-1, 3).mean(axis=0)) / 2


def rain_veil(rgb: np.ndarray, range_m: np.ndarray, rate_mm_h: float, airlight: np.ndarray) -> np.ndarray:
    """Koschmieder's law with the rain's extinction: rgb (H, W, 3) uint8, range_m (H, W) metres
    along each pixel's ray (0: the sky). ``round(J t + A (1 - t))``, ``t = exp(-alpha d)``."""
    if rate_mm_h <= 0:
        return rgb
    return fog_image(rgb, range_m, rain_extinction(rate_mm_h), airlight)


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
    if paved is not None:
        rgb = wet_road(rgb, depth, paved, K, -np.asarray(down_cam, np.float64), airlight)
    rgb = rain_veil(rgb, depth_to_range(depth, K), rate_mm_h, airlight)
    drops = sample_particles(rain_distribution(rate_mm_h), K, (W, H), optics, down_cam, v_cam, rng, CAMERA_ZNEAR)
    cover = coverage(project(drops, K, (W, H), optics, CAMERA_ZNEAR), (W, H), depth)
    return blend(rgb, cover, environment_radiance(rgb, K, airlight))


def paved_pixels(face: np.ndarray, face_class: np.ndarray) -> np.ndarray:
    """(H, W) bool: the pixels of the paved ground (road with its markings, sidewalks, paved lots),
    which the rain wets, from the id pass's face indices ``face`` (H, W) and the lidarseg class of
    each face ``face_class`` (F,) (simgen.labels.face_classes)."""
    return np.take(np.isin(face_class, PAVED), face)


def sky_colour(rgb: np.ndarray, depth: np.ndarray, fallback=CLEAR_SKY_RGB) -> np.ndarray:
    """(3,) the rendered sky's colour: the mean of rgb (H, W, 3) where ``depth`` (H, W) is 0 (every
    4th pixel), ``fallback`` where no sky is in view."""
    sky = rgb[::4, ::4][depth[::4, ::4] <= 0]
    return sky.mean(axis=0) if len(sky) else np.asarray(fallback, np.float64)
