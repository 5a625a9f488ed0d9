"""Colouring without a cliff: measured noise, exposure per view, the automatic threshold, the silhouette guard.

* noise: Immerkaer's robust estimate of the pixel noise (a Laplacian-
  difference kernel that cancels smooth image content), the median over the
  views, grey levels;
* exposure: every view's gain, the median over the hull's surface voxels
  seen by at least 3 views of (the view's mean colour / the voxel's mean
  colour); the views are divided by it;
* automatic threshold: on the hull's surface voxels (most of which lie on the
  true surface: only the concavities' lids do not), the consistency measure's
  median + ``AUTO_K`` robust deviations (1.4826 MAD), and at least
  ``NOISE_K`` times the noise; the hull's lid voxels over a concavity stand
  out above it;
* automatic support: the hull surface's measure has a robust spread (its
  median and MAD, as for the automatic threshold); the fewer robust
  deviations ``z`` a threshold lies above that median, the more of the
  consistent surface's voxels exceed it by chance (self shadows, highlights,
  scattered over the true surface), while a concavity's lid exceeds it as a
  region.  A carve then needs ``DEFAULT_SUPPORT + ceil(AUTO_K - z)``
  inconsistent voxels of its 3 x 3 neighbourhood (one more per deviation
  below the automatic threshold's ``AUTO_K``), between ``DEFAULT_SUPPORT``
  and 9: the plain support at and above the automatic threshold;
* guard: the pixels of a view's silhouette that the hull's voxels explained
  (the union of their projected boxes covers them) must stay explained; the
  carved voxels whose projected bounding box touches a pixel the carved model
  leaves unexplained are put back, so the model still projects onto every
  silhouette pixel the hull did.
"""

from __future__ import annotations

import numpy as np

from ..raster import model_mask

#: Automatic threshold: median + AUTO_K robust standard deviations of the hull surface's measure.
AUTO_K = 6.0
#: ... and at least NOISE_K times the pixel noise.
NOISE_K = 3.0


def image_noise(stack):
    """Pixel noise, grey levels: the median over views of Immerkaer's estimate. ``stack (V, H, W, C) uint8``."""
    import cv2

    kern = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], np.float32)
    out = []
    for img in stack:
        g = img.astype(np.float32).mean(axis=2)
        r = cv2.filter2D(g, -1, kern)[1:-1, 1:-1]
        out.append(np.sqrt(np.pi / 2.0) * np.abs(r).mean() / 6.0)
    return float(np.median(out))


def exposure_gains(st, min_views=3, iterations=8):
    """Per-view gains ``(V,)`` from a pooled :class:`_Stats` of surface voxels (1 where unknown).

    Alternates the voxels' mean brightness (over the views, each divided by
    its gain) and each view's gain (the median ratio of its brightness to the
    voxels' means), so that a voxel seen only by bright views does not bias
    its neighbours' views; normalised to a geometric mean of 1.
    """
    V = st.v_vis.shape[0]
    vis = st.v_vis > 0
    ok = np.count_nonzero(vis, axis=0) >= min_views
    gains = np.ones(V)
    if not ok.any():
        return gains
    w = st.v_vis[:, ok].astype(np.float64)
    luma = st.v_sums[:, ok].mean(axis=2) / np.maximum(w, 1)  # (V, M) per-view mean grey
    for _ in range(iterations):
        mean = (w * luma / gains[:, None]).sum(axis=0) / np.maximum(w.sum(axis=0), 1)
        for v in range(V):
            sel = (w[v] > 0) & (mean > 10.0)
            if np.count_nonzero(sel) >= 20:
                gains[v] = float(np.median(luma[v, sel] / mean[sel]))
        gains = gains / np.exp(np.mean(np.log(gains)))
    return gains


def normalise(stack, gains):
    """Divide each view by its gain; ``(V, H, W, C) uint8`` -> same."""
    out = np.empty_like(stack)
    for v, g in enumerate(gains):
        out[v] = np.clip(np.rint(stack[v] / g), 0, 255).astype(np.uint8)
    return out


def auto_threshold(st, measure, noise, min_pix):
    """The automatic threshold from the hull surface's statistics; returns (threshold, details dict)."""
    tested = st.n_vis >= max(min_pix, 1)
    s = st.std(measure)[tested & (np.count_nonzero(st.v_vis > 0, axis=0) >= 2)]
    if s.size < 20:
        return max(NOISE_K * noise, 1.0), {"noise": noise, "median": None, "mad": None}
    med = float(np.median(s))
    mad = 1.4826 * float(np.median(np.abs(s - med)))
    t = max(med + AUTO_K * mad, NOISE_K * noise, 1.0)
    return t, {"noise": noise, "median": med, "mad": mad}


def auto_support(threshold, details, base, most=9):
    """The support for ``threshold`` from the surface's median and robust deviation (``details`` of auto_threshold)."""
    med, mad = details.get("median"), details.get("mad")
    if med is None or not mad or mad <= 0:
        return int(base)
    z = (float(threshold) - med) / mad
    return int(np.clip(base + np.ceil(AUTO_K - z - 1e-6), base, most))  # 1e-6: the automatic threshold itself -> base


def guard(occ, candidates, cameras, grid, masks):
    """Put back carved voxels so that every silhouette pixel the candidates explained stays explained.

    Returns the new occupancy and the number of voxels put back.
    """
    carved = candidates & ~occ
    if not carved.any():
        return occ, 0
    ijk = np.argwhere(carved)
    h = grid.voxel_size
    centres = np.asarray(grid.origin) + ijk * h
    offs = np.array([[dx, dy, dz] for dx in (-0.5, 0.5) for dy in (-0.5, 0.5) for dz in (-0.5, 0.5)]) * h
    corners = (centres[:, None, :] + offs[None]).reshape(-1, 3)
    restore = np.zeros(len(ijk), bool)
    for cam, m in zip(cameras, masks):
        m = np.asarray(m, bool)
        lost = m & model_mask(candidates, cam, grid=grid) & ~model_mask(occ, cam, grid=grid)
        if not lost.any():
            continue
        H, W = lost.shape
        sat = np.zeros((H + 1, W + 1), np.int64)
        sat[1:, 1:] = lost.cumsum(0).cumsum(1)
        uv = cam.project(corners).reshape(-1, 8, 2)
        lo = np.floor(np.nanmin(uv, axis=1) + 0.5).astype(np.int64)  # pixel centres inside the box
        hi = np.ceil(np.nanmax(uv, axis=1) - 0.5).astype(np.int64)
        u0, v0 = np.clip(lo[:, 0], 0, W), np.clip(lo[:, 1], 0, H)
        u1, v1 = np.clip(hi[:, 0] + 1, 0, W), np.clip(hi[:, 1] + 1, 0, H)
        ok = (u1 > u0) & (v1 > v0)
        count = np.where(ok, sat[v1, u1] - sat[v0, u1] - sat[v1, u0] + sat[v0, u0], 0)
        restore |= count > 0
    out = occ.copy()
    r = ijk[restore]
    out[r[:, 0], r[:, 1], r[:, 2]] = True
    return out, int(np.count_nonzero(restore))
