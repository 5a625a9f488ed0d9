"""Photo-consistency statistics of :mod:`organlab.coloring`: pooled pixel moments, spatial support."""

from __future__ import annotations

import numpy as np

_BG_FRACTION = 0.5
_REFINE = 2
_BG_VIEWS = 1


class _Stats:
    """Pixel statistics of M voxels in V views, filled by the kernels, then pooled."""

    #: (V,) azimuth of each view's camera centre about the world z axis, radians;
    #: set by color_voxels for measure='shading' while it runs.
    azimuth = None
    #: The measure color_voxels runs with (the robust ones are computed only when asked for).
    measure = None

    def __init__(self, V, M, C):
        self.v_vis = np.empty((V, M), np.int32)
        self.v_tot = np.empty((V, M), np.int32)
        self.v_sums = np.empty((V, M, C))
        self.v_sq = np.empty((V, M, C))
        self.v_bg = np.empty((V, M), np.int32)
        self.v_cnt = np.empty((V, M), np.int32)

    def arrays(self):
        return self.v_vis, self.v_tot, self.v_sums, self.v_sq, self.v_bg, self.v_cnt

    def pool(self):
        self.n_vis = self.v_vis.sum(axis=0, dtype=np.int64)
        self.n_tot = self.v_tot.sum(axis=0, dtype=np.int64)
        self.sums = self.v_sums.sum(axis=0)
        self.sq = self.v_sq.sum(axis=0)
        with np.errstate(invalid="ignore", divide="ignore"):
            per_view = np.where(self.v_vis[:, :, None] > 0, self.v_sums**2 / self.v_vis[:, :, None], 0.0)
        self.bw = per_view.sum(axis=0)
        self.bgv = _seen_through(self.v_bg, self.v_cnt)
        m = self.measure
        self.trim = _trimmed_std(self.v_vis, self.v_sums) if m == "trimmed" else None
        self.chroma = _trimmed_std(self.v_vis, self.v_sums, normalized=True) if m == "normalized" else None
        self.fit = _shading_fit_std(self.v_vis, self.v_sums, self.azimuth) if m == "shading" else None
        return self

    def merge(self, other, rows):
        """Take the pooled statistics of ``rows`` from ``other``; returns self."""
        for name in ("n_vis", "n_tot", "sums", "sq", "bw", "bgv", "trim", "chroma", "fit"):
            if getattr(self, name) is not None:
                getattr(self, name)[rows] = getattr(other, name)[rows]
        return self

    def mean(self):
        return self.sums / np.maximum(self.n_vis, 1)[:, None]

    def std(self, measure="pooled"):
        """Standard deviation, grey levels: ``sqrt`` of the mean per-channel variance.

        ``pooled``: of all visible pixels (Seitz & Dyer); ``between``: of the
        per-view mean colours, each weighted by its number of pixels (the
        texture inside one footprint does not count); ``trimmed``: ``between``
        without the one view whose mean colour is farthest from the others'
        (a highlight or a glint seen in one view), when at least 3 views see
        the voxel.
        """
        if measure == "trimmed":
            return self.trim
        if measure == "normalized":
            return self.chroma
        if measure == "shading":
            return self.fit
        n = np.maximum(self.n_vis, 1)[:, None]
        mean = self.sums / n
        second = self.sq if measure == "pooled" else self.bw
        var = np.maximum(second / n - mean * mean, 0.0)
        return np.sqrt(var.mean(axis=1))

    def decide(self, threshold, measure, min_pix, min_frac):
        """Per voxel: inconsistent, seen, tested (bool arrays)."""
        seen = self.n_vis > 0
        tested = seen & (self.n_vis >= min_pix) & (self.n_vis >= min_frac * self.n_tot)
        return tested & (self.std(measure) > threshold), seen, tested


def _within(ab, na, nb_, flags, radius):
    """Voxels of a layer within chessboard distance ``radius`` of a flagged one (all when radius is None)."""
    if radius is None:
        return np.ones(len(ab), bool)
    from scipy import ndimage

    g = np.zeros((na, nb_), bool)
    g[ab[flags, 0], ab[flags, 1]] = True
    g = ndimage.binary_dilation(g, structure=np.ones((3, 3), bool), iterations=int(radius))
    return g[ab[:, 0], ab[:, 1]]


def _support_2d(ab, na, nb_, flags, support):
    """Keep the flags of voxels with at least ``support`` flagged voxels in their 3 x 3 in-layer neighbourhood."""
    if support <= 1 or not flags.any():
        return flags
    g = np.zeros((na + 2, nb_ + 2), np.int32)
    g[ab[:, 0] + 1, ab[:, 1] + 1] = flags
    count = np.zeros_like(g)
    for da in (-1, 0, 1):
        for db in (-1, 0, 1):
            count[1:-1, 1:-1] += g[1 + da : na + 1 + da, 1 + db : nb_ + 1 + db]
    return flags & (count[ab[:, 0] + 1, ab[:, 1] + 1] >= support)


def _support_3d(ijk, shape, flags, support):
    """Keep the flags of voxels with at least ``support`` flagged voxels in their 3 x 3 x 3 neighbourhood."""
    if support <= 1 or not flags.any():
        return flags
    from scipy import ndimage

    g = np.zeros(shape, np.int32)
    g[ijk[:, 0], ijk[:, 1], ijk[:, 2]] = flags
    count = ndimage.correlate(g, np.ones((3, 3, 3), np.int32), mode="constant")
    return flags & (count[ijk[:, 0], ijk[:, 1], ijk[:, 2]] >= support)


def _seen_through(v_bg, v_cnt):
    """Voxels whose footprint is mostly background pixels in some view: (V, M) counts -> (M,) bool."""
    return np.count_nonzero(v_bg > _BG_FRACTION * v_cnt, axis=0) >= _BG_VIEWS


def _rgb(mean, C):
    col = np.clip(np.rint(mean), 0, 255).astype(np.uint8)
    return np.repeat(col, 3, axis=1) if C == 1 else col


# =====================================================================
# public


def _trimmed_std(v_vis, v_sums, *, normalized=False):
    """Between-view standard deviation without the most deviant view: (V, M), (V, M, C) -> (M,) grey levels.

    ``normalized``: each view's mean colour is first scaled to the voxel's
    mean brightness over the views (shading and exposure divided out; the
    colour's hue and saturation remain), for RGB; grey images are unchanged.
    """
    w = v_vis.astype(np.float64)  # (V, M)
    with np.errstate(invalid="ignore", divide="ignore"):
        means = np.where(w[:, :, None] > 0, v_sums / np.maximum(w, 1)[:, :, None], 0.0)
    if normalized and means.shape[2] == 3:
        lum = means.mean(axis=2)  # (V, M)
        ref = (w * lum).sum(axis=0) / np.maximum(w.sum(axis=0), 1)  # (M,)
        means = means * (ref[None, :] / np.maximum(lum, 1.0))[:, :, None]
    def moments(weights):
        n = weights.sum(axis=0)
        mu = (weights[:, :, None] * means).sum(axis=0) / np.maximum(n, 1)[:, None]
        var = (weights[:, :, None] * (means - mu) ** 2).sum(axis=0) / np.maximum(n, 1)[:, None]
        return mu, var.mean(axis=1)
    mu, var = moments(w)
    n_views = np.count_nonzero(w > 0, axis=0)
    dev = np.where(w > 0, ((means - mu) ** 2).sum(axis=2), -1.0)
    worst = np.argmax(dev, axis=0)
    w2 = w.copy()
    drop = n_views >= 3
    w2[worst[drop], np.flatnonzero(drop)] = 0.0
    _, var2 = moments(w2)
    return np.sqrt(np.maximum(np.where(drop, var2, var), 0.0))


#: Views a voxel needs for the shading fit (fewer: the trimmed between-view spread).
_FIT_MIN_VIEWS = 6
#: Harmonics of the table angle in the shading curve (2 fits a clipped cosine better, but absorbs
#: more of a concavity's disagreement: measured worse on the dented specimen).
_FIT_HARMONICS = 1
#: Most deviant views dropped before the final fit (highlights, glints).
_FIT_TRIM = 1


def _shading_fit_std(v_vis, v_sums, azimuth):
    """Spread of the per-view mean colours about a shading curve of the view's azimuth: (M,) grey levels.

    On a turntable with the lamp fixed to the camera, a surface point's
    brightness is a smooth periodic function of the table angle ``a``
    (Lambertian: a clipped cosine); a voxel that fills a concavity sees
    different surface points, whose colours do not follow one smooth curve.
    Per channel, a weighted least-squares fit of ``c0 + sum_k (ck cos ka +
    sk sin ka)``, ``k <= _FIT_HARMONICS``, over the views that see the voxel;
    the ``_FIT_TRIM`` most deviant views are dropped (highlights) and the
    curve refitted; the result is the weighted RMS of the residuals.  Voxels
    seen by fewer than ``_FIT_MIN_VIEWS`` views get the trimmed between-view
    spread.
    """
    w = v_vis.astype(np.float64)  # (V, M)
    with np.errstate(invalid="ignore", divide="ignore"):
        y = np.where(w[:, :, None] > 0, v_sums / np.maximum(w, 1)[:, :, None], 0.0)  # (V, M, C)
    a = np.asarray(azimuth, np.float64)
    cols = [np.ones_like(a)]
    for k in range(1, _FIT_HARMONICS + 1):
        cols += [np.cos(k * a), np.sin(k * a)]
    basis = np.stack(cols, axis=1)  # (V, P)
    P = basis.shape[1]
    n_views = np.count_nonzero(w > 0, axis=0)
    fit_ok = n_views >= _FIT_MIN_VIEWS
    out = _trimmed_std(v_vis, v_sums)
    if not fit_ok.any():
        return out
    w, y = w[:, fit_ok], y[:, fit_ok].copy()
    cols_m = np.arange(w.shape[1])
    for it in range(_FIT_TRIM + 1):
        A = np.einsum("vm,vi,vj->mij", w, basis, basis) + 1e-6 * np.eye(P)
        rhs = np.einsum("vm,vi,vmc->mic", w, basis, y)
        coef = np.linalg.solve(A, rhs)  # (M, P, C)
        r2 = ((y - np.einsum("vi,mic->vmc", basis, coef)) ** 2).mean(axis=2)  # (V, M)
        if it < _FIT_TRIM:
            worst = np.argmax(np.where(w > 0, r2, -1.0), axis=0)
            w = w.copy()
            w[worst, cols_m] = 0.0
    dof = np.maximum(np.count_nonzero(w > 0, axis=0) - P, 1) / np.maximum(np.count_nonzero(w > 0, axis=0), 1)
    out = out.copy()
    out[fit_ok] = np.sqrt((w * r2).sum(axis=0) / np.maximum(w.sum(axis=0), 1) / dof)
    return out
