"""The sun: its direction, shared by every renderer, and the shadows it casts in the pyrender cameras.

Shadows come from a shadow map. After a camera's id pass, the visible points whose face turns
toward the sun (the receivers) are bounded in the *sun frame* (z toward the sun, x along the
camera's forward axis projected across the sun's direction, y = z x x). An orthographic depth pass
looks down -z over exactly that x-y rectangle (:class:`SunView`), so its texels go where the
camera looks; the map holds only what can cast a shadow (the caller leaves out the ground). A
receiver is in shadow when the map holds a surface more than a bias above it along z; its pixel
then takes its face's ambient colour (the sun term of the shading removed). Faces turned away
from the sun are ambient-only already and are not tested.

The bias covers what the two depth buffers cannot resolve: a texel's reach along the receiver's
slope (``tan`` of the angle between its normal and the sun), the camera depth buffer's step,
which grows with the square of the distance, and a floor. A shadow on a wall or a roof therefore
starts up to a texel or two away from where its caster meets it.

The per-pixel work is compiled with numba (``cache=True``, plain IEEE arithmetic, no fastmath:
the same inputs give the same bytes), one loop that reads each input once.
"""
from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

DEFAULT_AZIMUTH = 0.8       # rad, from global x toward y; a world that records none gets these
DEFAULT_ELEVATION = 0.9     # rad above the horizon
MAX_TAN = 10.0              # slope factor cap: a face this grazing gets little sun anyway
BIAS_FLOOR = 0.02           # metres: the depth buffers' rounding near the camera


def sun_direction(meta: dict) -> np.ndarray:
    """(3,) unit vector toward the sun, global frame, from a world's ``sun_azimuth`` and
    ``sun_elevation`` (rad). Light travels along its negative."""
    az = float(meta.get("sun_azimuth", DEFAULT_AZIMUTH))
    el = float(meta.get("sun_elevation", DEFAULT_ELEVATION))
    return np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])


def R_sun_from_global(sun: np.ndarray, forward: np.ndarray) -> np.ndarray:
    """(3, 3) rotation into the sun frame: z = ``sun``, x = ``forward`` (global) made
    perpendicular to it (global x when the two are parallel), y = z x x."""
    z = sun / np.linalg.norm(sun)
    x = forward - z * (forward @ z)
    if np.linalg.norm(x) < 1e-6:
        x = np.array([1.0, 0.0, 0.0]) - z * z[0]
    x = x / np.linalg.norm(x)
    return np.stack([x, np.cross(z, x), z])


def slope_tan(cos_sun: np.ndarray) -> np.ndarray:
    """(F,) float32 per face: tan of the angle between its normal and the sun, capped at
    ``MAX_TAN``; -1 for a face turned away (cos <= 0), which is never tested."""
    c = np.asarray(cos_sun, np.float64)
    tan = np.sqrt(np.clip(1.0 - c * c, 0.0, None)) / np.maximum(c, 1e-12)
    return np.where(c > 0, np.minimum(tan, MAX_TAN), -1.0).astype(np.float32)


@dataclass(frozen=True)
class SunView:
    """The orthographic shadow camera over the receivers' x-y rectangle in the sun frame.

    ``centre`` (x, y), half sizes ``xmag``, ``ymag`` (m); the camera sits at sun-frame height
    ``top`` looking down -z, with window depth d in [0, 1] at height ``top - znear - d (zfar - znear)``.
    """
    R_sun_from_global: np.ndarray
    centre: tuple[float, float]
    xmag: float
    ymag: float
    top: float
    znear: float
    zfar: float

    @property
    def T_global_from_view(self) -> np.ndarray:
        """(4, 4) pose of the shadow camera in OpenGL axes (x right, y up, looking along -z)."""
        T = np.eye(4)
        T[:3, :3] = self.R_sun_from_global.T
        T[:3, 3] = self.R_sun_from_global.T @ np.array([self.centre[0], self.centre[1], self.top])
        return T

    def params(self, size: tuple[int, int]) -> np.ndarray:
        """(7,) float64 for :func:`shade`: left x, top y, texel width and height (m) of a map of
        ``size`` (W, H), the camera height, znear and zfar."""
        W, H = size
        return np.array([self.centre[0] - self.xmag, self.centre[1] + self.ymag, 2 * self.xmag / W,
                         2 * self.ymag / H, self.top, self.znear, self.zfar])


def fit_view(R: np.ndarray, lo: np.ndarray, hi: np.ndarray, caster_top: float, size: tuple[int, int]) -> SunView:
    """A :class:`SunView` over the sun-frame box ``lo``..``hi`` (3,) of the receivers, its camera
    above ``caster_top`` (the highest sun-frame z of anything drawn into it), for a map of
    ``size`` (W, H). pyrender gives an orthographic camera the viewport's aspect (xmag = W / H
    ymag), so the texels are square and the shorter side of the box gets the slack."""
    W, H = size
    margin = 0.05 + 0.005 * float(np.max(hi[:2] - lo[:2]))      # keeps edge receivers off the border
    ymag = max(float(hi[1] - lo[1]) / 2 + margin, (float(hi[0] - lo[0]) / 2 + margin) * H / W, 0.5)
    xmag = ymag * W / H
    top = max(float(caster_top), float(hi[2])) + 1.0
    return SunView(R, (float(lo[0] + hi[0]) / 2, float(lo[1] + hi[1]) / 2), xmag, ymag, top,
                   znear=0.5, zfar=top - float(lo[2]) + 1.0)


def over_rectangle(centre: np.ndarray, radius: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Indices of the spheres, (n, 3) sun-frame ``centre`` and (n,) ``radius``, that reach over
    the x-y rectangle of the box ``lo``..``hi``: what may cast a shadow into it."""
    mid, half = (lo[:2] + hi[:2]) / 2, (hi[:2] - lo[:2]) / 2
    return np.flatnonzero(np.all(np.abs(centre[:, :2] - mid) <= half + radius[:, None], axis=1))


@numba.njit(cache=True, nogil=True, error_model="numpy")
def receiver_bounds(face, depth, tan, K4, R_sun_from_cam, t_sun, stride):
    """Sun-frame bounds of the receivers: pixels with depth > 0 whose face has ``tan`` >= 0,
    every ``stride``-th row and column (the map's margin covers the pixels between, but for far
    grazing ones, which then stay lit).

    face : (H, W) uint32 face index.  depth : (H, W) float32 camera z (m), 0 = nothing.
    tan : (F,) float32 from :func:`slope_tan`.  K4 : (4,) fx, fy, cx, cy.
    R_sun_from_cam : (3, 3), t_sun : (3,) camera centre in the sun frame.
    Returns lo (3,), hi (3,) and the number of receivers seen (lo > hi when none).
    """
    H, W = face.shape
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    count = 0
    for v in range(0, H, stride):
        vn = (v + 0.5 - K4[3]) / K4[1]
        for u in range(0, W, stride):
            z = depth[v, u]
            if z <= 0 or tan[face[v, u]] < 0:
                continue
            un = (u + 0.5 - K4[2]) / K4[0]
            count += 1
            for k in range(3):
                p = z * (R_sun_from_cam[k, 0] * un + R_sun_from_cam[k, 1] * vn + R_sun_from_cam[k, 2]) + t_sun[k]
                lo[k] = min(lo[k], p)
                hi[k] = max(hi[k], p)
    return lo, hi, count


@numba.njit(cache=True, nogil=True, error_model="numpy")
def shade(face, depth, lit_rgbx, ambient_rgbx, tan, K4, R_sun_from_cam, t_sun, sun_map, view, depth_step):
    """The rgb image: each pixel's lit face colour, or its ambient one where shadowed.

    face, depth, tan, K4, R_sun_from_cam, t_sun : as in :func:`receiver_bounds`.
    lit_rgbx, ambient_rgbx : (F,) uint32 colours, r | g << 8 | b << 16.
    sun_map : (Hm, Wm) float32 window depth of the shadow camera, top row first (1 = nothing).
    view : (7,) from :meth:`SunView.params`.  depth_step : camera depth buffer step per z^2 (1/m).
    Returns (H, W, 3) uint8.
    """
    H, W = face.shape
    Hm, Wm = sun_map.shape
    x0, y0, sx, sy, top, znear, zfar = view[0], view[1], view[2], view[3], view[4], view[5], view[6]
    texel = max(sx, sy)
    R = R_sun_from_cam
    rgb = np.empty((H, W, 3), np.uint8)
    for v in range(H):
        vn = (v + 0.5 - K4[3]) / K4[1]
        # The sun-frame ray of pixel (u, v) is a + u * b: its row's part, then per column.
        ax = R[0, 0] * (0.5 - K4[2]) / K4[0] + R[0, 1] * vn + R[0, 2]
        ay = R[1, 0] * (0.5 - K4[2]) / K4[0] + R[1, 1] * vn + R[1, 2]
        az = R[2, 0] * (0.5 - K4[2]) / K4[0] + R[2, 1] * vn + R[2, 2]
        bx, by, bz = R[0, 0] / K4[0], R[1, 0] / K4[0], R[2, 0] / K4[0]
        for u in range(W):
            f = face[v, u]
            colour = lit_rgbx[f]
            z = depth[v, u]
            if z > 0 and tan[f] >= 0:
                fi = (z * (ax + u * bx) + t_sun[0] - x0) / sx
                fj = (y0 - z * (ay + u * by) - t_sun[1]) / sy
                if 0 <= fi < Wm and 0 <= fj < Hm:
                    d = sun_map[int(fj), int(fi)]
                    if d < 1.0:
                        pz = z * (az + u * bz) + t_sun[2]
                        occluder = top - znear - d * (zfar - znear)
                        if occluder > pz + BIAS_FLOOR + tan[f] * texel + depth_step * z * z:
                            colour = ambient_rgbx[f]
            rgb[v, u, 0] = colour & 255
            rgb[v, u, 1] = (colour >> 8) & 255
            rgb[v, u, 2] = (colour >> 16) & 255
    return rgb
