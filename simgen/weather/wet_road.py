"""A wet road in a camera image: darker where the water film traps light, and a mirror of what
lies above it (derivations: docs/weather.md).

Darker (Lekner and Dorf 1988). Light enters the film (the air-water interface reflects ``r_e`` of
diffuse light: the hemispherical average of Fresnel's reflectance, 0.066 for n = 1.333), reaches
the surface of albedo a, and leaves it diffusely; of that, the share ``1 - r_i`` escapes the film
and ``r_i = 1 - (1 - r_e) / n^2`` (0.474) is reflected back to the surface (total internal
reflection beyond the critical angle, and Fresnel's within it), which gives it another chance to
be absorbed. Summing the bounces, the wet surface's albedo is
``a_w = a (1 - r_e)(1 - r_i) / (1 - a r_i)``: 0.52 a for asphalt (a = 0.1), 0.69 a for a white
marking (a = 0.6). Radiance leaving the film at an angle theta from the normal carries Fresnel's
``1 - R(theta)`` of the inside's, whose hemispherical average is ``1 - r_e``, so the diffuse part
seen from the camera is the dry pixel times ``a_w / a (1 - R(theta)) / (1 - r_e)``, the albedo a
read from the dry pixel (its value over 255).

Glossier. The film's top is a horizontal mirror of reflectance ``R(theta)``, Fresnel's for
unpolarised light; what it mirrors is found in image space: the reflected ray from each road
point is marched through the depth buffer until it passes behind a visible surface other than the
wet ground (it takes that surface's colour) or leaves the image or the near plane (it takes the
sky, the rain's overcast airlight). That is exact for every reflected ray whose first hit is
visible to the camera; a hit on something the camera does not see (a car's underside) takes the
surface in front of it. The march runs on every ``stride``-th pixel (a grid about 200 wide), is
blurred by the film's roughness (:func:`mirrored`) and interpolated between.

References: J. Lekner, M. C. Dorf, "Why some things are darker when wet", Appl. Opt. 27, 1988.
S. Twomey, C. F. Bohren, J. L. Mergenthaler, "Reflectance and albedo differences between wet and
dry surfaces", Appl. Opt. 25, 1986.
"""
from __future__ import annotations

import functools

import cv2
import numba
import numpy as np

from .veil import WetGround, compose

WATER_INDEX = 1.333
MARCH_START = 0.05     # m along the reflected ray: its first step
MARCH_GROWTH = 1.15    # each step 15% longer than the last
MARCH_STEPS = 60       # reaches 0.05 x 1.15^60 = 220 m
HIT_EPS = 0.02         # m behind a surface before the ray counts as passing it
COARSE_WIDTH = 200     # px: the march's grid is about this wide
ROUGHNESS = 0.01       # rad, rms slope of the film's surface (a choice: docs/weather.md)
GRAZING_COS = 0.2      # cos(incidence) where the mirror is bright (78 degrees), for the blur across


def fresnel(cos_i: np.ndarray, n: float = WATER_INDEX) -> np.ndarray:
    """Reflectance of unpolarised light at an air-to-medium interface (index n) for incidence
    cosines ``cos_i`` (any shape, in (0, 1])."""
    c = np.clip(np.asarray(cos_i, np.float64), 1e-9, 1.0)
    cos_t = np.sqrt(1.0 - (1.0 - c * c) / (n * n))
    rs = (c - n * cos_t) / (c + n * cos_t)
    rp = (n * c - cos_t) / (n * c + cos_t)
    return (rs * rs + rp * rp) / 2


@functools.lru_cache(maxsize=4)
def diffuse_fresnel(n: float = WATER_INDEX) -> float:
    """``r_e``: the reflectance of diffuse light at the interface, ``int R(theta) 2 sin cos dtheta``."""
    x, w = np.polynomial.legendre.leggauss(200)
    c = 0.5 * (x + 1.0)                                    # cos theta on (0, 1); d(cos^2) = 2 c dc
    return float(0.5 * np.sum(w * fresnel(c, n) * 2 * c))


def wet_albedo_ratio(albedo: np.ndarray, n: float = WATER_INDEX) -> np.ndarray:
    """``a_w / a``, Lekner and Dorf's wet-to-dry albedo ratio for dry albedos ``albedo`` in [0, 1]."""
    r_e = diffuse_fresnel(n)
    r_i = 1.0 - (1.0 - r_e) / n**2
    return (1.0 - r_e) * (1.0 - r_i) / (1.0 - np.asarray(albedo, np.float64) * r_i)


@functools.lru_cache(maxsize=1)
def _dark_lut() -> np.ndarray:
    """(256,) float32: each dry level v times the wet albedo ratio of albedo v / 255, over 1 - r_e."""
    v = np.arange(256.0)
    return (v * wet_albedo_ratio(v / 255.0) / (1.0 - diffuse_fresnel())).astype(np.float32)


@functools.lru_cache(maxsize=16)
def _mirror_reflectance(shape: tuple[int, int], K_bytes: bytes, up_bytes: bytes) -> np.ndarray:
    """(H, W) float32 Fresnel reflectance of a horizontal water surface seen through each pixel:
    incidence cosine ``-ray . up``, up (3,) the surface normal in the camera frame (a camera's
    constant)."""
    K = np.frombuffer(K_bytes, np.float64).reshape(3, 3)
    up = np.frombuffer(up_bytes, np.float64)
    H, W = shape
    u = (np.arange(W) + 0.5 - K[0, 2]) / K[0, 0]
    v = (np.arange(H) + 0.5 - K[1, 2]) / K[1, 1]
    ray = np.stack(np.broadcast_arrays(u[None, :], v[:, None], np.ones((1, 1))), -1)
    cos_i = -(ray @ up) / np.linalg.norm(ray, axis=-1)
    out = np.where(cos_i > 0, fresnel(cos_i), 0.0).astype(np.float32)
    out.flags.writeable = False
    return out


def wet_ground(rgb: np.ndarray, depth: np.ndarray, wet: np.ndarray, K: np.ndarray, up_cam: np.ndarray,
               sky_radiance: np.ndarray) -> WetGround:
    """What the film does to the image (module docstring), for simgen.weather.veil.compose.

    rgb : (H, W, 3) uint8 dry image.  depth : (H, W) camera z (m), 0 for the sky.
    wet : (H, W) bool, the horizontal surfaces under a water film (the paved ground).
    up_cam : (3,) unit normal of the ground, camera frame.  sky_radiance : (3,) what a reflected
    ray that leaves the scene brings (pixel units)."""
    H, W = depth.shape
    up = np.asarray(up_cam, np.float64)
    K = np.asarray(K, np.float64)
    wet = np.ascontiguousarray(wet, np.bool_)
    mirror = mirrored(rgb, np.ascontiguousarray(depth, np.float32), wet, K, up, sky_radiance)
    return WetGround(wet, _mirror_reflectance((H, W), K.tobytes(), up.tobytes()), _dark_lut(), mirror)


def wet_road(rgb: np.ndarray, depth: np.ndarray, wet: np.ndarray, K: np.ndarray, up_cam: np.ndarray,
             sky_radiance: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8: the image with its wet pixels darkened and mirroring, nothing else
    (:func:`wet_ground` composed without a veil or particles)."""
    ground = wet_ground(rgb, depth, wet, K, up_cam, sky_radiance)
    return compose(rgb, np.ones(depth.shape, np.float32), np.zeros(3), ground=ground)


def mirrored(rgb: np.ndarray, depth: np.ndarray, wet: np.ndarray, K: np.ndarray, up: np.ndarray,
             sky_radiance: np.ndarray) -> np.ndarray:
    """(H, W, 3) float32: what the water's mirror shows at each pixel (module docstring), marched
    on a grid of every ``stride``-th pixel, blurred by the film's roughness by normalised
    convolution (a marched wet pixel weighs 1, others 0), the sky where no marched pixel is near,
    and interpolated to the full image bilinearly.

    Roughness: the water's surface normals spread by ROUGHNESS rad (rms) tilt the mirrored ray by
    twice that in the plane of incidence, and by twice that times cos(incidence) across it (nearly
    0 at the grazing angles where the mirror is bright): a Gaussian of 2 ROUGHNESS f pixels
    vertically and GRAZING_COS times that horizontally, which stretches reflections downwards as on
    a wet road."""
    H, W = depth.shape
    stride = max(1, round(W / COARSE_WIDTH))
    Hc, Wc = -(-H // stride), -(-W // stride)
    colour = np.zeros((Hc, Wc, 3), np.float32)
    weight = np.zeros((Hc, Wc), np.float32)
    K4 = np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2]], np.float64)
    _march(rgb, depth, wet, K4, up, np.asarray(sky_radiance, np.float32), stride, colour, weight)
    if ROUGHNESS > 0:
        sigma_y = 2 * ROUGHNESS * K[1, 1] / stride
        sigma_x = GRAZING_COS * 2 * ROUGHNESS * K[0, 0] / stride
        colour = cv2.GaussianBlur(colour, (0, 0), sigmaX=sigma_x, sigmaY=sigma_y, borderType=cv2.BORDER_CONSTANT)
        weight = cv2.GaussianBlur(weight, (0, 0), sigmaX=sigma_x, sigmaY=sigma_y, borderType=cv2.BORDER_CONSTANT)
    seen = weight > 1e-4
    coarse = np.where(seen[..., None], colour / np.where(seen, weight, 1.0)[..., None],
                      np.asarray(sky_radiance, np.float32)).astype(np.float32)
    # Cell (j, i) holds pixel (j stride + stride // 2, ...): a resize by exactly the stride (cv2
    # maps x to (x + 0.5) / stride - 0.5) puts it within half a pixel of there.
    return cv2.resize(coarse, (Wc * stride, Hc * stride), interpolation=cv2.INTER_LINEAR)[:H, :W]


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _march(rgb, depth, wet, K4, up, sky, stride, colour, weight):
    """For every ``stride``-th pixel (the middle one of each cell) that is wet: march its reflected
    ray through the depth buffer (module docstring) and write what it meets into ``colour``
    (Hc, Wc, 3), its weight 1 into ``weight`` (Hc, Wc). Compiled: one sequential loop."""
    H, W = depth.shape
    fx, fy, cx, cy = K4[0], K4[1], K4[2], K4[3]
    half = stride // 2
    for jc in range(colour.shape[0]):
        v = jc * stride + half
        if v >= H:
            continue
        for ic in range(colour.shape[1]):
            u = ic * stride + half
            if u >= W or not wet[v, u] or depth[v, u] <= 0:
                continue
            rx, ry = (u + 0.5 - cx) / fx, (v + 0.5 - cy) / fy
            z0 = depth[v, u]
            norm = np.sqrt(rx * rx + ry * ry + 1.0)
            dx, dy, dz = rx / norm, ry / norm, 1.0 / norm
            c = dx * up[0] + dy * up[1] + dz * up[2]
            if c >= 0:
                continue
            mx, my, mz = dx - 2 * c * up[0], dy - 2 * c * up[1], dz - 2 * c * up[2]
            r, g, b = sky[0], sky[1], sky[2]
            t = MARCH_START
            for _ in range(MARCH_STEPS):
                qx, qy, qz = rx * z0 + t * mx, ry * z0 + t * my, z0 + t * mz
                if qz <= 0.05:
                    break
                uq, vq = fx * qx / qz + cx, fy * qy / qz + cy
                if uq < 0 or uq >= W or vq < 0 or vq >= H:
                    break
                iu, iv = int(uq), int(vq)
                scene = depth[iv, iu]
                # Behind a visible surface by more than a rounding and less than a step's reach;
                # not the wet ground itself, which a ray mirrored off it leaves (at grazing angles
                # one pixel spans metres of road, so its centre's depth can be nearer than the ray).
                if (scene > 0 and not wet[iv, iu] and qz > scene + HIT_EPS
                        and qz < scene + max(0.5, 1.5 * (MARCH_GROWTH - 1) * t)):
                    r, g, b = rgb[iv, iu, 0], rgb[iv, iu, 1], rgb[iv, iu, 2]
                    break
                t *= MARCH_GROWTH
            colour[jc, ic, 0], colour[jc, ic, 1], colour[jc, ic, 2] = r, g, b
            weight[jc, ic] = 1.0
