"""numba kernels of the photo-consistency method (:mod:`organlab.coloring._photo`).

Rays are given per pixel (origin shared, unit directions, world frame, mm);
the occupancy is a ``uint8`` grid whose voxel ``(i, j, k)`` has its centre at
``origin + (i, j, k) * h``.  Cameras are packed by organlab.nbcam.pack_camera.
"""

from __future__ import annotations

import numba as nb
import numpy as np

from ..nbcam import to_camera, to_pixel


@nb.njit(cache=True, nogil=True)
def _box_span(o, d, lo, hi):
    """Ray parameters ``(t0, t1)`` of a ray inside the box ``[lo, hi]`` (t1 < t0: a miss)."""
    t0, t1 = 0.0, 1e30
    for a in range(3):
        if abs(d[a]) < 1e-12:
            if o[a] < lo[a] or o[a] > hi[a]:
                return 1.0, 0.0
            continue
        ta = (lo[a] - o[a]) / d[a]
        tb = (hi[a] - o[a]) / d[a]
        if ta > tb:
            ta, tb = tb, ta
        t0 = max(t0, ta)
        t1 = min(t1, tb)
    return t0, t1


@nb.njit(cache=True, nogil=True)
def _occupied(occ, origin, h, x, y, z):
    i = int(np.floor((x - origin[0]) / h + 0.5))
    j = int(np.floor((y - origin[1]) / h + 0.5))
    k = int(np.floor((z - origin[2]) / h + 0.5))
    if i < 0 or j < 0 or k < 0 or i >= occ.shape[0] or j >= occ.shape[1] or k >= occ.shape[2]:
        return False
    return occ[i, j, k] != 0


@nb.njit(cache=True, nogil=True, parallel=True)
def surface_depth(o, dirs, occ, origin, h, lo, hi, step):
    """Distance along each ray to the first occupied voxel (NaN: none), marched at ``step`` mm then bisected."""
    n = dirs.shape[0]
    out = np.full(n, np.nan)
    for p in nb.prange(n):
        d = dirs[p]
        t0, t1 = _box_span(o, d, lo, hi)
        if t1 < t0:
            continue
        t = t0
        prev = t0
        while t <= t1:
            if _occupied(occ, origin, h, o[0] + t * d[0], o[1] + t * d[1], o[2] + t * d[2]):
                a, b = prev, t
                for _ in range(6):
                    m = 0.5 * (a + b)
                    if _occupied(occ, origin, h, o[0] + m * d[0], o[1] + m * d[1], o[2] + m * d[2]):
                        b = m
                    else:
                        a = m
                out[p] = b
                break
            prev = t
            t += step
    return out


@nb.njit(cache=True, nogil=True)
def _bilinear(img, u, v):
    H, W = img.shape
    x0 = int(np.floor(u))
    y0 = int(np.floor(v))
    if x0 < 0 or y0 < 0 or x0 + 1 >= W or y0 + 1 >= H:
        return np.nan
    fx = u - x0
    fy = v - y0
    a = img[y0, x0] * (1 - fx) + img[y0, x0 + 1] * fx
    b = img[y0 + 1, x0] * (1 - fx) + img[y0 + 1, x0 + 1] * fx
    return a * (1 - fy) + b * fy


@nb.njit(cache=True, nogil=True, parallel=True)
def warp_samples(o, dirs, t_surf, dt, n_steps, cams, grey, fg, out):
    """Neighbour grey levels at the points ``t_surf + s * dt`` (s < n_steps) of every ray.

    ``out`` is ``(J, n_steps, n)`` float32, NaN where the point projects
    outside view ``j``'s image or silhouette (``fg`` 1 = specimen).
    """
    n = dirs.shape[0]
    J = cams.shape[0]
    for p in nb.prange(n):
        d = dirs[p]
        t0 = t_surf[p]
        for s in range(n_steps):
            t = t0 + s * dt
            x = o[0] + t * d[0]
            y = o[1] + t * d[1]
            z = o[2] + t * d[2]
            for j in range(J):
                val = np.nan
                if t0 == t0:
                    xc, yc, zc = to_camera(cams[j], x, y, z)
                    if zc > 0.0:
                        u, v = to_pixel(cams[j], xc / zc, yc / zc)
                        ui = int(np.floor(u + 0.5))
                        vi = int(np.floor(v + 0.5))
                        if 0 <= ui < fg.shape[2] and 0 <= vi < fg.shape[1] and fg[j, vi, ui] != 0:
                            val = _bilinear(grey[j], u, v)
                out[j, s, p] = val


@nb.njit(cache=True, nogil=True)
def free_votes(o, dirs, t_from, t_to, occ, origin, h, votes, stamp, view):
    """Add one vote (per view, once per voxel) to every occupied voxel the segment ``[t_from, t_to]`` of a ray crosses
    and whose centre lies before ``t_to`` along the ray."""
    step = 0.25 * h
    for p in range(dirs.shape[0]):
        d = dirs[p]
        t = t_from[p]
        while t <= t_to[p]:
            x = o[0] + t * d[0]
            y = o[1] + t * d[1]
            z = o[2] + t * d[2]
            i = int(np.floor((x - origin[0]) / h + 0.5))
            j = int(np.floor((y - origin[1]) / h + 0.5))
            k = int(np.floor((z - origin[2]) / h + 0.5))
            if 0 <= i < occ.shape[0] and 0 <= j < occ.shape[1] and 0 <= k < occ.shape[2]:
                # the voxel's centre must lie in front of the segment's end, not only a corner of its cell
                tc = ((origin[0] + i * h - o[0]) * d[0] + (origin[1] + j * h - o[1]) * d[1]
                      + (origin[2] + k * h - o[2]) * d[2])
                if occ[i, j, k] != 0 and stamp[i, j, k] != view and tc <= t_to[p]:
                    stamp[i, j, k] = view
                    votes[i, j, k] += 1
            t += step
