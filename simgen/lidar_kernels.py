"""Compiled per-ray kernels of the lidar sweep (numba).

After Embree's query, what is left of a sweep is short arithmetic per ray: the hit distance on
the reported triangle's plane, the move into each actor's box frame, and the noise, detection
threshold and frame change of every return. In numpy that is many passes over the rays, each
allocating an array, which together cost more than the query. Here each is one loop, compiled
with numba (``cache=True``: compiled once per checkout, then loaded), that reads the inputs once
and writes the outputs once. ``nogil=True``, so the scanner's threads run them in parallel on ray chunks.

Plain IEEE arithmetic in a fixed order (no ``fastmath``): the same inputs give the same bytes.
``error_model="numpy"``: a division by zero gives inf or nan, as in numpy, instead of raising.
"""
from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True, nogil=True, error_model="numpy")
def plane_hits(tri, origins, dirs, normals, plane, tfar):
    """Exact hit distance and |cos| of incidence on each ray's reported triangle.

    tri : (m,) int64 triangle per ray, -1 for a miss; a hit beyond ``tfar`` becomes a miss
    (written back into ``tri``).  origins, dirs : (m, 3) float64, unit directions.
    normals : (f, 3) unit face normals.  plane : (f,) n . v0 per face.  tfar : (m,), or (0,)
    for no limit.  Returns dist (m,) (inf for a miss) and |cos| (m,) (0 for a miss).
    """
    m = tri.shape[0]
    dist = np.empty(m)
    cos = np.empty(m)
    limit = tfar.shape[0] > 0
    for i in range(m):
        f = tri[i]
        d = np.inf
        c = 0.0
        if f >= 0:
            nx, ny, nz = normals[f, 0], normals[f, 1], normals[f, 2]
            c = dirs[i, 0] * nx + dirs[i, 1] * ny + dirs[i, 2] * nz
            d = (plane[f] - (origins[i, 0] * nx + origins[i, 1] * ny + origins[i, 2] * nz)) / c
            if limit and d > tfar[i]:
                tri[i] = -1
                d = np.inf
                c = 0.0
        dist[i] = d
        cos[i] = abs(c)
    return dist, cos


@numba.njit(cache=True, nogil=True, error_model="numpy")
def into_box_frames(rays, owner, origin, dirs, centre, cos_yaw, sin_yaw, offset):
    """Rays moved into their actor's box frame (rotation about z by -yaw), then to its atlas copy.

    rays, owner : (c,) ray index and actor index per candidate.  origin, dirs : (m, 3) global.
    centre : (k, 3) box centres.  cos_yaw, sin_yaw : (k,).  offset : (k, 3) atlas offsets.
    Returns local origins and directions, (c, 3) each.
    """
    n = rays.shape[0]
    o_local = np.empty((n, 3))
    d_local = np.empty((n, 3))
    for i in range(n):
        r, j = rays[i], owner[i]
        c, s = cos_yaw[j], sin_yaw[j]
        ox, oy = origin[r, 0] - centre[j, 0], origin[r, 1] - centre[j, 1]
        o_local[i, 0] = c * ox + s * oy + offset[j, 0]
        o_local[i, 1] = c * oy - s * ox + offset[j, 1]
        o_local[i, 2] = origin[r, 2] - centre[j, 2] + offset[j, 2]
        dx, dy = dirs[r, 0], dirs[r, 1]
        d_local[i, 0] = c * dx + s * dy
        d_local[i, 1] = c * dy - s * dx
        d_local[i, 2] = dirs[r, 2]
    return o_local, d_local


@numba.njit(cache=True, nogil=True, error_model="numpy")
def sweep_rays(origin_col, yaw, dir_ego, n_beams):
    """Per-ray origins and directions (m, 3), global frame, from per-column sensor origins
    (n_az, 3) and ego yaws (n_az,) and the pattern's ego-frame directions (m, 3)."""
    m = dir_ego.shape[0]
    origin = np.empty((m, 3))
    dirs = np.empty((m, 3))
    for col in range(origin_col.shape[0]):
        c, s = np.cos(yaw[col]), np.sin(yaw[col])
        for i in range(col * n_beams, (col + 1) * n_beams):
            origin[i, 0] = origin_col[col, 0]
            origin[i, 1] = origin_col[col, 1]
            origin[i, 2] = origin_col[col, 2]
            dirs[i, 0] = c * dir_ego[i, 0] - s * dir_ego[i, 1]
            dirs[i, 1] = s * dir_ego[i, 0] + c * dir_ego[i, 1]
            dirs[i, 2] = dir_ego[i, 2]
    return origin, dirs


@numba.njit(cache=True, nogil=True, error_model="numpy")
def returns(first, dist, noise, rho, cos_inc, ids, labels, dirs, ring, t_col, origin_lidar, R_lidar_from_global,
            min_range, max_range, min_return, ref_range, n_beams):
    """The returns a sweep's rays give: measured range, detection threshold, sensor frame.

    Rays ``first .. first + len(dist)`` of the sweep; ``dist``, ``noise``, ``rho``, ``cos_inc``,
    ``ids``, ``labels`` are their slices, ``dirs``, ``ring`` the whole sweep's. A ray returns when its
    measured range (``dist + noise``) lies in [min_range, max_range] and its power
    ``rho cos / range^2`` reaches ``min_return``. origin_lidar : (n_az, 3) each column's origin
    in the lidar frame at the sweep's end; the point is ``origin_lidar[col] + (R dir) range``.

    Returns, per return: (k, 5) float32 points (x, y, z, intensity 0..255, ring), firing time,
    actor id, rho, |cos|, measured range (k,), (k, 3) unit directions in the lidar frame and the
    lidarseg label (k,).
    """
    n = dist.shape[0]
    keep = np.empty(n, np.int64)
    meas = np.empty(n)
    power = np.empty(n)
    k = 0
    for i in range(n):
        r = dist[i] + noise[i]
        if r >= min_range and r <= max_range:
            p = rho[i] * cos_inc[i] / r ** 2
            if p >= min_return:
                keep[k] = first + i
                meas[k] = r
                power[k] = p
                k += 1
    pts = np.empty((k, 5), np.float32)
    dir_lidar = np.empty((k, 3))
    t = np.empty(k)
    ids_k = np.empty(k, ids.dtype)
    rho_k = np.empty(k, rho.dtype)
    cos_k = np.empty(k)
    labels_k = np.empty(k, labels.dtype)
    ref2 = ref_range ** 2
    for j in range(k):
        i = keep[j]
        col = i // n_beams
        for a in range(3):
            v = (R_lidar_from_global[a, 0] * dirs[i, 0] + R_lidar_from_global[a, 1] * dirs[i, 1]
                 + R_lidar_from_global[a, 2] * dirs[i, 2])
            dir_lidar[j, a] = v
            pts[j, a] = origin_lidar[col, a] + v * meas[j]
        pts[j, 3] = np.round(255.0 * min(max(power[j] * ref2, 0.0), 1.0))
        pts[j, 4] = ring[i]
        t[j] = t_col[col]
        ids_k[j] = ids[i - first]
        rho_k[j] = rho[i - first]
        cos_k[j] = cos_inc[i - first]
        labels_k[j] = labels[i - first]
    return pts, t, ids_k, rho_k, cos_k, meas[:k], dir_lidar, labels_k
