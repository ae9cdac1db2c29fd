"""The per-pixel side of rain and snowfall in a camera image (derivations: docs/weather.md): the
overcast airlight, the radiance around a particle, and one compiled pass that composes the wet
ground, Koschmieder's veil and the particles' coverage.

- Airlight. Koschmieder's A is the horizon sky's radiance. Under rain or snowfall the sky is
  overcast, and clouds scatter every wavelength alike, so A is grey; at the camera's exposure it
  has the luminance (Rec. 709 weights) of the rendered sky (184 by day). The sky's pixels take it.
- Environment. A raindrop refracts light from a field of view of about 165 degrees behind it, so
  its radiance is a mean of its whole environment and hardly depends on the background it crosses
  (Garg and Nayar 2004, 2007); a snowflake, a white diffuser, sees the same two halves: the sky
  above the horizon (A) and the scene below it (G, the veiled image's mean below the principal
  point's row, the horizon of a level camera). Their mean ``(A + G) / 2`` is the drop's radiance
  and, times the flake's albedo, the flake's (simgen.weather.snow_camera).
- Composition, per pixel and channel, in this order (the ground's light crosses the air to the
  camera; the near particles are in front of everything): a wet pixel becomes
  ``dark[I] (1 - R) + M R`` (simgen.weather.wet_road), the veil ``J t + A (1 - t)`` with
  ``t = exp(-alpha d)`` on the pixel's range d (0 for the sky), the particles
  ``(1 - c) J + c E`` with their coverage c (simgen.weather.streaks), rounded once. The veil is
  simgen.degrade.fog_image's law; fused with the other two, one pass over the image replaces three
  (fog_image's OpenCV blend alone took 6.6 ms of CPU per 1600x900 image).

References: H. Koschmieder, "Theorie der horizontalen Sichtweite", Beitr. Phys. freien Atm. 12,
1924; K. Garg, S. K. Nayar, "Vision and rain", IJCV 75, 2007.
"""
from __future__ import annotations

from typing import NamedTuple

import numba
import numpy as np

from ..camera import SKY

CLEAR_SKY_RGB = tuple(int(255 * c) for c in SKY)    # the renderer's sky by day, as it draws it
REC709 = np.array([0.2126, 0.7152, 0.0722])
_NONE_2D = np.zeros((0, 0), np.float32)
_NONE_3D = np.zeros((0, 0, 3), np.float32)


def overcast_airlight(sky_rgb) -> np.ndarray:
    """(3,) float64: the grey with the Rec. 709 luminance of the rendered sky ``sky_rgb`` (3,)."""
    return np.full(3, float(REC709 @ np.asarray(sky_rgb, np.float64)))


def rendered_sky(night: bool) -> np.ndarray:
    """(3,) the colour the renderer gives the sky: camera.SKY by day; at night the night sky's
    luminance through the night exposure (simgen.weather.night, night_sensor)."""
    if not night:
        return np.asarray(CLEAR_SKY_RGB, np.float64)
    from . import night as night_model, night_sensor
    luminance = np.asarray(night_model.SKY_LUMINANCE * night_model.WARM_WHITE, np.float32)[None, None]
    return night_sensor.clean_image(luminance)[0, 0].astype(np.float64)


def sky_colour(rgb: np.ndarray, depth: np.ndarray, fallback=CLEAR_SKY_RGB) -> np.ndarray:
    """(3,) the rendered sky's colour: the mean of rgb (H, W, 3) where ``depth`` (H, W) is 0 (every
    4th pixel), ``fallback`` (:func:`rendered_sky`) where no sky is in view."""
    sky = rgb[::4, ::4][depth[::4, ::4] <= 0]
    return sky.mean(axis=0) if len(sky) else np.asarray(fallback, np.float64)


def transmittance(range_m: np.ndarray, alpha: float) -> np.ndarray:
    """(H, W) float32 ``exp(-alpha d)`` of each pixel's range ``range_m`` (m), 0 for the sky (0)."""
    t = np.exp(np.float32(-alpha) * range_m.astype(np.float32, copy=False))
    t[range_m <= 0] = 0.0
    return t


def environment_radiance(rgb: np.ndarray, t: np.ndarray, K: np.ndarray, airlight: np.ndarray) -> np.ndarray:
    """(3,) ``(A + G) / 2``: A the airlight, G the mean of the veiled image ``rgb t + A (1 - t)``
    below the principal point's row (every 4th pixel: a mean needs no more). rgb (H, W, 3),
    t (H, W) the veil's transmittance."""
    row = int(min(max(K[1, 2], 0), rgb.shape[0] - 1))
    J = rgb[row::4, ::4].reshape(-1, 3).astype(np.float64)
    tt = t[row::4, ::4].reshape(-1, 1).astype(np.float64)
    A = np.asarray(airlight, np.float64)
    return (A + (J * tt + A * (1 - tt)).mean(axis=0)) / 2


class WetGround(NamedTuple):
    """The wet ground of one image (simgen.weather.wet_road): ``wet`` (H, W) bool, the mirror's
    reflectance ``R`` (H, W) float32, the diffuse part per dry level ``dark`` (256,) float32 and
    the mirrored radiance ``mirror`` (H, W, 3) float32."""
    wet: np.ndarray
    R: np.ndarray
    dark: np.ndarray
    mirror: np.ndarray


def compose(rgb: np.ndarray, t: np.ndarray, airlight: np.ndarray, cover: np.ndarray | None = None,
            radiance: np.ndarray | None = None, ground: WetGround | None = None) -> np.ndarray:
    """(H, W, 3) uint8: each pixel of rgb (H, W, 3) uint8 wet where ``ground`` says so, veiled
    with transmittance t (H, W) toward ``airlight`` (3,), then blended toward the particles'
    ``radiance`` (3,) by their coverage ``cover`` (H, W) (clipped to 1), rounded once."""
    H, W = t.shape
    out = np.empty_like(rgb)
    no_cover = cover is None
    _compose(rgb, np.ascontiguousarray(t, np.float32), np.asarray(airlight, np.float64),
             _NONE_2D if no_cover else np.ascontiguousarray(cover, np.float32),
             np.zeros(3) if no_cover else np.asarray(radiance, np.float64),
             np.zeros((0, 0), np.bool_) if ground is None else np.ascontiguousarray(ground.wet, np.bool_),
             _NONE_2D if ground is None else ground.R, np.zeros(256, np.float32) if ground is None else ground.dark,
             _NONE_3D if ground is None else ground.mirror, out)
    return out


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _compose(rgb, t, airlight, cover, radiance, wet, R, dark, mirror, out):
    """The pass of :func:`compose` (module docstring); empty ``cover`` or ``wet`` arrays mean none.
    float32 arithmetic (every term is non-negative, so adding 0.5 and truncating rounds).
    Compiled: one sequential loop (the same inputs give the same bytes)."""
    H, W = t.shape
    has_cover = cover.shape[0] == H
    has_wet = wet.shape[0] == H
    one, half, top = np.float32(1.0), np.float32(0.5), np.float32(255.0)
    A = airlight.astype(np.float32)
    E = radiance.astype(np.float32)
    for v in range(H):
        for u in range(W):
            tt = t[v, u]
            c = min(cover[v, u], one) if has_cover else np.float32(0.0)
            is_wet = has_wet and wet[v, u]
            r = R[v, u] if is_wet else np.float32(0.0)
            for k in range(3):
                x = dark[rgb[v, u, k]] * (one - r) + mirror[v, u, k] * r if is_wet else np.float32(rgb[v, u, k])
                x = x * tt + A[k] * (one - tt)
                if c > 0:
                    x = (one - c) * x + c * E[k]
                out[v, u, k] = np.uint8(min(x, top) + half)
