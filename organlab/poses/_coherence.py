"""Silhouette coherence along outline rays: does every view's outline touch the hull of the others?

For a point on view ``v``'s silhouette outline, the viewing ray touches the
specimen (on its contour generator), so some point of the ray projects inside
(or onto the outline of) every other silhouette.  Along the ray, the depth
into the hull of the other views is ``h(X) = min_j D_j(P_j X)`` (``D_j``: the
signed distance to silhouette ``j``'s outline, px, inside positive); its
maximum over the ray is ``>= 0`` at the true poses (up to the silhouettes'
noise).  A negative maximum is a piece of silhouette ``v`` that no model can
explain: the residual is ``min(0, max_X h(X))``, px.  This is Hernandez,
Schmitt & Cipolla's silhouette coherence (2007) evaluated on outline rays, a
one-sided measure that, unlike the outer epipolar tangents, sees the
silhouettes' concavities (a gap between two legs, a bleb's notch).
"""

from __future__ import annotations

import numpy as np

from ..camera import undistort


def signed_distance(coverage):
    """Signed distance to the coverage-0.5 outline, px, inside positive, ``(H, W)`` float32."""
    from scipy import ndimage

    cov = np.asarray(coverage, dtype=np.float32)
    m = cov >= 0.5
    d = np.where(m, ndimage.distance_transform_edt(m) - 0.5, -(ndimage.distance_transform_edt(~m) - 0.5))
    part = (cov > 0) & (cov < 1)
    d[part] = cov[part] - 0.5
    return d.astype(np.float32)


def outline_points(coverage, n_points, *, level=0.5):
    """About ``n_points`` points evenly spaced along a silhouette's outline, ``(N, 2)`` px ``(u, v)``."""
    from skimage.measure import find_contours

    cov = np.asarray(coverage, dtype=np.float64)
    cs = [c for c in find_contours(np.pad(cov, 1), level) if len(c) > 8]
    if not cs:
        return np.zeros((0, 2))
    lengths = np.array([np.sum(np.linalg.norm(np.diff(c, axis=0), axis=1)) for c in cs])
    step = lengths.sum() / max(int(n_points), 1)
    out = []
    for c, L in zip(cs, lengths):
        seg = np.linalg.norm(np.diff(c, axis=0), axis=1)
        s = np.concatenate([[0.0], np.cumsum(seg)])
        q = np.arange(step / 2, L, step)
        if len(q):
            out.append(np.stack([np.interp(q, s, c[:, 1]), np.interp(q, s, c[:, 0])], axis=1) - 1.0)
    return np.concatenate(out) if out else np.zeros((0, 2))


def _bilinear(img, u, v):
    h, w = img.shape
    inside = (u >= 0) & (u <= w - 1) & (v >= 0) & (v <= h - 1)
    uc = np.clip(u, 0, w - 1.001)
    vc = np.clip(v, 0, h - 1.001)
    u0 = uc.astype(np.int64)
    v0 = vc.astype(np.int64)
    fu = uc - u0
    fv = vc - v0
    a = img[v0, u0] * (1 - fu) + img[v0, u0 + 1] * fu
    b = img[v0 + 1, u0] * (1 - fu) + img[v0 + 1, u0 + 1] * fu
    val = a * (1 - fv) + b * fv
    # outside the frame: no constraint from that view
    return np.where(inside, val, np.inf)


def _project(K, dist, R, t, X):
    """Pixels of points ``X (..., 3)`` through one camera (distortion applied)."""
    pc = X @ R.T + t
    z = pc[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        x = pc[..., 0] / z
        y = pc[..., 1] / z
    if np.any(dist):
        k1, k2, p1, p2, k3 = dist
        r2 = x * x + y * y
        rad = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        x, y = x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x), y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    u = K[0, 0] * x + K[0, 1] * y + K[0, 2]
    v = K[1, 1] * y + K[1, 2]
    bad = ~(z > 0)
    return np.where(bad, -1e9, u), np.where(bad, -1e9, v)


class Coherence:
    """Outline-ray coherence residuals of every view under changing poses.

    Parameters
    ----------
    coverages : list of (H, W) arrays
    camera : Camera
        The intrinsics (every view shares them).
    R, t : (n, 3, 3), (n, 3)
        The poses the depth intervals are chosen at.
    roi : ((3,), (3,))
        The voxel space, mm.
    n_points, n_depths : int
        Outline points per view, depth samples per ray.
    """

    def __init__(self, coverages, camera, R, t, roi, *, n_points=96, n_depths=24):
        self.K, self.dist = camera.K, np.asarray(camera.dist, np.float64)
        self.D = [signed_distance(c) for c in coverages]
        self.n = len(coverages)
        self.n_depths = int(n_depths)
        self.px = [outline_points(c, n_points) for c in coverages]
        # normalised rays of the outline points, camera frame
        K = self.K
        self.rays_cam = []
        for px in self.px:
            yd = (px[:, 1] - K[1, 2]) / K[1, 1]
            xd = (px[:, 0] - K[0, 2] - K[0, 1] * yd) / K[0, 0]
            xn = undistort(np.stack([xd, yd], axis=1), self.dist)
            self.rays_cam.append(np.column_stack([xn, np.ones(len(xn))]))
        self.roi = (np.asarray(roi[0], float), np.asarray(roi[1], float))
        self.set_intervals(R, t)

    def _ray_points(self, v, R, t, depths):
        """Points ``(N, K, 3)`` along view ``v``'s outline rays at the given depths (camera z, mm)."""
        C = -R[v].T @ t[v]
        d = self.rays_cam[v] @ R[v]  # world directions, z_cam = 1 per unit
        return C + depths[..., None] * d[:, None, :]

    def set_intervals(self, R, t, *, n_fine=160, margin_px=4.0):
        """Per ray, the depth interval where it passes near the hull of the other views (fixed while fitting)."""
        lo, hi = self.roi
        self.depths = []
        for v in range(self.n):
            C = -R[v].T @ t[v]
            d = self.rays_cam[v] @ R[v]
            with np.errstate(divide="ignore", invalid="ignore"):
                t0 = (lo - C) / d
                t1 = (hi - C) / d
            tmin = np.nanmax(np.minimum(t0, t1), axis=1)
            tmax = np.nanmin(np.maximum(t0, t1), axis=1)
            tmin = np.maximum(tmin, 1.0)
            s = np.linspace(0, 1, n_fine)
            dep = tmin[:, None] + (tmax - tmin)[:, None] * s[None]
            X = C + dep[..., None] * d[:, None, :]
            h = self._hull_depth(X, R, t, exclude=v)
            near = h > -margin_px
            a = np.where(near.any(1), np.argmax(near, 1), 0)
            b = np.where(near.any(1), n_fine - 1 - np.argmax(near[:, ::-1], 1), n_fine - 1)
            a = np.maximum(a - 2, 0)
            b = np.minimum(b + 2, n_fine - 1)
            q = np.linspace(0, 1, self.n_depths)
            da, db = dep[np.arange(len(dep)), a], dep[np.arange(len(dep)), b]
            self.depths.append(da[:, None] + (db - da)[:, None] * q[None])
        self._cache = None

    def _view_depth(self, j, R, t, X):
        u, v = _project(self.K, self.dist, R[j], t[j], X)
        return _bilinear(self.D[j], u, v)

    def _hull_depth(self, X, R, t, exclude):
        h = np.full(X.shape[:-1], np.inf)
        for j in range(self.n):
            if j != exclude:
                h = np.minimum(h, self._view_depth(j, R, t, X))
        return h

    def table(self, R, t):
        """Per view ``v``: ``(N, K, n)`` depths of its ray samples in every view (``inf`` for ``v`` itself)."""
        out = []
        for v in range(self.n):
            X = self._ray_points(v, R, t, self.depths[v])
            T = np.empty(X.shape[:-1] + (self.n,), np.float64)
            for j in range(self.n):
                T[..., j] = np.inf if j == v else self._view_depth(j, R, t, X)
            out.append(T)
        return out

    @staticmethod
    def reduce(T):
        """``min(0, max_depth min_view)`` per ray, px."""
        r = T.min(axis=2).max(axis=1)
        r = np.where(np.isfinite(r), r, 0.0)
        return np.minimum(r, 0.0)

    def residuals(self, R, t):
        return np.concatenate([self.reduce(T) for T in self.table(R, t)])

    def jacobian_angles(self, R, t, poses_of, x, cols, h=1e-3):
        """Forward differences of :meth:`residuals` in parameters ``cols`` that each move one view.

        ``poses_of(x)`` gives ``(R, t)``; ``cols`` is a list of ``(param_index, view)``.
        """
        T0 = self.table(R, t)
        r0 = [self.reduce(T) for T in T0]
        offs = np.concatenate([[0], np.cumsum([len(r) for r in r0])])
        Jc = np.zeros((offs[-1], len(cols)))
        for c, (k, u) in enumerate(cols):
            xk = x.copy()
            xk[k] += h
            Rk, tk = poses_of(xk)
            for v in range(self.n):
                if v == u:  # its own rays moved: every view's depth along them
                    X = self._ray_points(v, Rk, tk, self.depths[v])
                    T = np.empty_like(T0[v])
                    for j in range(self.n):
                        T[..., j] = np.inf if j == v else self._view_depth(j, Rk, tk, X)
                else:  # only view u's depth along v's rays
                    X = self._ray_points(v, R, t, self.depths[v])
                    T = T0[v].copy()
                    T[..., u] = self._view_depth(u, Rk, tk, X)
                Jc[offs[v] : offs[v + 1], c] = (self.reduce(T) - r0[v]) / h
        return np.concatenate(r0), Jc
