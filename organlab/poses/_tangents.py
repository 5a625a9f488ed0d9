"""Outer epipolar tangents of silhouettes: the residuals the pose refinement minimises.

For two views ``i`` and ``j`` every plane through the baseline ``C_i C_j`` is an
epipolar plane.  Of those planes, the two that just touch the specimen (the
extremal ones, about the baseline) touch it at *frontier points*, which both
cameras see on their silhouette's outline (Cipolla, Astrom & Giblin 1995;
Mendonca, Wong & Cipolla 2001).  Each view's silhouette alone gives those two
planes (the planes through the baseline tangent to its outline); with the true
poses the two views give the same planes, with wrong poses they do not.  The
angle between the planes, about the baseline, converted to pixels, is the
residual: two per pair of views, exact at the true poses for any solid (only
the silhouettes' convex hulls matter), and cheap (no carving).

Everything here works on one fixed set of outline points per view: the convex
hull of the sub-pixel outline (coverage 0.5, :func:`organlab.raster.iso_contours`, each point then placed
by the coverage summed across the edge: :func:`_profile_points`), undistorted to normalised camera
coordinates ``(x, y, 1)``.
"""

from __future__ import annotations

import numpy as np

from numba import njit

from ..nbcam import undistort_points
from ..raster import iso_contours

#: Pairs whose baseline passes nearer than this to the silhouettes' directions
#: (the extremal planes' half-angle about the baseline, degrees) are left out:
#: their planes are ill-defined.
MAX_HALF_ANGLE_DEG = 75.0
#: Half-width (px) of the coverage profile across the edge that places each outline point (0: the 0.5-crossing).
PROFILE_HALF_PX = 3


def _profile_points(pad, rc, half):
    """:func:`_profile_points_numpy` compiled (bit for bit: tests/test_poses_check.py; the numpy steps on some 700
    points a view were 0.35 ms of the poses check's 2 ms a view)."""
    if 2 * half >= 8:  # numpy sums longer rows pairwise, in blocks
        return _profile_points_numpy(pad, rc, half)
    return _profile_kernel(np.ascontiguousarray(pad, np.float64), np.ascontiguousarray(rc, np.float64), int(half))


@njit(cache=True, nogil=True)
def _profile_kernel(pad, rc, half):
    """:func:`_profile_points_numpy`, one point at a time, its operations in its order (numpy sums a row of
    fewer than 8 values from left to right)."""
    out = rc.copy()
    nr, nc = pad.shape
    m = 2 * half
    prof = np.empty(m)
    for q in range(rc.shape[0]):
        r, c = rc[q, 0], rc[q, 1]
        along_row = abs(r - np.rint(r)) < 1e-9
        if along_row:
            line, pos, n = np.int64(np.rint(r)), c, nc
        else:
            line, pos, n = np.int64(np.rint(c)), r, nr
        k0 = np.int64(np.floor(pos)) - half + 1
        if not (k0 >= 0 and k0 + m - 1 < n):
            continue
        for i in range(m):
            prof[i] = pad[line, k0 + i] if along_row else pad[k0 + i, line]
        first_in = prof[half - 1] > prof[half]
        lo, hi = (prof[0], prof[m - 1]) if first_in else (prof[m - 1], prof[0])
        if not (lo >= 0.98 and hi <= 0.02):
            continue
        sign = -1.0 if first_in else 1.0
        mono = True
        for i in range(m - 1):
            if not ((prof[i + 1] - prof[i]) * sign >= -0.02):
                mono = False
                break
        if not mono:
            continue
        tot = prof[0]
        for i in range(1, m):
            tot += prof[i]
        x = (np.float64(k0) - 0.5) + tot if first_in else (np.float64(k0 + m - 1) + 0.5) - tot
        if abs(x - pos) < 1.0:
            out[q, 1 if along_row else 0] = x
    return out


def _profile_points_numpy(pad, rc, half):
    """Outline points ``(row, col)`` of ``pad`` at level 0.5 moved to the edge that the coverage summed across it
    (``2 half`` px along the point's grid link) places: for a straight edge and area coverage that sum is the
    edge's exact position, where the linear 0.5-crossing is off by up to 0.09 px.  Points whose profile is not
    a single, saturated, monotone step keep their 0.5-crossing."""
    out = rc.copy()
    r, c = rc[:, 0], rc[:, 1]
    on_row = np.abs(r - np.round(r)) < 1e-9  # on a link between two pixels of one row
    off = np.arange(-half + 1, half + 1)
    for along_row in (True, False):
        sel = np.nonzero(on_row if along_row else ~on_row)[0]
        line = np.round((r if along_row else c)[sel]).astype(np.int64)
        pos = (c if along_row else r)[sel]
        n = pad.shape[1] if along_row else pad.shape[0]
        ks = np.floor(pos).astype(np.int64)[:, None] + off
        inside = (ks[:, 0] >= 0) & (ks[:, -1] < n)
        kc = np.clip(ks, 0, n - 1)
        prof = pad[line[:, None], kc] if along_row else pad[kc, line[:, None]]
        first_in = prof[:, half - 1] > prof[:, half]
        lo, hi = np.where(first_in, prof[:, 0], prof[:, -1]), np.where(first_in, prof[:, -1], prof[:, 0])
        d = np.diff(prof, axis=1) * np.where(first_in, -1.0, 1.0)[:, None]
        s = prof.sum(axis=1)
        x = np.where(first_in, ks[:, 0] - 0.5 + s, ks[:, -1] + 0.5 - s)
        good = inside & (lo >= 0.98) & (hi <= 0.02) & (d >= -0.02).all(axis=1) & (np.abs(x - pos) < 1.0)
        out[sel[good], 1 if along_row else 0] = x[good]
    return out


def outline_rays(coverage, camera, *, level=0.5, border_px=1.5):
    """Convex-hull outline points of a silhouette, as normalised camera rays.

    Parameters
    ----------
    coverage : (H, W) float or bool
        The silhouette (coverage in ``[0, 1]`` or a mask).
    camera : Camera
        Its intrinsics (``K``, ``dist``) are used.
    level : float
        Outline level of the coverage.
    border_px : float
        Hull points this close to the image border are marked: the silhouette
        may be cut by the frame there.

    Returns
    -------
    rays : (M, 3) float64
        ``(x, y, 1)`` normalised coordinates of the hull vertices, camera frame.
    on_border : (M,) bool
    """
    import cv2

    cov = np.asarray(coverage, dtype=np.float64)
    h, w = cov.shape
    pad = np.pad(cov, 1)  # outlines closed at the image border
    pts, _ = iso_contours(pad, level)  # skimage's find_contours, compiled: its points, all contours
    if len(pts) == 0:
        return np.zeros((0, 3)), np.zeros(0, bool)
    if PROFILE_HALF_PX:
        pts = _profile_points(pad, pts, int(PROFILE_HALF_PX))
    pts = pts[:, ::-1] - 1.0  # (u, v) px
    pts[:, 0] = np.clip(pts[:, 0], -0.5, w - 0.5)
    pts[:, 1] = np.clip(pts[:, 1], -0.5, h - 0.5)
    K = camera.K
    fx, fy, cx, cy, skew = K[0, 0], K[1, 1], K[0, 2], K[1, 2], K[0, 1]
    yd = (pts[:, 1] - cy) / fy
    xd = (pts[:, 0] - cx - skew * yd) / fx
    # organlab.camera.undistort compiled (bit for bit; its numpy steps were 0.6 ms a view)
    xn = undistort_points(np.stack([xd, yd], axis=1), np.ascontiguousarray(camera.dist, dtype=np.float64))
    hull = cv2.convexHull(xn.astype(np.float32), returnPoints=False).ravel()
    # float32 hull indices, exact float64 points
    sel = np.unique(hull)
    keep = xn[sel]
    uv = pts[sel]
    border = (uv[:, 0] < border_px - 0.5) | (uv[:, 1] < border_px - 0.5) | (uv[:, 0] > w - 0.5 - border_px) | (uv[:, 1] > h - 0.5 - border_px)
    return np.column_stack([keep, np.ones(len(keep))]), border


def pad_rays(ray_sets):
    """Stack per-view ray sets ``(M_v, 3)`` into ``(n, M, 3)`` by repeating each set's first ray."""
    m = max(len(r) for r in ray_sets)
    out = np.empty((len(ray_sets), m, 3))
    for k, r in enumerate(ray_sets):
        out[k, : len(r)] = r
        out[k, len(r) :] = r[0]
    return out


def _norm(v):
    return np.sqrt(np.einsum("pk,pk->p", v, v))


def _cross(a, b):
    """``np.cross`` of ``(..., 3)`` arrays, without its axis handling (a tenth of its time on small arrays)."""
    return np.stack([a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1], a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2],
                     a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]], axis=-1)


def _frames(centres, centroid_w, I, J):
    """Each pair's baseline ``b`` and the plane through view ``i``'s middle ray (``u1``; ``u2 = b x u1``)."""
    b = centres[J] - centres[I]
    length = _norm(b)
    b /= length[:, None]
    rc = centroid_w[I]
    rc = rc / _norm(rc)[:, None]
    u1 = rc - np.einsum("pk,pk->p", rc, b)[:, None] * b
    sin_i = _norm(u1)
    u1 /= sin_i[:, None]
    u2 = _cross(b, u1)
    rcj = centroid_w[J] / _norm(centroid_w[J])[:, None]
    sin_j = _norm(rcj - np.einsum("pk,pk->p", rcj, b)[:, None] * b)
    return b, u1, u2, sin_i, sin_j, length


def _extremes(q):
    """``argmin``, ``argmax`` over axis 1 of the angles ``atan2(q[..., 1], q[..., 0])`` of ``(P, M, 2)`` ``q``.

    When every point lies ahead (``q[..., 0] > 0``: the usable pairs, their planes within
    :data:`MAX_HALF_ANGLE_DEG`) ``tan`` is compared (a division, not an arctangent per point).
    """
    x, y = q[..., 0], q[..., 1]
    t = y / x if (x > 0).all() else np.arctan2(y, x)
    return t.argmin(axis=1), t.argmax(axis=1)


def pair_angles(rays_w, centres, centroid_w, I, J, *, return_index=False):
    """Extremal epipolar planes of each view of each pair, as angles about the baseline.

    Parameters
    ----------
    rays_w : (n, M, 3) float64
        Outline rays of every view, world frame (any length).
    centres : (n, 3) float64
        Camera centres, world frame, mm.
    centroid_w : (n, 3) float64
        A ray toward the silhouette's middle, per view, world frame.
    I, J : (P,) int
        The pairs.
    return_index : bool
        Also return which ray of each view gives each extremal plane.

    Returns
    -------
    psi : (P, 4) float64
        ``(min_i, max_i, min_j, max_j)``, radians, about the baseline, from
        the plane through view ``i``'s middle ray.
    sin_i, sin_j : (P,) float64
        Sine of the angle between the middle ray and the baseline (pixels per
        radian of plane rotation, divided by the focal length).
    index : (P, 4) int
        With ``return_index``: the rays (of view ``i``, ``i``, ``j``, ``j``) giving ``psi``.
    """
    _, u1, u2, sin_i, sin_j, _ = _frames(centres, centroid_w, I, J)
    U = np.stack([u1, u2], axis=2)  # (P, 3, 2)
    qi, qj = rays_w[I] @ U, rays_w[J] @ U  # (P, M, 2): each ray across and along the plane through the middle ray
    idx = np.stack([*_extremes(qi), *_extremes(qj)], axis=1)
    P = np.arange(len(I))[:, None]
    sel = np.concatenate([qi[P, idx[:, :2]], qj[P, idx[:, 2:]]], axis=1)  # (P, 4, 2)
    psi = np.arctan2(sel[..., 1], sel[..., 0])
    if return_index:
        return psi, sin_i, sin_j, idx
    return psi, sin_i, sin_j


def pair_angle_derivatives(rays_w, centres, centroid_w, I, J, index):
    """How the extremal planes of :func:`pair_angles` turn with the views' poses (the chain rule).

    Each extremal plane touches one ray (``index``, from :func:`pair_angles`); while that ray stays the
    extremal one, its angle ``atan2(r . u2, r . u1)`` moves with the ray (the view turned about its centre)
    and with the frame ``(u1, u2, b)``.  The frame turns with the baseline ``b`` and, about ``b``, with view
    ``i``'s middle ray: that turn about the baseline moves all four angles of a pair alike, so it is left
    out here; differences between view ``i``'s and view ``j``'s angles (the residuals) are exact.

    Parameters
    ----------
    rays_w, centres, centroid_w, I, J
        As for :func:`pair_angles`.
    index : (P, 4) int
        The extremal rays (``return_index`` of :func:`pair_angles`).

    Returns
    -------
    turn : (P, 4, 3) float64
        ``d psi / d theta`` (rad per rad): ``theta`` a turn of that angle's view (view ``i`` for the first two,
        ``j`` for the last two) about its centre, a rotation vector in the world frame (its rays ``r`` move
        by ``theta x r``).
    move : (P, 4, 3) float64
        ``d psi / d (C_j - C_i)`` (rad per mm), world frame.

    Examples
    --------
    >>> import numpy as np
    >>> rng = np.random.default_rng(0)
    >>> rays = rng.normal([0.0, 0.0, 1.0], 0.1, (2, 20, 3))
    >>> C, cen, I, J = np.array([[0.0, 0, -10], [3.0, 0, -9]]), rays.mean(1), np.array([0]), np.array([1])
    >>> psi, _, _, idx = pair_angles(rays, C, cen, I, J, return_index=True)
    >>> turn, move = pair_angle_derivatives(rays, C, cen, I, J, idx)
    >>> dC = np.array([0.0, 1e-6, 0.0])                      # view j's centre moved 1e-6 mm
    >>> C2 = C.copy(); C2[1] += dC
    >>> psi2 = pair_angles(rays, C2, cen, I, J)[0]
    >>> d = (psi2 - psi) - move @ dC                       # first order, up to a common turn
    >>> bool(np.ptp(d) < 1e-12)
    True
    """
    b, u1, u2, _, _, length = _frames(centres, centroid_w, I, J)
    r = np.concatenate([rays_w[I[:, None], index[:, :2]], rays_w[J[:, None], index[:, 2:]]], axis=1)  # (P, 4, 3)
    U = np.stack([u1, u2], axis=2)
    ac = r @ U  # (P, 4, 2)
    a, c = ac[..., 0], ac[..., 1]
    den = a * a + c * c
    g = (a[..., None] * u2[:, None] - c[..., None] * u1[:, None]) / den[..., None]  # d psi / d r
    turn = _cross(r, g)
    # the frame turns by w (d u = w x u) when the baseline moves: w's part across b is
    # u2 (u1 . db) - u1 (u2 . db), and d psi = -w . turn
    tu = turn @ U
    k = u1[:, None] * tu[..., 1:] - u2[:, None] * tu[..., :1]
    return turn, -k / length[:, None, None]
