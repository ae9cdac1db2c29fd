"""The night's per-pixel shading: each pixel's luminance from the ambient and the lights
(simgen/weather/night.py), in tiles that each shade with only the lights that can reach them.

A pixel's surface point is its camera ray at its depth; its irradiance is the ambient plus, per
light, ``I(direction) cos(theta) / r^2`` (lux); its luminance ``albedo E / pi`` plus its own
emission (cd/m^2 per colour channel). Where nothing was hit it is the night sky's.

Cost: lights x pixels, bounded by the lights a camera uses (night.MAX_STREET_LIGHTS +
night.MAX_VEHICLE_LAMPS). Most of those light only part of the view: a street light nothing
beyond 40 m, a head lamp nothing behind it. The image is therefore shaded in tiles of
``TILE`` x ``TILE`` pixels: a first pass bounds each tile's surface points by a box, and the tile
keeps the lights whose sphere of influence meets the box and, for a head lamp, part of whose box
lies ahead of it; the second pass shades the tile's pixels with those alone (tiled deferred
shading). The result is the same as with every light, bit for bit: a culled light adds exactly
0 to each of the tile's pixels.

Compiled with numba like the sun's shadows (simgen/sun.py): plain IEEE arithmetic, no fastmath,
so the same inputs give the same bytes.
"""
from __future__ import annotations

import numba
import numpy as np

from .night import (AMBIENT_LUX, HEAD, LAMP_RADIUS, NEUTRAL, SKY_LUMINANCE, STREET, WARM_WHITE, FaceTables, Lights,
                    headlamp_intensity, street_intensity)

TILE = 16          # pixels


def shade(face: np.ndarray, depth: np.ndarray, K: np.ndarray, T_global_from_cam: np.ndarray,
          tables: FaceTables, lights: Lights) -> np.ndarray:
    """(H, W, 3) float32 luminance (cd/m^2 per channel) of a camera's id pass: ``face`` (H, W)
    uint32 face index, ``depth`` (H, W) float32 camera z (m, 0 = sky), ``K`` (3, 3),
    T_global_from_cam (4, 4), lit by the ambient and ``lights`` (those the camera uses), with the
    street luminaires drawn where they are in view."""
    K4 = np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2]])
    discs = luminaire_discs(lights, K, T_global_from_cam)
    return _luminance(face, depth, K4, np.ascontiguousarray(T_global_from_cam[:3, :3]),
                      np.ascontiguousarray(T_global_from_cam[:3, 3]), tables.albedo, tables.normal, tables.emit,
                      AMBIENT_LUX * NEUTRAL, SKY_LUMINANCE * WARM_WHITE, lights.pos, lights.forward, lights.left,
                      lights.kind, lights.colour, lights.reach ** 2, lights.footprint, discs)


def luminaire_discs(lights: Lights, K: np.ndarray, T_global_from_cam: np.ndarray) -> np.ndarray:
    """(m, 7) float64 per street luminaire in front of the camera: its image centre u, v (px), the
    disc's radius (px, at least 0.7 so that a far one still covers a pixel), its camera z (m) and
    its luminance (cd/m^2, 3 channels) toward the camera, ``I(gamma) / (pi r^2 cos gamma)`` for a
    downward disc of radius ``LAMP_RADIUS`` seen at ``gamma`` from below."""
    lamps = lights.take(np.flatnonzero(lights.kind == STREET))
    p_cam = (lamps.pos - T_global_from_cam[:3, 3]) @ T_global_from_cam[:3, :3]
    to_cam = T_global_from_cam[:3, 3] - lamps.pos
    to_cam /= np.linalg.norm(to_cam, axis=1, keepdims=True)
    cos_gamma = -to_cam[:, 2]
    front = (p_cam[:, 2] > 0.5) & (cos_gamma > 0.01)
    lamps, p_cam, to_cam, cos_gamma = lamps.take(np.flatnonzero(front)), p_cam[front], to_cam[front], cos_gamma[front]
    uv = p_cam[:, :2] / p_cam[:, 2:] * [K[0, 0], K[1, 1]] + [K[0, 2], K[1, 2]]
    radius = np.maximum(0.7, K[0, 0] * LAMP_RADIUS / p_cam[:, 2])
    intensity = np.array([street_intensity(w @ f, w @ l, w[2], *fp)          # a few dozen lamps
                          for w, f, l, fp in zip(to_cam, lamps.forward, lamps.left, lamps.footprint)])
    lum = (intensity / (np.pi * LAMP_RADIUS ** 2 * cos_gamma))[:, None] * lamps.colour
    return np.concatenate([uv, radius[:, None], p_cam[:, 2:], lum], 1).reshape(-1, 7)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _tile_bounds(face, depth, K4, R, t, v0, v1, u0, u1, lo, hi):
    """The box ``lo``..``hi`` (3,) of the global surface points of pixels [v0, v1) x [u0, u1);
    returns whether it holds any (sky pixels hold none)."""
    found = False
    for k in range(3):
        lo[k], hi[k] = np.inf, -np.inf
    for v in range(v0, v1):
        vn = (v + 0.5 - K4[3]) / K4[1]
        for u in range(u0, u1):
            z = depth[v, u]
            if face[v, u] == 0 or z <= 0.0:
                continue
            found = True
            un = (u + 0.5 - K4[2]) / K4[0]
            for k in range(3):
                p = t[k] + z * (R[k, 0] * un + R[k, 1] * vn + R[k, 2])
                lo[k] = min(lo[k], p)
                hi[k] = max(hi[k], p)
    return found


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _tile_lights(lo, hi, pos, forward, kind, reach2, keep):
    """Write into ``keep`` the indices of the lights that can reach the box ``lo``..``hi``: its
    nearest point within the light's reach and, for a head lamp, some corner ahead of it (x > 0
    in its beam frame). Returns how many."""
    m = 0
    for i in range(pos.shape[0]):
        d2 = 0.0
        ahead = 0.0
        for k in range(3):
            gap = max(lo[k] - pos[i, k], 0.0, pos[i, k] - hi[k])
            d2 += gap * gap
            ahead += max((lo[k] - pos[i, k]) * forward[i, k], (hi[k] - pos[i, k]) * forward[i, k])
        if d2 > reach2[i] or (kind[i] == HEAD and ahead <= 0.0):
            continue
        keep[m] = i
        m += 1
    return m


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _tile_discs(discs, v0, v1, u0, u1, keep):
    """Write into ``keep`` the indices of the luminaire discs that overlap pixels [v0, v1) x
    [u0, u1). Returns how many."""
    m = 0
    for j in range(discs.shape[0]):
        u, v, radius = discs[j, 0], discs[j, 1], discs[j, 2]
        if u + radius >= u0 and u - radius <= u1 and v + radius >= v0 and v - radius <= v1:
            keep[m] = j
            m += 1
    return m


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _luminance(face, depth, K4, R, t, albedo, normal, emit, ambient, sky, pos, forward, left, kind, colour, reach2,
               footprint, discs):
    """The per-pixel work of :func:`shade`, tile by tile: the lights and discs that reach the
    tile, then its pixels (:func:`_shade_tile`)."""
    H, W = face.shape
    out = np.empty((H, W, 3), np.float32)
    keep, keep_discs = np.empty(pos.shape[0], np.int64), np.empty(discs.shape[0], np.int64)
    lo, hi = np.empty(3), np.empty(3)
    for v0 in range(0, H, TILE):
        v1 = min(v0 + TILE, H)
        for u0 in range(0, W, TILE):
            u1 = min(u0 + TILE, W)
            m = 0
            if _tile_bounds(face, depth, K4, R, t, v0, v1, u0, u1, lo, hi):
                m = _tile_lights(lo, hi, pos, forward, kind, reach2, keep)
            n_discs = _tile_discs(discs, v0, v1, u0, u1, keep_discs)
            _shade_tile(face, depth, K4, R, t, albedo, normal, emit, ambient, sky, pos, forward, left, kind, colour,
                        reach2, footprint, discs, v0, v1, u0, u1, keep, m, keep_discs, n_discs, out)
    return out


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _shade_tile(face, depth, K4, R, t, albedo, normal, emit, ambient, sky, pos, forward, left, kind, colour, reach2,
                footprint, discs, v0, v1, u0, u1, keep, m, keep_discs, n_discs, out):
    """Shade pixels [v0, v1) x [u0, u1) into ``out`` with the lights ``keep[:m]`` and the discs
    ``keep_discs[:n_discs]``: each pixel's surface point from its depth, ``albedo E / pi`` plus its
    emission, or the sky's luminance; then a luminaire's disc where nothing nearer hides it."""
    for v in range(v0, v1):
        vn = (v + 0.5 - K4[3]) / K4[1]
        for u in range(u0, u1):
            f = face[v, u]
            z = depth[v, u]
            sky_pixel = f == 0 or z <= 0.0
            if sky_pixel:
                lum0, lum1, lum2 = sky[0], sky[1], sky[2]
            else:
                # The surface point p and its normal n; its irradiance e from the ambient and
                # each light: I cos / r^2. (Written out here: a per-pixel call that takes
                # arrays would count references on each of them.)
                un = (u + 0.5 - K4[2]) / K4[0]
                px = t[0] + z * (R[0, 0] * un + R[0, 1] * vn + R[0, 2])
                py = t[1] + z * (R[1, 0] * un + R[1, 1] * vn + R[1, 2])
                pz = t[2] + z * (R[2, 0] * un + R[2, 1] * vn + R[2, 2])
                nx, ny, nz = normal[f, 0], normal[f, 1], normal[f, 2]
                e0, e1, e2 = ambient[0], ambient[1], ambient[2]
                for jj in range(m):
                    i = keep[jj]
                    dx, dy, dz = pos[i, 0] - px, pos[i, 1] - py, pos[i, 2] - pz
                    r2 = dx * dx + dy * dy + dz * dz
                    facing = nx * dx + ny * dy + nz * dz
                    if r2 > reach2[i] or r2 < 1e-6 or facing <= 0.0:       # out of reach, or turned away
                        continue
                    r = np.sqrt(r2)
                    # The unit direction from the light to the point, in the light's frame.
                    wx = -(dx * forward[i, 0] + dy * forward[i, 1] + dz * forward[i, 2]) / r
                    wy = -(dx * left[i, 0] + dy * left[i, 1] + dz * left[i, 2]) / r
                    if kind[i] == STREET:
                        intensity = street_intensity(wx, wy, -dz / r, footprint[i, 0], footprint[i, 1], footprint[i, 2])
                    else:
                        intensity = headlamp_intensity(wx, wy, -dz / r)
                    k = intensity * facing / (r * r2)                        # I cos / r^2
                    e0 += k * colour[i, 0]
                    e1 += k * colour[i, 1]
                    e2 += k * colour[i, 2]
                lum0 = albedo[f, 0] * e0 / np.pi + emit[f, 0]
                lum1 = albedo[f, 1] * e1 / np.pi + emit[f, 1]
                lum2 = albedo[f, 2] * e2 / np.pi + emit[f, 2]
            for jj in range(n_discs):
                j = keep_discs[jj]
                du, dv = u + 0.5 - discs[j, 0], v + 0.5 - discs[j, 1]
                if du * du + dv * dv <= discs[j, 2] * discs[j, 2] and (sky_pixel or z > discs[j, 3]):
                    lum0 += discs[j, 4]
                    lum1 += discs[j, 5]
                    lum2 += discs[j, 6]
            out[v, u, 0] = lum0
            out[v, u, 1] = lum1
            out[v, u, 2] = lum2
