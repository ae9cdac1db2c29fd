"""Sensor degradation: fog (camera and lidar, one extinction), lens dirt, beam loss, a narrowed
lidar field of view and dead sensors. Pure functions of arrays and an explicit rng.

Fog
---
One extinction coefficient ``alpha`` (1/m) drives both sensors, so that a fog setting means the
same thing to each. Severity 1-5 uses the lidar alphas of the common-corruption benchmark,
``FOG_ALPHA``; the meteorological optical range (visibility) is ``MOR = ln(20) / alpha``.

- Camera, Koschmieder's law on the rendered metric range ``d`` of each pixel:
  ``I = J t + A (1 - t)``, ``t = exp(-alpha d)``; sky pixels (no hit) take the airlight ``A``.
- Lidar: the lidar equation with a hard and a soft (fog) target, after Rasshofer et al. (2011)
  and Hahner et al. (ICCV 2021, Sec. 3), re-derived from their equations with the units written
  out (no code of theirs is used). Strongest return: the sensor reports the higher of the hard
  echo ``rho cos exp(-2 alpha R0) / R0^2`` and the fog's peak, when it reaches the clear-weather
  threshold ``min_return``; so fog replaces a hard return only where it is stronger. The fog's
  echo is weighted by the overlap of the transmitter's beam and the receiver's field of view,
  derived from the sensor's biaxial geometry (:class:`Optics`, :func:`overlap`). The fog's peak
  power and range, as functions of R0, are a table built once per alpha (:func:`fog_table`); the
  receiver locates that broad, weak peak with noise that grows as its curvature and power fall
  (:func:`fog_range_sigma`), so fog returns form a cloud in front of the sensor.
  Intensities use lidar.py's scale: ``intensity = 255 * clip(p * ref_range^2, 0, 1)``.

The derivation with units, the parameters and how the results move with them: docs/fog.md.

References: R. H. Rasshofer, M. Spies, H. Spies, "Influences of weather phenomena on automotive
laser radar systems", Adv. Radio Sci. 9, 2011. M. Hahner, C. Sakaridis, D. Dai, L. Van Gool,
"Fog Simulation on Real LiDAR Point Clouds for 3D Object Detection in Adverse Weather", ICCV 2021.
T. Halldorsson, J. Langerholc, "Geometrical form factors for the lidar function", Appl. Opt. 17,
1978. K. Stelmaszczyk et al., "Analytical function for lidar geometrical compression form-factor
calculations", Appl. Opt. 44, 2005. Velodyne, HDL-32E User's Manual.
"""
from __future__ import annotations

import functools
import math
from typing import NamedTuple

import cv2
import numpy as np

FOG_ALPHA = (0.0, 0.005, 0.01, 0.02, 0.03, 0.06)   # severity 0..5 (1/m)
C_LIGHT = 299_792_458.0
TAU_H = 20e-9             # half-power pulse width (s), Hahner's default
BETA_PER_INV_MOR = 0.046  # backscatter beta = 0.046 / MOR (1/m)
MIN_RANGE = 0.05          # m, the HDL-32E manual's nearest valid data
RANGE_SIGMA = 0.02        # m, the HDL-32E's range accuracy (one sigma) ...
RANGE_SIGMA_POWER = 0.1 / 25.0**2   # ... for a hard echo of this power (1/m^2): rho 0.1 at 25 m
PEAK_SPAN = 0.25          # m, half-span of the difference that measures a fog peak's curvature
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
    t = np.exp(np.float32(-alpha) * range_m.astype(np.float32, copy=False))
    t[range_m <= 0] = 0.0
    # OpenCV's blendLinear computes (J w1 + A w2) / (w1 + w2 + 1e-5) per pixel, from the uint8
    # image to the nearest uint8 level, in one pass instead of separate float32 steps that each
    # allocate and touch an image-sized array. Weights
    # summing to 1e4 make its epsilon a 1e-9 share (with t and 1 - t it would be 1e-5, 0.0026 of
    # a level at 255).
    w = t * np.float32(1e4)
    airlight_image = _airlight_image(rgb.shape, tuple(float(a) for a in airlight))
    return cv2.blendLinear(np.ascontiguousarray(rgb), airlight_image, w, np.float32(1e4) - w)


@functools.lru_cache(maxsize=4)
def _airlight_image(shape: tuple[int, ...], airlight: tuple[float, ...]) -> np.ndarray:
    """(H, W, 3) uint8 image of the airlight colour (rounded to levels), read-only."""
    image = np.empty(shape, np.uint8)
    image[:] = np.round(airlight).astype(np.uint8)
    image.flags.writeable = False
    return image


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


# ---------------------------------------------------------------- lidar optics

class Optics(NamedTuple):
    """One laser-detector pair of a biaxial lidar, both cones top-hat and their axes parallel:
    ``offset`` (m) between the transmitter's and the receiver's axes, the beam's radius at the
    exit ``tx_radius`` (m) and half-angle divergence ``tx_divergence`` (rad), the receiver's
    aperture radius ``rx_radius`` (m) and half-angle field of view ``rx_fov`` (rad)."""
    offset: float
    tx_radius: float
    tx_divergence: float
    rx_radius: float
    rx_fov: float

    def onset(self) -> float:
        """Range (m) at which the beam first enters the receiver's field (the overlap is 0 before)."""
        return max((self.offset - self.tx_radius - self.rx_radius) / (self.tx_divergence + self.rx_fov), 0.0)

    def full(self) -> float:
        """Range (m) from which the receiver's field holds the whole beam (the overlap is 1 after)."""
        return max((self.offset + self.tx_radius - self.rx_radius) / (self.rx_fov - self.tx_divergence), 0.0)


# The HDL-32E: the divergence is its manual's laser spot (the wider side); Velodyne publishes no
# lens offset, apertures or receiver field of view, so those are a design that fits its head
# (docs/fog.md: the sources, and how the fog moves with each constant).
HDL32E = Optics(offset=0.030, tx_radius=0.005, tx_divergence=1.67e-3, rx_radius=0.0125, rx_fov=4.0e-3)


def overlap(r: np.ndarray, optics: Optics = HDL32E) -> np.ndarray:
    """The overlap ("crossover") xi(r) (same shape as ``r``, m): the share of the beam's cross-section
    at range r inside the receiver's field, i.e. the intersection of two discs of radii
    ``a = tx_radius + tx_divergence r`` (beam) and ``b = rx_radius + rx_fov r`` (field), centres
    ``offset`` apart, over the beam's area. 0 up to ``optics.onset()``, 1 from ``optics.full()``."""
    r = np.asarray(r, np.float64)
    a = optics.tx_radius + optics.tx_divergence * r
    b = optics.rx_radius + optics.rx_fov * r
    d = optics.offset
    with np.errstate(invalid="ignore", divide="ignore"):
        cos_a = np.clip((d * d + a * a - b * b) / (2 * d * a), -1.0, 1.0)
        cos_b = np.clip((d * d + b * b - a * a) / (2 * d * b), -1.0, 1.0)
        kite = np.sqrt(np.maximum((a + b - d) * (d + a - b) * (d - a + b) * (d + a + b), 0.0))
        lens = a * a * np.arccos(cos_a) + b * b * np.arccos(cos_b) - 0.5 * kite
    share = np.clip(lens / (np.pi * a * a), 0.0, 1.0)
    # Exact where one disc holds the other, so that the overlap is exactly 1 from full overlap on.
    share = np.where(d <= a - b, (b / a) ** 2, share)
    return np.where(d >= a + b, 0.0, np.where(d <= b - a, 1.0, share))


# ---------------------------------------------------------------- lidar fog

class FogReturns(NamedTuple):
    """What fog makes of each clean return (all (n,)): its attenuated hard power ``p_hard`` and the
    fog's strongest power ``p_soft`` (1/m^2, lidar.py's units), the range of the fog's peak as the
    sensor reports it (m, without noise) and one sigma (m) of where the receiver locates it
    (``range_sigma``, 0 where the hard echo wins), whether the fog wins (``p_soft > p_hard``) and
    whether the ray reports a return at all (``max(p_hard, p_soft) >= min_return``)."""
    p_hard: np.ndarray
    p_soft: np.ndarray
    fog_range: np.ndarray
    range_sigma: np.ndarray
    fog_wins: np.ndarray
    kept: np.ndarray


def _fog_cells(alpha: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The soft-target integrand on the table grid: R grid r (n,) m, the fog of each cell
    ``[r_j, r_j + dr)`` sampled at its centre, ``h_j = pi beta xi exp(-2 alpha R') / R'^2`` (n,),
    and the pulse by lag ``i - j`` (m,), ``sin^2(pi s / (c tau_H))`` at ``s = (lag - 1/2) dr``.
    The midpoint rule makes the fog in front of a target at r_k exactly the cells j < k."""
    dr = TABLE_STEP
    r = np.arange(0.0, TABLE_MAX, dr)
    beta = BETA_PER_INV_MOR / visibility_of(alpha)
    rm = r + dr / 2
    h = np.pi * beta * overlap(rm) / rm**2 * np.exp(-2 * alpha * rm)
    width = C_LIGHT * TAU_H                                   # range extent of the pulse (m)
    lag = np.arange(int(np.ceil(width / dr)) + 1)
    pulse = np.where(lag > 0, np.sin(np.pi * np.clip((lag - 0.5) * dr / width, 0.0, 1.0)) ** 2, 0.0)
    return r, h, pulse


@functools.lru_cache(maxsize=16)
def _fog_echo(alpha: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(r, h, pulse) of :func:`_fog_cells` and the fog's own echo ``p_soft(R)`` (n,) on the grid,
    with no target in it: one discrete convolution of the pulse with the fog cells."""
    r, h, pulse = _fog_cells(alpha)
    return r, h, pulse, np.convolve(h, pulse)[: len(r)] * TABLE_STEP


def _cut_peaks(h: np.ndarray, pulse: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """For targets at the first ``k`` grid ranges: the strongest echo (k,) of the fog in front of
    each (cells j < k0) at waveform ranges past the target (i > k0), and its waveform index (k,).
    One cumulative sum over the cells of a (k + len(pulse), k) matrix."""
    rows = np.arange(k + len(pulse))[:, None]                 # waveform range index i
    cols = np.arange(k)[None, :]                              # fog cell j
    lag = rows - cols
    M = np.where(lag < len(pulse), pulse[np.clip(lag, 0, len(pulse) - 1)], 0.0) * h[:k]   # pulse[0] = 0
    cut = np.zeros((len(rows), k))
    cut[:, 1:] = np.cumsum(M, axis=1)[:, :-1] * TABLE_STEP    # cut[i, k0]: the echo at r_i of cells j < k0
    past = np.where(rows > cols, cut, -1.0)
    i_best = np.argmax(past, axis=0)
    return past[i_best, np.arange(k)], i_best


@functools.lru_cache(maxsize=16)
def fog_table(alpha: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(R0 grid (n,) m, strongest fog power ``max_R p_soft(R; R0)`` (n,) 1/m^2, its reported range
    (n,) m) for extinction ``alpha``, on a uniform grid from 0 (step TABLE_STEP).

    Up to R0 the cut at the target changes nothing, so the running maximum of the fog's own echo
    is a lower bound; past the fog's own peak nothing can exceed that peak, so it is the answer.
    For R0 short of the peak the waveform past R0 (fog in front of the target only) is checked
    exactly."""
    r, h, pulse, full = _fog_echo(alpha)
    arg = np.maximum.accumulate(np.where(full >= np.maximum.accumulate(full), np.arange(len(r)), 0))
    best = full[arg]
    k = int(np.argmax(full)) + 1
    cut_best, cut_arg = _cut_peaks(h, pulse, k)
    better = cut_best > best[:k]
    best[:k] = np.where(better, cut_best, best[:k])
    arg[:k] = np.where(better, cut_arg, arg[:k])
    # Reported range: the waveform peak less the hard echo's calibration offset c tau_H / 2.
    return r, best, np.maximum(r[np.minimum(arg, len(r) - 1)] - C_LIGHT * TAU_H / 2, 0.0)


@functools.lru_cache(maxsize=16)
def fog_peak_curvature(alpha: float) -> float:
    """``-p_soft''(R) / p_soft(R)`` (1/m^2) at the peak of the fog's own echo: how sharply it peaks
    (a sin^2 pulse of range width W gives 2 pi^2 / W^2). Central difference over +-PEAK_SPAN."""
    r, _, _, full = _fog_echo(alpha)
    i, k = int(np.argmax(full)), int(round(PEAK_SPAN / TABLE_STEP))
    return float((2 * full[i] - full[i + k] - full[max(i - k, 0)]) / (k * TABLE_STEP) ** 2 / full[i])


def fog_range_sigma(p_soft: np.ndarray, alpha: float) -> np.ndarray:
    """One sigma (m) of the range at which the receiver locates a fog peak of power ``p_soft`` (n,).

    A peak is located where the waveform's slope crosses zero; noise of slope sigma_s moves it by
    ``sigma_s / |P''|``. The same receiver locates a hard echo of power RANGE_SIGMA_POWER (curvature
    ``2 pi^2 / W^2`` times its power) to RANGE_SIGMA, which fixes sigma_s; the fog's broad, weak
    peak has far less curvature, so it is located far less precisely."""
    hard = 2 * np.pi**2 / (C_LIGHT * TAU_H) ** 2 * RANGE_SIGMA_POWER
    soft = fog_peak_curvature(alpha) * np.asarray(p_soft, np.float64)
    return np.divide(RANGE_SIGMA * hard, soft, out=np.zeros_like(soft), where=soft > 0)


def fog_returns(rho_cos: np.ndarray, range_m: np.ndarray, alpha: float, min_return: float) -> FogReturns:
    """The strongest-return bookkeeping of fog ``alpha`` for clean returns of reflectivity times
    cos(incidence) ``rho_cos`` (n,) at measured range ``range_m`` (n,) m; ``min_return`` is the
    clear-weather threshold (1/m^2)."""
    r, best, fog_r = fog_table(alpha)
    p_hard = rho_cos / range_m**2 * np.exp(-2 * alpha * range_m)
    idx = np.minimum(np.rint(range_m / TABLE_STEP).astype(np.int64), len(r) - 1)   # uniform grid from 0
    p_soft = best[idx]
    fog_wins = p_soft > p_hard
    sigma = np.where(fog_wins, fog_range_sigma(p_soft, alpha), 0.0)
    return FogReturns(p_hard, p_soft, fog_r[idx], sigma, fog_wins, np.maximum(p_hard, p_soft) >= min_return)


def fog_lidar(points: np.ndarray, rho_cos: np.ndarray, range_m: np.ndarray, dir_lidar: np.ndarray, alpha: float,
              min_return: float, ref_range: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Apply fog to one sweep.

    points : (n, >=5) float32 x, y, z, intensity, ring (lidar frame), then any columns carried
    along unchanged (e.g. a per-point label). rho_cos : (n,) reflectivity times cos(incidence).
    range_m : (n,) measured range. dir_lidar : (n, 3) unit ray directions. min_return :
    clear-weather detection threshold on ``p`` (1/m^2); ref_range : intensity scale (lidar.py).

    Returns (points (k, same columns), is_fog (k,) bool): the rows whose ray still reports a
    return, in order; hard ones attenuated in place, fog-won ones moved along their ray to where
    the receiver locates the fog's peak (its range plus the receiver's noise, kept between
    MIN_RANGE and the target) with the fog intensity (:func:`fog_returns` says which).
    """
    if alpha <= 0 or len(points) == 0:
        return points.copy(), np.zeros(len(points), bool)
    f = fog_returns(rho_cos, range_m, alpha, min_return)
    power = np.where(f.fog_wins, f.p_soft, f.p_hard)
    noise = rng.standard_normal(len(points))                    # drawn for all: a fixed stream
    located = np.clip(f.fog_range + f.range_sigma * noise, MIN_RANGE, range_m)
    new_range = np.where(f.fog_wins, located, range_m)
    out = points.copy()
    out[:, :3] = points[:, :3] - dir_lidar * (range_m - new_range)[:, None]
    out[:, 3] = np.round(255.0 * np.clip(power * ref_range**2, 0.0, 1.0))
    return out[f.kept].astype(np.float32), f.fog_wins[f.kept]


def hard_range_limit(rho_cos: float, alpha: float, min_return: float) -> float:
    """The farthest range (m, on the table grid) at which a target of ``rho_cos`` is still reported
    as itself in fog ``alpha``: its attenuated power reaches ``min_return`` and beats the fog's.
    (Its power falls with range and the fog's strongest power never does, so the set is an interval.)"""
    r = np.arange(0.0, TABLE_MAX, TABLE_STEP)
    p_fog = fog_table(alpha)[1] if alpha > 0 else np.zeros_like(r)
    with np.errstate(divide="ignore"):
        p = rho_cos / r**2 * np.exp(-2 * alpha * r)
    ok = (p >= min_return) & (p >= p_fog)
    return float(r[ok].max()) if ok.any() else 0.0


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
