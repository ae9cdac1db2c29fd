"""A camera pixel at night after the EMVA 1288 linear model: luminance -> electrons -> 8-bit value.

The chain, for one colour channel of one pixel (EMVA Standard 1288, release 4.0, "Linear camera
model"): the lens forms an image irradiance of ``E_img = pi tau L / (4 N^2)`` (lux, on axis, for a
scene luminance ``L`` in cd/m^2, a lens of f-number ``N`` and transmission ``tau``); the pixel of
area ``A`` collects ``E_img A t`` lux m^2 s, which at 555 nm is ``k = 1 / (683 lm/W * h c / 555 nm)
= 4.09e15`` photons per lux m^2 s; a share ``eta`` (the quantum efficiency) becomes
photo-electrons. The electrons are Poisson-distributed (shot noise); the readout adds a
Gaussian of ``sigma_d`` electrons (temporal dark noise); the analogue gain ``g`` and a 12-bit ADC
turn them into digital numbers, clipped at the full-well capacity divided by the gain. The
camera's tone curve (the sRGB transfer function, IEC 61966-2-1) then maps the linear value to 8
bits. Each colour channel is treated as a pixel of its own that sees the channel's luminance at
555 nm (the photons per lumen of white light are 1.5-2x more, and a Bayer filter passes about
half of them to its channel: the two factors are taken to cancel).

The camera is the nuScenes one (Basler acA1600-60gc, an e2v EV76C570 global-shutter CMOS of
4.5 um pixels, 1600 x 900 used). Its sensor figures are the typical ones for such a pixel: quantum
efficiency 0.6, saturation capacity 10 000 e-, temporal dark noise 3 e- rms; the lens f/2.0 with
a transmission of 0.9 (automotive lenses are f/1.6-2.4). Together: ``eta k pi tau / (4 N^2) A =
8.8e3`` e- per second per cd/m^2 (:meth:`Sensor.electrons_per_nit_second`).

Exposure. A camera's auto-exposure first lengthens the exposure, up to the longest a moving car
can afford without motion blur (20 ms here: 1 rad/s of relative motion, an object passing at 10 m
and 10 m/s, smears over 25 pixels of the front camera), then raises the analogue gain, up to its
maximum (16x, 24 dB). At night in a city it ends at both limits: the mean luminance of a night
frame (about 0.1-0.3 cd/m^2, measured on the rendered frames) is below the 18 % grey that it aims
for even at 20 ms and 16x (full scale 3.6 cd/m^2, so 18 % = 0.64 cd/m^2). :func:`night_exposure`
is that pinned exposure.

A rendered pixel that is coarser than the camera's (a render below 1600 x 900) stands for the
sum of ``b`` native pixels (:func:`binning`): ``b`` times the electrons, ``b`` times the read
noise's variance and the full well, so the noise of a low-resolution render is that of the
native image averaged down to it.

The clean image (no noise) is made where the scene is shaded (:func:`clean_image`); the noise is
added last, after the other weather's effects on the image (:func:`add_noise`), drawn from the
scene's ``night_camera`` generator only.
"""
from __future__ import annotations

import functools
from dataclasses import dataclass

import numba
import numpy as np

from ..rig import NATIVE_RESOLUTION

PHOTONS_PER_LUX_SECOND = 4.0907e15   # photons / (m^2 lux s) at 555 nm: 1 / (683 lm/W * h c / 555 nm)
SATURATED = 255                       # an 8-bit value at full scale: the signal may be anything above


@dataclass(frozen=True)
class Sensor:
    """One native pixel of the camera and its lens (units in the field comments)."""
    quantum_efficiency: float = 0.6      # electrons per photon
    full_well: float = 10_000.0          # e-, saturation capacity
    read_noise: float = 3.0              # e- rms, temporal dark noise
    adc_bits: int = 12
    pixel_pitch: float = 4.5e-6          # m
    f_number: float = 2.0
    lens_transmission: float = 0.9
    max_exposure: float = 0.020          # s, the motion-blur cap of the auto-exposure
    max_gain: float = 16.0               # analogue gain (24 dB)

    def electrons_per_nit_second(self) -> float:
        """Photo-electrons per second per cd/m^2 of scene luminance, one native pixel on axis."""
        image_lux_per_nit = np.pi * self.lens_transmission / (4.0 * self.f_number ** 2)
        return self.quantum_efficiency * PHOTONS_PER_LUX_SECOND * image_lux_per_nit * self.pixel_pitch ** 2

    @property
    def adc_max(self) -> int:
        return 2 ** self.adc_bits - 1


@dataclass(frozen=True)
class Exposure:
    time: float        # s
    gain: float        # analogue gain (1 = unity)


CAMERA = Sensor()


def night_exposure(sensor: Sensor = CAMERA) -> Exposure:
    """The auto-exposure's choice at night: the longest exposure and the highest gain."""
    return Exposure(sensor.max_exposure, sensor.max_gain)


def full_scale_luminance(sensor: Sensor, exposure: Exposure) -> float:
    """The luminance (cd/m^2) that fills the ADC at this exposure: ``full_well / (g k t)``."""
    return sensor.full_well / (exposure.gain * sensor.electrons_per_nit_second() * exposure.time)


def binning(resolution: tuple[int, int]) -> float:
    """Native (1600 x 900) pixels that one rendered pixel of ``resolution`` (W, H) stands for."""
    return NATIVE_RESOLUTION[0] * NATIVE_RESOLUTION[1] / float(resolution[0] * resolution[1])


def srgb_encode(linear: np.ndarray) -> np.ndarray:
    """The sRGB transfer function (IEC 61966-2-1): linear [0, 1] -> encoded [0, 1]."""
    x = np.clip(np.asarray(linear, np.float64), 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055)


def srgb_decode(encoded: np.ndarray) -> np.ndarray:
    """Its inverse: encoded [0, 1] -> linear [0, 1]."""
    v = np.asarray(encoded, np.float64)
    return np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4)


DECODE_8BIT = srgb_decode(np.arange(256) / 255.0)          # (256,) linear value of each 8-bit level
DECODE_8BIT.flags.writeable = False


@functools.lru_cache(maxsize=4)
def _encode_table(adc_bits: int) -> np.ndarray:
    """(2^bits,) uint8: the tone curve applied to each raw ADC level."""
    levels = 2 ** adc_bits
    table = np.round(255.0 * srgb_encode(np.arange(levels) / (levels - 1))).astype(np.uint8)
    table.flags.writeable = False
    return table


def clean_image(luminance: np.ndarray, sensor: Sensor = CAMERA, exposure: Exposure | None = None) -> np.ndarray:
    """The noise-free camera image of a scene: luminance (H, W, 3) float, cd/m^2 per colour channel
    -> (H, W, 3) uint8, its share of the full scale at ``exposure`` (the night one by default)
    through the tone curve, looked up at 16 bits (within a level of the exact curve; a 16-bit
    step is 0.03 of a level where the curve is steepest). At or above full scale: 255."""
    exposure = exposure or night_exposure(sensor)
    levels = np.float32((2 ** 16 - 1) / full_scale_luminance(sensor, exposure))
    index = np.minimum(np.asarray(luminance, np.float32) * levels + np.float32(0.5), np.float32(2 ** 16 - 1))
    return np.take(_encode_table(16), index.astype(np.int32))


def add_noise(rgb: np.ndarray, bins: float, rng: np.random.Generator, sensor: Sensor = CAMERA,
              gain: float | None = None) -> np.ndarray:
    """The image a real pixel delivers for the clean image ``rgb`` (H, W, 3) uint8: each value read
    back to its electrons at ``gain`` (the night's maximum by default) for ``bins`` native pixels
    per rendered pixel, then shot noise (Poisson), read noise (Gaussian, ``sqrt(bins)`` sigma_d),
    the 12-bit ADC (rounded, clipped to [0, full scale]) and the tone curve. A saturated value
    (255) stays 255: what it shows may be any brighter. Draws the Poisson image, then the
    Gaussian one (standard normals, float32), from ``rng``. Returns (H, W, 3) uint8."""
    gain = sensor.max_gain if gain is None else gain
    full_scale_e = bins * sensor.full_well / gain                 # electrons of the ADC's full scale
    electrons = rng.poisson(np.take(DECODE_8BIT * full_scale_e, rgb))
    read = rng.standard_normal(rgb.shape, dtype=np.float32)
    dn_per_e = sensor.adc_max / full_scale_e
    return _digitise(electrons, read, np.sqrt(bins) * sensor.read_noise * dn_per_e, dn_per_e, sensor.adc_max,
                     _encode_table(sensor.adc_bits), rgb)


@numba.njit(cache=True, nogil=True)
def _digitise(electrons, read, read_dn, dn_per_e, adc_max, table, rgb):
    """The ADC and the tone curve, in one pass: ``electrons`` (H, W, 3) int64 plus ``read`` (H, W, 3)
    float32 standard normals times ``read_dn`` (the read noise in ADC levels), to the nearest level
    in [0, adc_max], through ``table`` to uint8; where ``rgb`` was saturated, 255."""
    out = np.empty(rgb.shape, np.uint8)
    e, r, c, o = electrons.ravel(), read.ravel(), rgb.ravel(), out.ravel()
    for i in range(o.size):
        dn = np.rint(e[i] * dn_per_e + r[i] * read_dn)
        o[i] = SATURATED if c[i] == SATURATED else table[int(min(max(dn, 0.0), adc_max))]
    return out


def temporal_snr(mean_e: np.ndarray, bins: float, sensor: Sensor = CAMERA) -> np.ndarray:
    """The model's signal-to-noise ratio of a pixel holding ``mean_e`` electrons (per native
    pixel) summed over ``bins`` native pixels: ``b mu / sqrt(b mu + b sigma_d^2)`` (EMVA 1288
    eq. 15, quantisation left out). For the measurements; :func:`add_noise` draws it."""
    mu = np.asarray(mean_e, np.float64) * bins
    return mu / np.sqrt(mu + bins * sensor.read_noise ** 2)
