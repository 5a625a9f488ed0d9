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
hull of the sub-pixel outline (coverage 0.5), undistorted to normalised camera
coordinates ``(x, y, 1)``.
"""

from __future__ import annotations

import numpy as np

from ..camera import undistort

#: Pairs whose baseline passes nearer than this to the silhouettes' directions
#: (the extremal planes' half-angle about the baseline, degrees) are left out:
#: their planes are ill-defined.
MAX_HALF_ANGLE_DEG = 75.0


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
    from skimage.measure import find_contours

    cov = np.asarray(coverage, dtype=np.float64)
    h, w = cov.shape
    pad = np.pad(cov, 1)  # outlines closed at the image border
    cs = find_contours(pad, level)
    if not cs:
        return np.zeros((0, 3)), np.zeros(0, bool)
    pts = np.concatenate(cs)[:, ::-1] - 1.0  # (u, v) px
    pts[:, 0] = np.clip(pts[:, 0], -0.5, w - 0.5)
    pts[:, 1] = np.clip(pts[:, 1], -0.5, h - 0.5)
    K = camera.K
    fx, fy, cx, cy, skew = K[0, 0], K[1, 1], K[0, 2], K[1, 2], K[0, 1]
    yd = (pts[:, 1] - cy) / fy
    xd = (pts[:, 0] - cx - skew * yd) / fx
    xn = undistort(np.stack([xd, yd], axis=1), camera.dist)
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

    Returns
    -------
    psi : (P, 4) float64
        ``(min_i, max_i, min_j, max_j)``, radians, about the baseline, from
        the plane through view ``i``'s middle ray.
    sin_i, sin_j : (P,) float64
        Sine of the angle between the middle ray and the baseline (pixels per
        radian of plane rotation, divided by the focal length).
    """
    b = centres[J] - centres[I]
    b /= np.linalg.norm(b, axis=1, keepdims=True)
    rc = centroid_w[I]
    rc = rc / np.linalg.norm(rc, axis=1, keepdims=True)
    u1 = rc - np.sum(rc * b, axis=1, keepdims=True) * b
    sin_i = np.linalg.norm(u1, axis=1)
    u1 /= sin_i[:, None]
    u2 = np.cross(b, u1)
    ri, rj = rays_w[I], rays_w[J]
    pi = np.arctan2(np.einsum("pmk,pk->pm", ri, u2), np.einsum("pmk,pk->pm", ri, u1))
    pj = np.arctan2(np.einsum("pmk,pk->pm", rj, u2), np.einsum("pmk,pk->pm", rj, u1))
    rcj = centroid_w[J] / np.linalg.norm(centroid_w[J], axis=1, keepdims=True)
    sin_j = np.linalg.norm(rcj - np.sum(rcj * b, axis=1, keepdims=True) * b, axis=1)
    psi = np.stack([pi.min(axis=1), pi.max(axis=1), pj.min(axis=1), pj.max(axis=1)], axis=1)
    if return_index:
        idx = np.stack([pi.argmin(axis=1), pi.argmax(axis=1), pj.argmin(axis=1), pj.argmax(axis=1)], axis=1)
        return psi, sin_i, sin_j, idx
    return psi, sin_i, sin_j
