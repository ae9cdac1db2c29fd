"""Sensor degradation: fog (camera and lidar, one extinction), lens dirt, beam loss, a narrowed
lidar field of view and dead sensors. Pure functions of arrays and an explicit rng.

Fog
---
One extinction coefficient ``alpha`` (1/m) drives both sensors. Severity 1-5 uses the lidar
alphas of the common-corruption benchmark, ``FOG_ALPHA``; the meteorological optical range
(visibility) is ``MOR = ln(20) / alpha``.

- Camera, Koschmieder's law on the rendered metric range ``d`` of each pixel:
  ``I = J t + A (1 - t)``, ``t = exp(-alpha d)``; sky pixels (no hit) take the airlight ``A``.
- Lidar, the model of Hahner et al. (ICCV 2021), re-derived here from its equations. With the
  transmitted pulse ``P0(t) = P0 sin^2(pi t / (2 tau_H))`` on ``[0, 2 tau_H]`` and the received
  power ``P_R(R) = C_A int P0(t) H(R - c t / 2) dt``, both responses in units of ``C_A P0 2/c``:

  * hard target of reflectivity ``rho`` at ``R0`` (peak of its echo):
    ``P_hard = rho cos(inc) / R0^2 * exp(-2 alpha R0)``;
  * fog (soft target, backscatter ``beta``, beam crossover ``xi``) between sensor and target:
    ``P_soft(R) = beta int_{R - c tau_H}^{R} sin^2(pi (R - R') / (c tau_H)) xi(R') / R'^2
    exp(-2 alpha R') dR'``, for ``R <= R0``.

  A return's power is the larger of ``P_hard`` and ``max_{R <= R0} P_soft(R)``. If the fog wins,
  the point moves along its ray to the argmax range and takes the fog intensity; a return
  whose power falls below the lidar's detection threshold is lost.

  The detection threshold rises with the daylight background. Fog scatters sunlight into the
  receiver's field of view: the airlight the camera model adds as ``A (1 - t)``, here over the
  beam's path up to its solid target, ``B = 1 - exp(-alpha R0)``. The receiver must hold its
  false-alarm rate against that background, so ``T = min_return (1 + G B)``. The gain ``G``
  (``LidarConfig.fog_background_gain``) is a calibration, not a derivation: at its default of
  200 the simulated HDL-32E behaves as lidars measured in fog do (Bijelic et al. 2018; Hahner
  et al. 2021): the far scene fades already in light fog, the point count falls with every
  severity, and fog clutter near the sensor appears only in dense fog (MOR below about 100 m).
  With ``G = 0`` every fog echo beats the clear-weather threshold, so each beam that loses its
  target reports fog instead and the point count never falls. ``max_R P_soft`` and its
  argmax, as functions of ``R0``, are a lookup table built once per ``alpha`` (a running max
  over a fine range grid), so a sweep costs one table look-up per point.
  ``beta = 0.046 / MOR`` (Rasshofer et al. 2011, advection fog), the crossover ``xi`` ramps
  from 0 at ``R1 = 0.9`` m to 1 at ``R2 = 1.0`` m, and ``tau_H = 10`` ns. Intensities use the
  simulator's own scale (lidar.py): ``intensity = 255 * clip(P * ref_range^2, 0, 1)``.
"""
from __future__ import annotations

import functools
import math

import cv2
import numpy as np

FOG_ALPHA = (0.0, 0.005, 0.01, 0.02, 0.03, 0.06)   # severity 0..5 (1/m)
C_LIGHT = 299_792_458.0
TAU_H = 10e-9             # half-power pulse width (s)
XI_R1, XI_R2 = 0.9, 1.0   # beam crossover: no overlap before R1, full overlap after R2 (m)
BETA_PER_INV_MOR = 0.046  # backscatter beta = 0.046 / MOR (1/m)
FOG_RANGE_NOISE = 0.05    # m, spread of the fog return's range
AIRLIGHT = np.array([205.0, 208.0, 212.0])         # RGB of fog-scattered daylight
TABLE_STEP = 0.01         # m
TABLE_MAX = 120.0         # m


def visibility_of(alpha: float) -> float:
    """Meteorological optical range (m) of extinction ``alpha``: ``ln(20) / alpha``."""
    return math.log(20.0) / alpha if alpha > 0 else math.inf


def alpha_of_visibility(mor: float) -> float:
    """Extinction (1/m) for a visibility of ``mor`` metres."""
    return math.log(20.0) / mor


# ---------------------------------------------------------------- camera

def fog_image(rgb: np.ndarray, range_m: np.ndarray, alpha: float, airlight=AIRLIGHT) -> np.ndarray:
    """Koschmieder fog. rgb (H, W, 3) uint8, range_m (H, W) metres along each pixel's ray, 0 where
    nothing was hit (sky: full airlight). Returns uint8 ``round(J t + A (1 - t))``."""
    # float32 with OpenCV's vectorised arithmetic: about 5x faster than float64 numpy at 1600x900.
    t = np.exp(np.float32(-alpha) * range_m.astype(np.float32))
    t[range_m <= 0] = 0.0
    A = tuple(float(a) for a in airlight) + (0.0,)
    x = cv2.subtract(rgb.astype(np.float32), A)
    x = cv2.multiply(x, cv2.merge([t, t, t]))
    x = cv2.add(x, A)                          # J t + A (1 - t), as A + (J - A) t; in [0, 255]
    return cv2.convertScaleAbs(x)              # rounds to the nearest level, saturates


def lens_dirt(rgb: np.ndarray, severity: int, rng: np.random.Generator) -> np.ndarray:
    """Blend ``severity`` (1-5) x 3 soft dirt / drop blobs onto an image (H, W, 3) uint8.

    Each blob is a blurred ellipse of brown-grey dirt with opacity 0.5-0.95; the blob layout
    comes from ``rng`` (use one rng per camera and scene: dirt stays put on the lens)."""
    if severity <= 0:
        return rgb
    H, W = rgb.shape[:2]
    n = 3 * severity
    mask = np.zeros((H, W), np.float32)
    color = np.zeros((H, W, 3), np.float32)
    cx, cy = rng.uniform(0, W, n), rng.uniform(0, H, n)
    ax = rng.uniform(0.03, 0.06 + 0.02 * severity, n) * W
    ay = ax * rng.uniform(0.5, 1.2, n)
    ang = rng.uniform(0, 180, n)
    opacity = rng.uniform(0.5, 0.95, n)
    tint = rng.uniform(40, 110, (n, 1)) * np.array([[1.0, 0.9, 0.75]])
    for i in range(n):   # a handful of blobs, drawn by OpenCV (not a loop over pixels)
        blob = np.zeros((H, W), np.float32)
        cv2.ellipse(blob, (int(cx[i]), int(cy[i])), (max(1, int(ax[i])), max(1, int(ay[i]))), float(ang[i]),
                    0, 360, float(opacity[i]), -1)
        newer = blob > mask
        mask = np.maximum(mask, blob)
        color[newer] = tint[i]
    k = max(3, int(0.02 * W) | 1)
    mask = cv2.GaussianBlur(mask, (k, k), 0)[..., None]
    out = rgb.astype(np.float32) * (1 - mask) + color * mask
    return np.clip(np.round(out), 0, 255).astype(np.uint8)


# ---------------------------------------------------------------- lidar fog

@functools.lru_cache(maxsize=16)
def fog_table(alpha: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(R grid (n,), max_{R <= R0} P_soft (n,), its argmax range (n,)) for extinction ``alpha``.

    P_soft(R) on the grid is the discrete convolution of the pulse shape with
    ``beta xi(R') / R'^2 exp(-2 alpha R')``; built once per alpha (cached)."""
    r = np.arange(0.0, TABLE_MAX, TABLE_STEP)
    beta = BETA_PER_INV_MOR / visibility_of(alpha)
    xi = np.clip((r - XI_R1) / (XI_R2 - XI_R1), 0.0, 1.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        h = np.where(r > 0, beta * xi / r**2 * np.exp(-2 * alpha * r), 0.0)
    width = C_LIGHT * TAU_H                                   # range extent of the pulse (m)
    s = np.arange(0.0, width + TABLE_STEP, TABLE_STEP)        # R - R'
    pulse = np.sin(np.pi * s / width) ** 2
    p_soft = np.convolve(h, pulse, mode="full")[: len(r)] * TABLE_STEP   # sum_s pulse(s) h(R - s) ds
    best = np.maximum.accumulate(p_soft)
    arg = np.maximum.accumulate(np.where(p_soft >= best, np.arange(len(r)), 0))
    return r, best, r[arg]


def fog_lidar(points: np.ndarray, rho_cos: np.ndarray, range_m: np.ndarray, dir_lidar: np.ndarray, alpha: float,
              min_return: float, ref_range: float, rng: np.random.Generator, *,
              background_gain: float) -> tuple[np.ndarray, np.ndarray]:
    """Apply fog to one sweep.

    points : (n, >=5) float32 x, y, z, intensity, ring (lidar frame), then any columns carried
    along unchanged (e.g. a per-point label). rho_cos : (n,) reflectivity
    times cos(incidence). range_m : (n,) measured range. dir_lidar : (n, 3) unit ray directions.
    min_return : clear-weather detection threshold on ``P`` (1/m^2); ref_range : intensity scale
    (lidar.py). background_gain : ``G``, the threshold's rise under a full-airlight background.

    Returns (points' (k, same columns), is_fog (k,) bool): the surviving returns, hard ones attenuated in
    place, fog-won ones moved along their ray to the fog range with the fog intensity.
    """
    if alpha <= 0 or len(points) == 0:
        return points.copy(), np.zeros(len(points), bool)
    r, best, arg = fog_table(alpha)
    p_hard = rho_cos / range_m**2 * np.exp(-2 * alpha * range_m)
    idx = np.minimum((range_m / TABLE_STEP).astype(np.int64), len(r) - 1)     # the grid is uniform from 0
    p_soft, r_fog = best[idx], arg[idx]
    fog_wins = p_soft > p_hard
    power = np.where(fog_wins, p_soft, p_hard)
    noise = FOG_RANGE_NOISE * rng.standard_normal(len(points))    # drawn for all: a fixed stream
    new_range = np.where(fog_wins, np.maximum(r_fog + noise, 0.0), range_m)
    out = points.copy()
    out[:, :3] = points[:, :3] - dir_lidar * (range_m - new_range)[:, None]
    out[:, 3] = np.round(255.0 * np.clip(power * ref_range**2, 0.0, 1.0))
    background = 1.0 - np.exp(-alpha * range_m)             # airlight fraction along the beam
    keep = power >= min_return * (1.0 + background_gain * background)
    return out[keep].astype(np.float32), fog_wins[keep]


# ---------------------------------------------------------------- lidar structure

def drop_rings(points: np.ndarray, rings: np.ndarray) -> np.ndarray:
    """Points (n, >=5) without those whose ring (column 4) is in ``rings``; whole rows are kept."""
    return points[~np.isin(points[:, 4].astype(np.int64), np.asarray(rings, np.int64))]


def choose_rings(n_drop: int, rng: np.random.Generator, n_rings: int = 32) -> np.ndarray:
    """``n_drop`` distinct ring indices, sorted."""
    return np.sort(rng.choice(n_rings, size=n_drop, replace=False))


def keep_sector(points: np.ndarray, forward_lidar: np.ndarray, fov_deg: float) -> np.ndarray:
    """Points (n, >=5) whose horizontal azimuth is within ``fov_deg / 2`` of ``forward_lidar``
    (a unit xy direction in the lidar frame: the ego's forward axis); whole rows are kept."""
    if fov_deg >= 360:
        return points
    az = np.arctan2(points[:, 1], points[:, 0]) - math.atan2(forward_lidar[1], forward_lidar[0])
    az = (az + np.pi) % (2 * np.pi) - np.pi
    return points[np.abs(az) <= np.deg2rad(fov_deg) / 2]
