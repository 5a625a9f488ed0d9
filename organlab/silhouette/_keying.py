"""Private workers of :mod:`organlab.silhouette`: keying against a backdrop in CIE Lab.

A view is compared with what the empty scene would show there: a per-pixel
background model (from background frames), or one backdrop colour (declared
in ``session.json``, or estimated from the image border).  Steps:

1. exposure: the view's gain against the background, the median luminance
   ratio over the image border band (clipped to 0.7-1.4), divides out;
2. distance: CIE76 colour difference (Delta E, Lab) to the background;
3. shadows: pixels darker than the background by a ratio in 0.12-0.97 whose
   rg-chromaticity matches it (and whose background is bright enough to
   carry a chromaticity) are cast shadow, not specimen;
4. threshold (automatic): from the border band's own Delta E -- its noise
   (median + 6 x 1.4826 MAD) and its clutter (99.5th percentile of the
   band's background-like pixels) -- and from the background next to the
   specimen (99th percentile in a ring 3-10 px outside the convex hull of a
   first, Li, silhouette: JPEG artefacts, flare), each with a margin of 1.5, capped
   by Li's threshold of the whole image; the reasons go into ``KeyInfo``;
5. clean-up scaled to the image: opening and closing radii and the largest
   hole filled grow with the square root of the raw silhouette's area (the
   specimen's size in pixels), so dark parts inside the specimen are kept.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Border band width, fraction of the image's smaller side.
BAND = 0.03
SHADOW_RATIO = (0.12, 0.97)
SHADOW_CHROMA = 0.035
#: Closing radius, fraction of sqrt(silhouette area).
CLOSE_SCALE = 0.012
#: Largest hole filled, fraction of the silhouette's area.
HOLE_FRACTION = 0.01
#: Threshold over the border band's clutter (its 99.5th percentile of Delta E)
#: and over the background next to the specimen (99th percentile in the ring).
CLUTTER_MARGIN = 1.5
#: Inner and outer radius (px) of the ring outside a first silhouette whose
#: background sets a floor under the threshold (JPEG blocks are 8-16 px).
RING_PX = (3, 10)


@dataclass(frozen=True)
class KeyInfo:
    """How a view was keyed (for the report)."""

    threshold: float
    reason: str
    noise: float | None
    clutter: float | None
    li: float | None
    gain: float
    shadow_fraction: float
    close_radius: int
    ring: float | None = None

    def to_dict(self):
        return {k: (round(v, 4) if isinstance(v, float) else v) for k, v in self.__dict__.items()}


def to_lab(rgb):
    """(H, W, 3) RGB 0-255 -> (H, W, 3) float32 Lab (L 0-100)."""
    import cv2

    a = np.clip(np.asarray(rgb, np.float32) / 255.0, 0.0, 1.0)
    return cv2.cvtColor(np.ascontiguousarray(a), cv2.COLOR_RGB2Lab)


def border_band(shape, *, fraction=BAND):
    """(H, W) bool: the band along the image border."""
    h, w = shape[:2]
    b = max(2, int(round(fraction * min(h, w))))
    m = np.zeros((h, w), bool)
    m[:b], m[-b:], m[:, :b], m[:, -b:] = True, True, True, True
    return m


def _rgb(image):
    a = np.asarray(image, np.float32)
    return np.repeat(a[..., None], 3, axis=2) if a.ndim == 2 else a


def estimate_backdrop(images):
    """A backdrop colour from the border bands of views: (3,) float RGB, the median band pixel."""
    px = np.concatenate([_rgb(im)[border_band(np.shape(im))] for im in images])
    return np.median(px, axis=0).astype(np.float32)


def _luma(rgb):
    return rgb @ np.array([0.299, 0.587, 0.114], np.float32)


def _gain(img, bg, band):
    li, lb = _luma(img[band]), _luma(bg[band])
    ok = lb > 10.0
    if np.count_nonzero(ok) < 100:
        return 1.0
    r = li[ok] / lb[ok]
    r = r[(r > 0.5) & (r < 2.0)]
    return float(np.clip(np.median(r), 0.7, 1.4)) if r.size >= 100 else 1.0


def _shadow(img, bg):
    li, lb = _luma(img) + 1.0, _luma(bg) + 1.0
    ratio = li / lb
    ci = img / (img.sum(axis=2, keepdims=True) + 3.0)
    cb = bg / (bg.sum(axis=2, keepdims=True) + 3.0)
    cd = np.abs(ci - cb).max(axis=2)
    return (ratio > SHADOW_RATIO[0]) & (ratio < SHADOW_RATIO[1]) & (cd < SHADOW_CHROMA) & (lb > 40.0)


def key_distance(image, background, *, shadows=True):
    """Delta E of a view to its background, with exposure divided out and shadows set to 0.

    Parameters
    ----------
    image : (H, W) or (H, W, 3) uint8
    background : (H, W) or (H, W, 3) float, or (3,) float (one backdrop colour)

    Returns
    -------
    dist : (H, W) float32, Delta E units
    gain : float
    shadow : (H, W) bool
    """
    img = _rgb(image)
    bg = np.asarray(background, np.float32)
    bg = np.broadcast_to(bg, img.shape) if bg.ndim == 1 else _rgb(bg)
    band = border_band(img.shape)
    g = _gain(img, bg, band)
    bg = bg * g
    d = np.linalg.norm(to_lab(img) - to_lab(bg), axis=2)
    sh = _shadow(img, bg) if shadows else np.zeros(d.shape, bool)
    d[sh] = 0.0
    return d.astype(np.float32), g, sh


def auto_key_threshold(dist):
    """The keying threshold of a Delta E image and its reasons.

    Returns
    -------
    threshold, reason, noise, clutter, li, ring : float, str, float, float, float, float or None
        ``ring`` is the near-specimen rule's value (None when it had no ring).
    """
    from skimage import filters

    band = border_band(dist.shape)
    li = float(filters.threshold_li(dist)) if float(dist.max()) > float(dist.min()) else 1.0
    b = dist[band]
    bgl = b[b < li]
    if bgl.size < 50:
        return li, "li (no background in the border band)", 0.0, 0.0, li, None
    med = float(np.median(bgl))
    noise = med + 6.0 * 1.4826 * float(np.median(np.abs(bgl - med)))
    clutter = float(np.percentile(bgl, 99.5))
    ring = _ring_level(dist, li)
    t = max(noise, CLUTTER_MARGIN * clutter, 1.0)
    reason = "border noise" if noise >= clutter else "border clutter"
    if ring is not None and CLUTTER_MARGIN * ring > t:
        t, reason = CLUTTER_MARGIN * ring, "background next to the specimen"
    if t >= li:
        return li, "li (below the background's noise and clutter)", noise, clutter, li, ring
    return t, reason, noise, clutter, li, ring


def _ring_level(dist, li):
    """99th percentile of Delta E in a ring RING_PX outside a first (Li) silhouette's convex hull, or None.

    The border band can be far cleaner than the background next to the
    specimen: JPEG ringing and blocking (8 x 8 px blocks, 16 x 16 px of
    chroma at 4:2:0), lens flare and soft shadows all gather at the
    specimen's edge, where a threshold from the border's noise takes them
    for specimen.
    """
    import cv2

    first, _ = clean_scaled(dist > li)
    if not first.any():
        return None
    # its convex hull: dark parts of the specimen that Li's threshold misses (a dark band across it)
    # lie inside, not in the ring
    pts = cv2.findNonZero(first.astype(np.uint8))
    f8 = cv2.fillConvexPoly(np.zeros(first.shape, np.uint8), cv2.convexHull(pts), 1)

    def grown(r):
        return cv2.dilate(f8, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))) > 0

    ring = grown(RING_PX[1]) & ~grown(RING_PX[0]) & (dist < li)
    return float(np.percentile(dist[ring], 99.0)) if np.count_nonzero(ring) >= 50 else None


def clean_scaled(raw):
    """Opening, components, closing and small-hole filling with radii from the silhouette's size."""
    import cv2

    m = np.asarray(raw, np.uint8)
    area = float(np.count_nonzero(m))
    if area == 0:
        return m.astype(bool), 0
    r = max(1, int(round(CLOSE_SCALE * np.sqrt(area))))
    m = cv2.morphologyEx(m, cv2.MORPH_OPEN, _disk(max(1, r // 2)))
    n, labels, stats, _ = cv2.connectedComponentsWithStats(m, connectivity=8)
    if n <= 1:
        return np.zeros(m.shape, bool), r
    areas = stats[1:, cv2.CC_STAT_AREA]
    keep = np.flatnonzero(areas >= 0.05 * areas.max()) + 1
    m = np.isin(labels, keep).astype(np.uint8)
    pad = r + 1
    mp = cv2.copyMakeBorder(m, pad, pad, pad, pad, cv2.BORDER_REPLICATE)
    m = cv2.morphologyEx(mp, cv2.MORPH_CLOSE, _disk(r))[pad:-pad, pad:-pad]
    inv = (m == 0).astype(np.uint8)
    n2, lab2, st2, _ = cv2.connectedComponentsWithStats(inv, connectivity=4)
    border = np.unique(np.concatenate([lab2[0], lab2[-1], lab2[:, 0], lab2[:, -1]]))
    small = np.flatnonzero(st2[:, cv2.CC_STAT_AREA] <= HOLE_FRACTION * np.count_nonzero(m))
    holes = np.isin(lab2, np.setdiff1d(small, border)) & (inv > 0)
    return (m > 0) | holes, r


def _disk(radius):
    import cv2

    r = int(radius)
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))


def key(image, background, *, threshold=None, shadows=True):
    """Keyed silhouette of one view: ``(mask (H, W) bool, dist (H, W) float32, KeyInfo)``."""
    d, g, sh = key_distance(image, background, shadows=shadows)
    if threshold is None:
        t, reason, noise, clutter, li, ring = auto_key_threshold(d)
    else:
        t, reason, noise, clutter, li, ring = float(threshold), "given", None, None, None, None
    mask, r = clean_scaled(d > t)
    info = KeyInfo(float(t), reason, noise, clutter, li, g, float(sh.mean()), r, ring)
    return mask, d, info
