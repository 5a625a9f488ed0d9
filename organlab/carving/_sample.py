"""Per-view sampling kernels shared by the dense hull field (:mod:`._field`) and the band (:mod:`._band`).

The one place the signed distance of a world point in a view is computed,
so both fields agree value for value.
"""

from __future__ import annotations

import math

from numba import njit

from ..nbcam import to_camera, to_pixel

__all__ = ["view_dmm", "insert_smallest"]


@njit(cache=True, nogil=True, inline="always")
def view_dmm(sdf, h, w, cp, x, y, z, lim):
    """Signed distance (mm, clipped to ``+-lim``) of world point (x, y, z) in one view.

    Returns ``(seen, dmm)``: ``seen`` False when the view cannot see the point
    (on or behind the image plane, outside the image, singular projection).
    The one place this is computed: the dense and the band field share it.
    """
    k1, k2, p1, p2, k3 = cp[17], cp[18], cp[19], cp[20], cp[21]
    fxy = cp[12] * cp[15]
    xc, yc, zc = to_camera(cp, x, y, z)
    if zc <= 0.0:
        return False, 0.0
    xn = xc / zc
    yn = yc / zc
    u, v = to_pixel(cp, xn, yn)
    if not (u >= -0.5 and u <= w - 0.5 and v >= -0.5 and v <= h - 0.5):
        return False, 0.0  # outside the image: this view does not constrain it
    # bilinear sample, clamped to the border pixel centres
    uu = min(max(u, 0.0), w - 1.0)
    vv = min(max(v, 0.0), h - 1.0)
    c0 = min(int(uu), w - 2)
    r0 = min(int(vv), h - 2)
    a = uu - c0
    b = vv - r0
    d = (1.0 - b) * ((1.0 - a) * sdf[r0, c0] + a * sdf[r0, c0 + 1]) + b * (
        (1.0 - a) * sdf[r0 + 1, c0] + a * sdf[r0 + 1, c0 + 1]
    )
    # local magnification of the projection (px per normalized unit)
    r2 = xn * xn + yn * yn
    rad = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    drad = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)
    j00 = rad + 2.0 * xn * xn * drad + 2.0 * p1 * yn + 6.0 * p2 * xn
    j01 = 2.0 * xn * yn * drad + 2.0 * p1 * xn + 2.0 * p2 * yn
    j10 = 2.0 * xn * yn * drad + 2.0 * p1 * xn + 2.0 * p2 * yn
    j11 = rad + 2.0 * yn * yn * drad + 6.0 * p1 * yn + 2.0 * p2 * xn
    det = abs(j00 * j11 - j01 * j10) * fxy
    if det < 1e-12:
        return False, 0.0
    dmm = d * zc / math.sqrt(det)
    if dmm > lim:
        dmm = lim
    elif dmm < -lim:
        dmm = -lim
    return True, dmm


@njit(cache=True, nogil=True, inline="always")
def insert_smallest(row, dmm):
    """Insert ``dmm`` into the ascending row of the k + 1 smallest, dropping the largest."""
    kk = row.shape[0]
    if dmm < row[kk - 1]:
        m = kk - 1
        while m > 0 and row[m - 1] > dmm:
            row[m] = row[m - 1]
            m -= 1
        row[m] = dmm
