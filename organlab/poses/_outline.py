"""Sub-pixel outlines for the epipolar tangents: the edge pixels' coverage re-estimated colour by colour.

The silhouettes' coverage (:func:`organlab.silhouette.coverage`) explains an
edge pixel as the blend ``I = a F + (1 - a) B`` of the background ``B`` and
*one* specimen colour ``F``: the mean of the pixels wholly inside within a
5 x 5 window.  On a textured specimen that mean mixes colours the edge pixel
does not show (a dark red patch at the edge, a pale one 2 px inside), and
``a`` is then wrong by up to 0.5: measured on the ``aaa-7`` renders at
640 x 480, coverage error RMS 0.17 on the edge pixels.  Carving hardly
notices (a pixel's error averages out over the outline), but the tangents
read the outline's convex hull, and those errors, largest on the dark-red
iliac legs standing on the grey plate, tilted the refined camera by 0.9
degrees (docs/trust.md, "Poses that correct themselves").

Here each edge pixel keeps, among the pixels wholly inside within
:data:`RADIUS` px, the colours that explain it as a blend with its
background (the residual ``|I - B - a (F_k - B)|`` near the smallest one,
within :data:`TAU` grey levels), nearer ones weighing more (``1 / d^2``),
and its coverage is their weighted ``a``: error RMS 0.10 on the same pixels,
and the fitted tilt 0.27 degrees against a true 0.30 (1.19 before).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit

from ..nbcam import undistort_points
from ..raster import iso_contours
from ._tangents import _profile_points

#: Pixels wholly inside within this many px (Chebyshev) of an edge pixel are its candidate colours.
RADIUS = 2
#: Residual scale, grey levels: about the residual of the right colour under 1 grey level of noise per channel
#: (``sqrt(3 (1 + a^2))``); candidates whose blend residual exceeds the best one's by a few TAU weigh nothing.
#: Measured at 640 x 480 (drifting ``dented`` tables, angle error median / max): 4 gave 0.17 / 0.54 and
#: 0.15 / 0.49 degrees on two renders, 2 gave 0.14 / 0.48 and 0.13 / 0.48 (the bumped ``aaa-7``'s tilt
#: 0.30 and 0.27 degrees, true 0.30).
TAU = 2.0


def edge_coverage(image, background, mask, *, radius: int | None = None, tau: float | None = None) -> np.ndarray:
    """Coverage of a silhouette's edge pixels from the colours nearby that explain each.

    Parameters
    ----------
    image : (H, W, 3) or (H, W) uint8
        The view.
    background : (H, W, 3) or (H, W) float
        The empty scene's model, same channels as ``image``.
    mask : (H, W) bool
        The silhouette (its edge band, 1 px either side, is re-estimated).
    radius : int, optional
        Candidate colours within this Chebyshev distance, px (default :data:`RADIUS`).
    tau : float, optional
        Residual scale, grey levels (default :data:`TAU`).

    Returns
    -------
    (H, W) float32 in [0, 1]
        1 inside, 0 outside, the blend fraction on the edge band.

    Examples
    --------
    >>> import numpy as np
    >>> bg = np.full((8, 8, 3), 40.0)
    >>> img = np.full((8, 8, 3), 40, np.uint8); img[:, 4:] = (200, 60, 60); img[:, 3] = (120, 50, 50)
    >>> cov = edge_coverage(img, bg, img[..., 0] > 80)
    >>> float(cov[4, 2]), float(cov[4, 3]), float(cov[4, 4])
    (0.0, 0.5, 1.0)
    """
    radius = RADIUS if radius is None else int(radius)
    tau = TAU if tau is None else float(tau)
    if radius < 1 or not tau > 0:
        raise ValueError(f"need radius >= 1 px and tau > 0 grey levels, got {radius} and {tau}")
    img, bg, m8 = _checked(image, background, mask)
    return _edge_box(img, bg, m8, radius, tau).frame()


def _checked(image, background, mask):
    """``(image, background, mask)`` of :func:`edge_coverage` as ``(H, W, C)``, ``(H, W, C)`` and ``(H, W)`` uint8."""
    img = np.asarray(image)
    bg = np.asarray(background)
    if img.ndim == 2:
        img = img[..., None]
    if bg.ndim == 2:
        bg = bg[..., None]
    if img.shape != bg.shape:
        raise ValueError(f"image {img.shape} and background {bg.shape} differ in shape")
    m8 = np.asarray(mask, np.uint8)
    if m8.shape != img.shape[:2]:
        raise ValueError(f"mask {m8.shape} and image {img.shape[:2]} differ in size")
    return img, bg, m8


def _edge_box(img, bg, m8, radius=RADIUS, tau=TAU):
    """:func:`edge_coverage` on the box about the silhouette only (checked inputs: ``(H, W, C)`` image and background,
    ``(H, W)`` uint8 mask): a :class:`_Box`, empty for an empty mask.  The poses check reads the box
    (:func:`organlab.poses._refine._outline_rays`) without the whole frame's 1.2 MB."""
    rows, cols = np.flatnonzero(m8.any(axis=1)), np.flatnonzero(m8.any(axis=0))  # the box (np.nonzero: 5 ms a frame)
    if rows.size == 0:
        return _Box(np.zeros((0, 0), np.float32), 0, 0, m8.shape)
    pad = int(radius) + 2
    h, w = m8.shape
    r0, r1 = max(rows.min() - pad, 0), min(rows.max() + pad + 1, h)
    c0, c1 = max(cols.min() - pad, 0), min(cols.max() + pad + 1, w)
    cov = _edge_coverage(img[r0:r1, c0:c1], bg[r0:r1, c0:c1], m8[r0:r1, c0:c1], int(radius), float(tau))
    return _Box(cov, int(r0), int(c0), m8.shape)


class _Box(NamedTuple):
    """A view's coverage on a box of its frame, 0 outside (:func:`_edge_box`): what :func:`edge_coverage`
    returns, without the whole frame (1.2 MB at 640 x 480, 2 ms a view to make and scan again)."""

    cov: np.ndarray  # (h, w) float32
    r0: int
    c0: int
    shape: tuple  # the frame's (H, W)

    def frame(self):
        """The whole frame's coverage (:func:`edge_coverage`)."""
        out = np.zeros(self.shape, np.float32)
        out[self.r0 : self.r0 + self.cov.shape[0], self.c0 : self.c0 + self.cov.shape[1]] = self.cov
        return out


def _edge_coverage(img, bg, m8, radius, tau):
    """:func:`edge_coverage` on the silhouette's box: the band found here, each band pixel's estimate in numba
    (:func:`_band_coverage`; the numpy version spent 5 ms a 640 x 480 view on its (pixels, candidates, channels)
    temporaries)."""
    import cv2

    k = np.ones((3, 3), np.uint8)
    inner = cv2.erode(m8, k, borderType=cv2.BORDER_REPLICATE)
    band = cv2.dilate(m8, k) & (inner == 0)
    off = np.array([(dy, dx) for dy in range(-radius, radius + 1) for dx in range(-radius, radius + 1) if dy or dx],
                   np.int64)
    # the pixel values as they are (uint8 image, float32 or float64 background): converted to float64 per use;
    # contiguous copies of the box: the kernel's one specialisation (:func:`warm_kernels`)
    img = np.ascontiguousarray(img)
    bg = np.ascontiguousarray(bg) if bg.dtype in (np.float32, np.float64) else np.ascontiguousarray(bg, np.float64)
    return _band_coverage(img, bg, np.ascontiguousarray(m8), inner, band, off, tau)


def warm_kernels() -> None:
    """Load the edge coverage's kernel (and the outline rays', 20 ms more) from numba's cache ahead of the poses stage.

    Loading it is 45 ms CPU in a fresh process (numba's registries already loaded, measured); the
    ``reconstruct`` command does it on a thread while the session's images are decoded.  A tiny view of
    the dtypes the stage passes (uint8 image, float32 background model): the same specialisation.
    """
    img = np.zeros((6, 6, 3), np.uint8)
    img[2:4, 2:4] = 200
    edge_coverage(img, np.zeros((6, 6, 3), np.float32), img[..., 0] > 0)
    iso_contours(np.zeros((2, 2)), 0.5)  # organlab.poses._tangents.outline_rays': the contours, the points, the undistortion
    _profile_points(np.zeros((8, 8)), np.full((1, 2), 3.5), 3)
    dist = np.ones(5)
    dist.flags.writeable = False  # the stage passes the camera's read-only ``dist``: that specialisation
    undistort_points(np.zeros((1, 2)), dist)


@njit(cache=True, nogil=True)
def _band_coverage(img, bg, m8, inner, band, off, tau):
    """1 on ``inner``, 0 off the silhouette, each ``band`` pixel's coverage from its candidate colours."""
    h, w, nc = img.shape
    k = off.shape[0]
    cov = np.zeros((h, w), np.float32)
    a = np.empty(k)
    e = np.empty(k)
    okk = np.zeros(k, np.bool_)
    dI = np.empty(nc)
    dF = np.empty(nc)
    b = np.empty(nc)
    for r in range(h):
        for c in range(w):
            if inner[r, c]:
                cov[r, c] = 1.0
                continue
            if not band[r, c]:
                continue
            for ch in range(nc):
                b[ch] = np.float64(bg[r, c, ch])
                dI[ch] = np.float64(img[r, c, ch]) - b[ch]
            e_min = np.inf
            for j in range(k):
                rr = min(max(r + off[j, 0], 0), h - 1)
                cc = min(max(c + off[j, 1], 0), w - 1)
                okk[j] = False
                if inner[rr, cc] == 0:
                    continue
                den = 0.0
                num = 0.0
                for ch in range(nc):
                    dF[ch] = np.float64(img[rr, cc, ch]) - b[ch]
                    den += dF[ch] * dF[ch]
                    num += dI[ch] * dF[ch]
                if not den > 1.0:
                    continue
                okk[j] = True
                aj = min(max(num / den, 0.0), 1.0)
                ej = 0.0
                for ch in range(nc):
                    q = dI[ch] - aj * dF[ch]
                    ej += q * q
                a[j] = aj
                e[j] = ej
                if ej < e_min:
                    e_min = ej
            if not np.isfinite(e_min):  # no candidate (no inside pixel near, or no contrast): the mask
                cov[r, c] = m8[r, c]
                continue
            sw = 0.0
            swa = 0.0
            for j in range(k):
                if okk[j]:
                    wt = np.exp(-0.5 * (e[j] - e_min) / tau**2) / (off[j, 0] ** 2 + off[j, 1] ** 2)
                    sw += wt
                    swa += wt * a[j]
            cov[r, c] = swa / max(sw, 1e-300)
    return cov
