"""Falling particles near a camera and the streaks they leave in one exposure: shared by the rain
and the snowfall camera models (derivations: docs/weather.md).

Which particles. A particle of optical diameter D at depth z images to a disc of ``d = f D / z``
pixels (f the focal length in pixels). Garg and Nayar (2005, 2007) separate the rain a camera sees
into the drops whose image is at least a pixel wide, ``z <= z_m = f D / 1 px``, which show as
individual streaks, and the far ones, each under a pixel, whose ensemble attenuates and brightens
like fog; that part is the Koschmieder veil of the model's extinction. So only particles with
``d >= d_min_px`` (1 px) are drawn, from the camera's near plane ``z_min`` on.

How many and where. With ``N(D)`` particles per m^3 per mm (simgen.weather.particles) and the
view's cross-section ``A(z)`` (m^2) at depth z, the drawn particles are a Poisson process of
density ``N(D) A(z)`` over ``z_min <= z <= f D / d_min``: their count is Poisson with mean
``M = int A(z) n(z) dz``, ``n(z)`` the particles per m^3 large enough to be resolved at z; each
one's depth follows ``A(z) n(z) / M`` and its diameter N(D) above the resolved size at that depth
(both by inverting their CDFs). ``A(z)`` is the image's window at depth z widened on each side by
the farthest a particle moves in half an exposure plus its radius, so that streaks entering the
image from outside are drawn too; particles whose streak misses the image are dropped after
projection.

The streak (Garg and Nayar 2004, 2007). A particle moving at velocity V relative to the camera
(its fall speed along gravity less the camera's own velocity) sweeps its disc from ``a`` to ``b``,
the projections of its position at the start and the end of the exposure T. A pixel it covers for
a time tau takes ``I = (1 - tau/T) I_b + (tau/T) E`` (background I_b, particle radiance E). The
coverage ``C = tau/T`` at a point at distance s along the streak and y across is the overlap of
``[s - rho, s + rho]`` (rho = sqrt(r^2 - y^2), r = d/2) with ``[0, L]``, over L = |b - a| (px):
``C <= d / L``, and its integral over the image is the disc's area ``pi d^2 / 4``. A fixed-focus
lens blurs the disc to ``d_eff = sqrt(d^2 + b^2)``, ``b = f A |1/z - 1/z_f|`` pixels (aperture A,
focus distance z_f; thin lens), spreading the same integral.

Rasterised in one compiled pass over the streaks (numba, as simgen/sun.py's shading): each is cut
into slabs across and cells along, 1 px apart; each cell carries its exact share of the coverage
and is splatted bilinearly into one accumulated image, except onto pixels where the scene's depth
buffer holds a surface nearer than the particle.

References: K. Garg, S. K. Nayar, "Detection and removal of rain from videos", CVPR 2004; "When
does a camera see rain?", ICCV 2005; "Vision and rain", IJCV 75, 2007.
"""
from __future__ import annotations

from typing import NamedTuple

import numba
import numpy as np

from .particles import SizeDistribution

ALONG_STEP = 1.0      # px between samples along a streak
ACROSS_STEP = 1.0     # px between slabs across a streak
DEPTH_GRID = 2048     # depths of the count's quadrature


class CameraOptics(NamedTuple):
    """What sets a particle's streak besides the scene: the exposure time ``exposure_s`` (s), the
    lens's entrance pupil diameter ``aperture_m`` (m) and its focus distance ``focus_m`` (m)."""
    exposure_s: float
    aperture_m: float
    focus_m: float


# The nuScenes cameras' optics by day (docs/weather.md). A 1/1.8" sensor of 1600 x 1200 pixels
# (nuScenes' sensor description) has a 4.5 um pitch, so f = 1266 px is a 5.7 mm lens; taken at
# f/2 its pupil is 2.85 mm, focused at its hyperfocal distance for a one-pixel blur circle,
# f_px A / 1 px = 3.6 m (sharp within a pixel from 1.8 m to infinity). Exposure: the ISO 2720
# equation t = K N^2 / (L S) with K = 12.5 cd s/m^2, N = 2, S = 100 and a scene of 60-130 cd/m^2
# (rain's 1,000-2,000 lx of overcast daylight on surfaces of reflectance 0.2) gives 4-8 ms: 5 ms,
# within nuScenes' auto-exposure limit of 20 ms.
DAY_OPTICS = CameraOptics(exposure_s=0.005, aperture_m=2.85e-3, focus_m=3.6)


class Particles(NamedTuple):
    """n particles during one exposure, camera frame (x right, y down, z forward): position at
    mid-exposure ``p_mid`` (n, 3) m, velocity relative to the camera ``velocity`` (n, 3) m/s,
    optical diameter ``diameter`` (n,) m."""
    p_mid: np.ndarray
    velocity: np.ndarray
    diameter: np.ndarray


def blur_px(z: np.ndarray, f_px: float, optics: CameraOptics) -> np.ndarray:
    """Defocus blur-circle diameter (px) of a point at depth ``z`` (m): ``f A |1/z - 1/z_f|``."""
    return f_px * optics.aperture_m * np.abs(1.0 / np.asarray(z, np.float64) - 1.0 / optics.focus_m)


def _window(K: np.ndarray, size: tuple[int, int]) -> tuple[float, float, float, float]:
    """The image's window per metre of depth: x_lo, x_hi, y_lo, y_hi (m/m)."""
    W, H = size
    return -K[0, 2] / K[0, 0], (W - K[0, 2]) / K[0, 0], -K[1, 2] / K[1, 1], (H - K[1, 2]) / K[1, 1]


def _min_melted(dist: SizeDistribution, optical_mm: np.ndarray) -> np.ndarray:
    """The melted diameter (mm) whose optical diameter is ``optical_mm`` (the inverse of the
    monotone ``dist.optical_diameter``), d_max where no particle is that large."""
    grid = np.linspace(0.0, dist.d_max, 4097)
    return np.interp(optical_mm, dist.optical_diameter(grid), grid, right=dist.d_max)


def depth_profile(dist: SizeDistribution, K: np.ndarray, size: tuple[int, int], margin_m: float, z_min: float,
                  d_min_px: float) -> tuple[np.ndarray, np.ndarray]:
    """The drawn particles' depths: a grid z (g,) m and the expected number of particles nearer
    than each, (g,) (trapezoid rule of ``A(z) n(z)``; its last entry is the mean count M)."""
    f = K[0, 0]
    z_top = f * dist.optical_diameter(dist.d_max) * 1e-3 / d_min_px
    if z_top <= z_min:
        return np.array([z_min, z_min]), np.zeros(2)
    z = np.geomspace(z_min, z_top, DEPTH_GRID)
    x_lo, x_hi, y_lo, y_hi = _window(K, size)
    area = ((x_hi - x_lo) * z + 2 * margin_m) * ((y_hi - y_lo) * z + 2 * margin_m)       # m^2
    n = dist.number_density(_min_melted(dist, z * d_min_px / f * 1e3))                     # 1/m^3
    density = area * n
    cum = np.concatenate([[0.0], np.cumsum((density[1:] + density[:-1]) / 2 * np.diff(z))])
    return z, cum


def sample_particles(dist: SizeDistribution, K: np.ndarray, size: tuple[int, int], optics: CameraOptics,
                     down_cam: np.ndarray, v_cam: np.ndarray, rng: np.random.Generator, z_min: float,
                     d_min_px: float = 1.0) -> Particles:
    """The particles of ``dist`` a camera resolves in one exposure (module docstring).

    K : (3, 3) intrinsics of an image of ``size`` (W, H). down_cam : (3,) unit vector of gravity,
    camera frame. v_cam : (3,) the camera's velocity through the air, camera frame (m/s).
    z_min : the nearest depth imaged (m). Draws, in order: the count, the depths, the diameters,
    the lateral positions (a fixed stream for a seed)."""
    down_cam = np.asarray(down_cam, np.float64)
    v_cam = np.asarray(v_cam, np.float64)
    top_speed = float(dist.fall_speed(dist.d_max)) + float(np.linalg.norm(v_cam))
    margin = top_speed * optics.exposure_s / 2 + dist.optical_diameter(dist.d_max) * 1e-3 / 2
    z_grid, cum = depth_profile(dist, K, size, margin, z_min, d_min_px)
    n = int(rng.poisson(cum[-1]))
    z = np.interp(rng.random(n) * cum[-1], cum, z_grid)
    melted = dist.sample(rng.random(n), _min_melted(dist, z * d_min_px / K[0, 0] * 1e3))
    x_lo, x_hi, y_lo, y_hi = _window(K, size)
    x = x_lo * z - margin + rng.random(n) * ((x_hi - x_lo) * z + 2 * margin)
    y = y_lo * z - margin + rng.random(n) * ((y_hi - y_lo) * z + 2 * margin)
    velocity = dist.fall_speed(melted)[:, None] * down_cam - v_cam
    return Particles(np.stack([x, y, z], 1), velocity, dist.optical_diameter(melted) * 1e-3)


class Streaks(NamedTuple):
    """Projected streaks (all (n,)): start ``a`` and end ``b`` (n, 2) px (continuous image
    coordinates, pixel (i, j) spans [i, i + 1) x [j, j + 1)), their depths ``z_a``, ``z_b`` (m),
    the sharp disc diameter ``d`` and the blurred one ``d_eff`` (px)."""
    a: np.ndarray
    b: np.ndarray
    z_a: np.ndarray
    z_b: np.ndarray
    d: np.ndarray
    d_eff: np.ndarray


def project(particles: Particles, K: np.ndarray, size: tuple[int, int], optics: CameraOptics,
            z_min: float) -> Streaks:
    """The streaks of ``particles`` in an image of ``size`` (W, H): the positions at the start and
    the end of the exposure projected through K; particles that come nearer than half the near
    plane during it (they pass the lens) and streaks whose bounding box misses the image are dropped."""
    half = particles.velocity * (optics.exposure_s / 2)
    start, end = particles.p_mid - half, particles.p_mid + half
    f = K[0, 0]
    z_mid = particles.p_mid[:, 2]
    d = f * particles.diameter / z_mid
    d_eff = np.hypot(d, blur_px(z_mid, f, optics))
    keep = np.minimum(start[:, 2], end[:, 2]) >= z_min / 2
    start, end, d, d_eff = start[keep], end[keep], d[keep], d_eff[keep]

    def uv(p):
        return np.stack([K[0, 0] * p[:, 0] / p[:, 2] + K[0, 2], K[1, 1] * p[:, 1] / p[:, 2] + K[1, 2]], 1)

    a, b = uv(start), uv(end)
    r = d_eff[:, None] / 2
    lo, hi = np.minimum(a, b) - r, np.maximum(a, b) + r
    W, H = size
    inside = (hi[:, 0] >= 0) & (lo[:, 0] <= W) & (hi[:, 1] >= 0) & (lo[:, 1] <= H)
    return Streaks(a[inside], b[inside], start[inside, 2], end[inside, 2], d[inside], d_eff[inside])


def coverage(streaks: Streaks, size: tuple[int, int], depth: np.ndarray) -> np.ndarray:
    """(H, W) float32 share of the exposure during which each pixel is covered by a particle
    (summed over particles, not clipped), the parts of streaks behind the scene's surfaces left
    out. depth : (H, W) camera z of the scene (m), 0 where nothing was hit (the sky)."""
    W, H = size
    out = np.zeros((H, W), np.float32)
    if len(streaks.d):
        _rasterise(np.ascontiguousarray(streaks.a, np.float64), np.ascontiguousarray(streaks.b, np.float64),
                   streaks.z_a.astype(np.float64), streaks.z_b.astype(np.float64), streaks.d.astype(np.float64),
                   streaks.d_eff.astype(np.float64), np.ascontiguousarray(depth, np.float32), out)
    return out


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _rasterise(a, b, z_a, z_b, d, d_eff, depth, out):
    """Add each streak's coverage into ``out`` (H, W) float32 (module docstring).

    Streak i sweeps a disc of diameter ``d_eff[i]`` (px) from ``a[i]`` to ``b[i]`` (n, 2); its
    coverage integrates to the sharp disc's area ``pi d[i]^2 / 4``. The disc is cut into slabs
    across the motion, ACROSS_STEP wide, each replaced by a slab of the same area and a constant
    half-chord rho; along a slab the coverage at s is ``|[s - rho, s + rho] & [0, L]| / L``,
    integrated exactly over cells ALONG_STEP long and placed at their midpoints.
    Each sample is splatted bilinearly onto the pixel centres, except onto pixels whose scene is
    nearer than it (``0 < depth < z``, z interpolated from z_a to z_b). Compiled: one sequential
    loop (the same inputs give the same bytes)."""
    H, W = out.shape
    for i in range(len(d)):
        dx, dy = b[i, 0] - a[i, 0], b[i, 1] - a[i, 1]
        L = np.sqrt(dx * dx + dy * dy)
        tx, ty = (dx / L, dy / L) if L > 1e-9 else (0.0, 1.0)
        r = d_eff[i] / 2
        if r <= 0:
            continue
        n_y = max(1, int(np.ceil(d_eff[i] / ACROSS_STEP)))
        width = d_eff[i] / n_y
        scale = (d[i] / d_eff[i]) ** 2
        for k in range(n_y):
            lo, hi = -r + k * width, -r + (k + 1) * width
            area = _disc_below(hi, r) - _disc_below(lo, r)
            rho = area / (2 * width)
            y_c = (lo + hi) / 2
            span = L + 2 * rho
            n_s = max(1, int(np.ceil(span / ALONG_STEP)))
            step = span / n_s
            unit = scale * width                  # the slab's coverage per unit of its along-integral
            for j in range(n_s):
                s0 = -rho + j * step
                w = _cell_share(s0, s0 + step, rho, L) * unit
                s = s0 + step / 2
                x = a[i, 0] + s * tx - y_c * ty
                y = a[i, 1] + s * ty + y_c * tx
                frac = min(max(s / L, 0.0), 1.0) if L > 1e-9 else 0.5
                _splat(out, depth, x - 0.5, y - 0.5, w, z_a[i] + (z_b[i] - z_a[i]) * frac)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _disc_below(y, r):
    """Area of a disc of radius r below the chord at offset y from its centre, less pi r^2 / 2."""
    y = min(max(y, -r), r)
    return y * np.sqrt(max(r * r - y * y, 0.0)) + r * r * np.arcsin(y / r)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _ramp_integral(x, L):
    """``int_-inf^x clip(t, 0, L) dt``."""
    if x <= 0:
        return 0.0
    if x <= L:
        return x * x / 2
    return L * L / 2 + L * (x - L)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _cell_share(s0, s1, rho, L):
    """``int_s0^s1 C(s) ds``, C(s) the share of an exposure during which a half-chord rho moving
    over [0, L] covers the point s: ``(clip(s + rho, 0, L) - clip(s - rho, 0, L)) / L``, whose
    integral over all s is 2 rho (a resting one, L = 0, covers |s| < rho for the whole exposure)."""
    if L <= 1e-9:
        return max(min(s1, rho) - max(s0, -rho), 0.0)
    return (_ramp_integral(s1 + rho, L) - _ramp_integral(s0 + rho, L)
            - _ramp_integral(s1 - rho, L) + _ramp_integral(s0 - rho, L)) / L


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _splat(out, depth, x, y, w, z):
    """Add weight w at (x, y) in pixel-centre coordinates bilinearly into out (H, W), leaving out
    the pixels whose scene surface is nearer than the particle's depth z (``0 < depth < z``)."""
    H, W = out.shape
    i0, j0 = int(np.floor(x)), int(np.floor(y))
    fx, fy = x - i0, y - j0
    for dj in range(2):
        jj = j0 + dj
        if jj < 0 or jj >= H:
            continue
        wy = fy if dj else 1.0 - fy
        for di in range(2):
            ii = i0 + di
            if 0 <= ii < W and not (0 < depth[jj, ii] < z):
                out[jj, ii] += w * wy * (fx if di else 1.0 - fx)
