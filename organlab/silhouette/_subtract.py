"""Silhouettes: background model, subtraction, threshold, clean-up.

The specimen's silhouette in a view is where the view differs from the empty
scene.  The stage is a chain of small functions::

    bg = background_model(frames)                 # mean or median of empty frames
    diff = difference(image, bg)                  # grey or colour distance
    t = auto_threshold(diff)                      # Li's, or a value picked by the user
    mask = clean_mask(diff > t)                   # opening, closing, components, holes
    mask = grow_rim(mask, diff, image, bg, noise=n)  # its dim rim (hysteresis down to 3 noise sigmas)
    cov = coverage(image, bg, mask)               # sub-pixel silhouette in [0, 1]

:func:`silhouettes` runs it for every view of a session, using a
view's own ``mask`` where the session gives one.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, Literal

import numpy as np

from ..masks import Silhouette
from ._kernels import color_distance, median_frames, split_above, std_frames

__all__ = [
    "background_model",
    "background_noise",
    "difference",
    "auto_threshold",
    "clean_mask",
    "grow_rim",
    "coverage",
    "silhouette",
]

#: grow_rim: the low threshold in units of the background noise (a colour distance of 3 noise
#: standard deviations: 6e-6 of the background's pixels, as chi with 3 degrees of freedom).
RIM_LOW = 3.0
#: grow_rim: a grown pixel shows at least this fraction of the largest difference of the silhouette's
#: pixels next to it (a pixel covered by a fraction ``a`` of the specimen shows ``a`` times its contrast).
RIM_FRACTION = 0.5
#: grow_rim: the rim is grown at most this many pixels out from the silhouette.
RIM_DEPTH = 10
#: grow_rim: where it grew, one last ring of pixels showing at least this fraction of their silhouette
#: neighbours' largest difference (the outline's pixels: partly covered, and shaded more than the pixels inside).
RIM_OUTER = 0.35


def _stack(frames):
    frames = list(frames)
    if not frames:
        raise ValueError("at least one background frame is needed")
    shapes = {f.shape for f in frames}
    if len(shapes) != 1:
        raise ValueError(f"background frames differ in shape: {sorted(shapes)}")
    return np.stack([np.asarray(f) for f in frames])


def background_model(frames: Sequence[np.ndarray], *, method: Literal["median", "mean"] = "median") -> np.ndarray:
    """Model of the empty scene from several frames.

    Parameters
    ----------
    frames : sequence of (H, W) or (H, W, 3) uint8
        Images of the empty scene (no specimen), same size.
    method : {'median', 'mean'}
        Per-pixel statistic.  The median ignores a passing disturbance in a
        few frames; the mean averages the noise down a little further.

    Returns
    -------
    background : (H, W) or (H, W, 3) float32
    """
    stack = _stack(frames)
    if method == "median":
        if stack.dtype == np.uint8:
            return _median_uint8(stack)
        return np.median(stack, axis=0).astype(np.float32)
    if method == "mean":
        return stack.mean(axis=0, dtype=np.float64).astype(np.float32)
    raise ValueError(f"method must be 'median' or 'mean', got {method!r}")


def background_noise(frames: Sequence[np.ndarray]) -> float:
    """Typical pixel noise of the background frames, grey levels.

    Parameters
    ----------
    frames : sequence of (H, W) or (H, W, 3) uint8

    Returns
    -------
    float
        Median over pixels of the per-pixel standard deviation across frames
        (averaged over channels); 0 for a single frame.
    """
    stack = _stack(frames)
    if len(stack) < 2:
        return 0.0
    if stack.dtype == np.uint8:  # a numba kernel, the same values, without the stack's float32 copy
        n = stack.shape[0]
        sd = std_frames(np.ascontiguousarray(stack).reshape(n, -1)).reshape(stack.shape[1:])
    else:
        sd = stack.astype(np.float32).std(axis=0, ddof=1)
    if sd.ndim == 3:
        sd = sd.mean(axis=2)
    return float(np.median(sd))


def difference(image: np.ndarray, background: np.ndarray, *, mode: Literal["color", "grey"] = "color") -> np.ndarray:
    """Per-pixel distance between an image and the background model.

    Parameters
    ----------
    image : (H, W) or (H, W, 3) uint8
    background : (H, W) or (H, W, 3) float
    mode : {'color', 'grey'}
        ``'color'``: Euclidean distance of the RGB vectors divided by
        sqrt(3) (so a grey change of d levels gives d); ``'grey'``: absolute
        difference of the luminances.

    Returns
    -------
    diff : (H, W) float32, grey levels
    """
    if mode not in ("color", "grey"):
        raise ValueError(f"mode must be 'color' or 'grey', got {mode!r}")
    fast = _color_distance_uint8(image, background) if mode == "color" else None
    if fast is not None:
        return fast
    img = np.asarray(image, dtype=np.float32)
    bg = np.asarray(background, dtype=np.float32)
    if img.shape[:2] != bg.shape[:2]:
        raise ValueError(f"image {img.shape[:2]} and background {bg.shape[:2]} differ in size")
    if img.ndim == 3 and bg.ndim == 2:
        img = _luma(img)
    elif img.ndim == 2 and bg.ndim == 3:
        bg = _luma(bg)
    if img.ndim == 3 and mode == "grey":
        img, bg = _luma(img), _luma(bg)
    d = img - bg
    if d.ndim == 3:
        return (np.sqrt((d * d).sum(axis=2)) / np.sqrt(3.0)).astype(np.float32)
    return np.abs(d)


def _median_uint8(stack):
    """``np.median(stack, axis=0).astype(np.float32)`` of uint8 frames, by a numba kernel (same values)."""
    n = stack.shape[0]
    return median_frames(np.ascontiguousarray(stack).reshape(n, -1)).reshape(stack.shape[1:])


def _color_distance_uint8(image, background):
    """:func:`difference`'s colour distance by a numba kernel (same values), or None when it does not apply."""
    img = np.asarray(image)
    bg = np.asarray(background)
    if img.dtype != np.uint8 or img.ndim != 3 or img.shape[2] != 3 or bg.shape != img.shape:
        return None
    return color_distance(np.ascontiguousarray(img), np.ascontiguousarray(bg, dtype=np.float32))


def _luma(rgb):
    return rgb @ np.array([0.299, 0.587, 0.114], dtype=np.float32)


def auto_threshold(diff: np.ndarray, *, method: Literal["li", "otsu", "triangle"] = "li", floor: float = 0.0) -> float:
    """Automatic threshold of a difference image.

    Parameters
    ----------
    diff : (H, W) float
        From :func:`difference`.
    method : {'li', 'otsu', 'triangle'}
        ``'li'`` (default): Li's minimum cross-entropy threshold, which stays
        low enough to keep a specimen's dark or background-like parts while
        the background fills most of the image (on the synthetic phantom it
        misclassifies 1.5 % of the silhouette's pixels, Otsu's 20 %).
        ``'otsu'``: Otsu's between-class variance; ``'triangle'``: Zack's
        triangle method (close to the noise level).
    floor : float
        Lowest threshold returned, e.g. a multiple of the background noise.

    Returns
    -------
    threshold : float, grey levels
    """
    d = np.asarray(diff, dtype=np.float32)
    lo, hi = float(d.min()), float(d.max())  # NaN propagates into both, an infinity into one: no isfinite pass
    if not (np.isfinite(lo) and np.isfinite(hi)):
        raise ValueError("difference image has non-finite values")
    if hi - lo < 1e-6:
        raise ValueError("difference image is constant: the view does not differ from the background")
    if method not in ("li", "otsu", "triangle"):
        raise ValueError(f"method must be one of ['li', 'otsu', 'triangle'], got {method!r}")
    if method == "li":  # our own: skimage.filters is not imported (it imports scipy.ndimage: 0.15 s CPU, issue 24)
        return max(float(_li_threshold(d)), float(floor))
    from skimage import filters

    return max(float(getattr(filters, f"threshold_{method}")(d)), float(floor))


def _li_threshold(d):
    """Li's minimum cross-entropy threshold of a finite, non-constant float32 image: the float32 value
    ``skimage.filters.threshold_li(d)`` returns, to the bit, at about 3/4 of its CPU.

    Li's iteration (Li and Tam 1998): from the mean, ``t <- (m_b - m_f) / (log m_b - log m_f)``
    with ``m_f``, ``m_b`` the means above and at or below ``t`` (the values shifted to a minimum of 0), until
    ``t`` moves by at most half the smallest gap between two values.  The same float32 operations on the
    same arrays as scikit-image's (the means by ``np.mean`` over the values in image order), without
    its NaN and infinity copies (``auto_threshold`` checked the image finite and not constant), the two
    sides split in one pass (:func:`~organlab.silhouette._kernels.split_above`), the smallest gap from
    the sorted values instead of ``np.unique`` (the same consecutive distinct values).  The sample's 36
    views: 0.151-0.156 -> 0.109-0.123 s CPU, best of 5 on a loaded 2-core machine (tests/test_silhouette.py
    checks the values against scikit-image's).
    """
    lo = np.min(d)
    x = d.ravel() - lo  # float32, in C order as scikit-image's boolean-indexed copy
    gaps = np.diff(np.sort(x))
    tolerance = np.min(gaps[gaps > 0]) / 2
    t_next = np.mean(x)
    t_curr = -2 * tolerance
    above, below = np.empty_like(x), np.empty_like(x)
    while abs(t_next - t_curr) > tolerance:
        t_curr = t_next
        na, nb = split_above(x, np.float32(t_curr), above, below)
        mean_fore = np.mean(above[:na])
        mean_back = np.mean(below[:nb])
        if mean_back == 0.0:
            break
        t_next = (mean_back - mean_fore) / (np.log(mean_back) - np.log(mean_fore))
    return t_next + lo


def _disk(radius):
    import cv2

    r = int(radius)
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))


def clean_mask(mask: np.ndarray, *, open_radius: int = 1, close_radius: int = 2, min_area_fraction: float = 0.05,
               fill_holes: bool = True) -> np.ndarray:
    """Clean a raw thresholded silhouette.

    Morphological opening removes isolated noise pixels, closing bridges
    hairline cracks; then only the connected components that belong to the
    specimen are kept (the largest and any at least ``min_area_fraction`` of
    its area: a specimen may show as several parts, noise blobs are small),
    and holes wholly inside the silhouette are filled.

    Parameters
    ----------
    mask : (H, W) bool
    open_radius, close_radius : int, px
        Radii of the disk structuring elements (0 disables the step).
    min_area_fraction : float
        Components smaller than this fraction of the largest are dropped.
    fill_holes : bool
        Fill background regions that do not touch the image border.

    Returns
    -------
    (H, W) bool
    """
    import cv2

    m = np.asarray(mask).astype(np.uint8)
    if m.ndim != 2:
        raise ValueError(f"mask must be 2-D, got shape {m.shape}")
    if open_radius > 0:
        m = cv2.morphologyEx(m, cv2.MORPH_OPEN, _disk(open_radius))
    # everything after the opening happens within the opened mask's box, widened so that
    # the closing and the hole filling see what they would see in the whole image
    box = _box(m, 2 * max(int(close_radius), 0) + 2)
    out = np.zeros(m.shape, dtype=bool)
    if box is None:
        return out
    crop = m[box]
    if close_radius > 0:
        crop = cv2.morphologyEx(crop, cv2.MORPH_CLOSE, _disk(close_radius))
    kept = _keep_components(crop, min_area_fraction)
    if kept is None:
        return out
    out[box] = _fill_holes(kept) if fill_holes else kept
    return out


def _box(mask, margin):
    """Slices of the box of a mask's non-zero pixels widened by ``margin`` px (None when empty)."""
    import cv2

    x, y, w, h = cv2.boundingRect(mask)
    if w == 0 or h == 0:
        return None
    H, W = mask.shape
    return slice(max(y - margin, 0), min(y + h + margin, H)), slice(max(x - margin, 0), min(x + w + margin, W))


def _keep_components(m, min_area_fraction):
    """The 8-connected components of a uint8 mask at least ``min_area_fraction`` of the largest (None if none)."""
    import cv2

    n, labels, stats, _ = cv2.connectedComponentsWithStats(m, connectivity=8)
    if n <= 1:
        return None
    areas = stats[1:, cv2.CC_STAT_AREA]
    lut = np.zeros(n, dtype=bool)
    lut[1:] = areas >= min_area_fraction * areas.max()
    return lut[labels]


def _fill_holes(out):
    """Fill the background regions (4-connected) that do not touch the border of the array."""
    import cv2

    inv = (~out).astype(np.uint8)
    n, lab2 = cv2.connectedComponents(inv, connectivity=4)
    border = np.zeros(n, dtype=bool)
    border[lab2[0]] = border[lab2[-1]] = border[lab2[:, 0]] = border[lab2[:, -1]] = True
    border[0] = True  # label 0: the silhouette itself
    return out | ~border[lab2]


def grow_rim(mask: np.ndarray, diff: np.ndarray, image: np.ndarray | None = None, background: np.ndarray | None = None,
             *, noise: float, low: float = RIM_LOW, fraction: float = RIM_FRACTION, depth: int = RIM_DEPTH,
             fill_holes: bool = True, outer: float = RIM_OUTER) -> np.ndarray:
    """Keep the dim rim of a silhouette: the pixels connected to it that differ clearly from the background.

    Hysteresis thresholding: the silhouette (pixels above the view's threshold, cleaned) is the seed;
    it grows, one pixel ring at a time and at most ``depth`` rings, into the pixels whose difference
    exceeds ``low`` times the background ``noise`` and at least ``fraction`` of the largest
    difference of the silhouette's pixels next to them.  A specimen shaded toward its outline (a head
    lamp, a dark backdrop) shows a band there whose contrast falls below a global threshold while it
    is still far above the background's noise; its difference falls smoothly, pixel to pixel, so it
    passes the second test.  A pixel that the specimen covers by a fraction ``a`` shows ``a`` times
    the contrast of the pixels inside it: the second test refuses the ones covered by less than
    about ``fraction``, so a correct silhouette is not grown.  Where it grew, one last ring takes the
    candidates showing at least ``outer`` of that difference: the outline's own pixels, covered
    0.5-0.75 and shaded more than the pixels inside them (the shade keeps falling across the outline),
    which the ``fraction`` test refuses; where nothing grew (an exact mask, an evenly lit specimen)
    there is no last ring.  Pixels that look like a shadow on the background (colour images: a darker
    copy of the background's colour, within the same tolerance) are never added.

    Parameters
    ----------
    mask : (H, W) bool
        The silhouette, e.g. from :func:`clean_mask`.
    diff : (H, W) float
        The view's :func:`difference` image, grey levels.
    image : (H, W, 3) uint8, optional
        The view; with ``background``, the shadow test (grey views: no shadow test).
    background : (H, W, 3) float, optional
        The background model.
    noise : float, grey levels
        The background's pixel noise (:func:`background_noise`); <= 0 returns the mask unchanged.
    low : float
        The low threshold, in units of ``noise``.
    fraction : float
        In (0, 1]: a grown pixel's difference against the largest of its silhouette neighbours'.
    depth : int, px
        Rings grown at most, the last ring included (0 returns the mask unchanged).
    fill_holes : bool
        Fill the background regions the growth encloses (as :func:`clean_mask`).
    outer : float
        In (0, ``fraction``]: the last ring's fraction, within ``depth`` px of the pixels grown
        (``fraction``: no last ring).  0.35 took the rim-shaded ``aaa-3`` render (36 views, 1 mm)
        from -1.20 % to -0.24 % volume (0.25: +0.24 %, but it grew evenly lit masks).

    Returns
    -------
    (H, W) bool
        The mask, grown (a new array; the inputs are not changed).

    Examples
    --------
    >>> import numpy as np
    >>> diff = np.zeros((9, 12), np.float32)
    >>> diff[2:7, 2:6] = 40.0                  # the lit specimen
    >>> diff[2:7, 6:9] = [30.0, 22.0, 15.0]    # its rim, shaded toward the outline
    >>> diff[2:7, 9] = 5.0                     # the outline pixel, covered by about a third
    >>> mask = diff > 25.0                     # a global threshold keeps the lit part only
    >>> grown = grow_rim(mask, diff, noise=1.5)
    >>> int(mask.sum()), int(grown.sum()), bool(grown[:, 9].any())
    (25, 35, False)
    """
    import cv2

    m = np.asarray(mask, dtype=bool)
    d_all = np.asarray(diff, dtype=np.float32)
    if m.shape != d_all.shape:
        raise ValueError(f"mask {m.shape} and diff {d_all.shape} differ in size")
    if not 0 < float(fraction) <= 1:
        raise ValueError(f"fraction must be in (0, 1], got {fraction}")
    if not 0 < float(outer) <= float(fraction):
        raise ValueError(f"outer must be in (0, fraction], got {outer} (fraction {fraction})")
    out = m.copy()
    if not (float(noise) > 0 and int(depth) > 0 and m.any()):
        return out
    box = _box(m.view(np.uint8), int(depth) + 2)
    mb = m[box].astype(np.uint8)
    d = d_all[box]
    cand = (d > float(low) * float(noise)) & (mb == 0)
    # only pixels within `depth` rings can be reached
    reach = 2 * int(depth) + 1
    cand &= cv2.dilate(mb, cv2.getStructuringElement(cv2.MORPH_RECT, (reach, reach))).astype(bool)
    if cand.any() and image is not None and background is not None and np.ndim(image) == 3 and np.ndim(background) == 3:
        rows, cols = np.nonzero(cand)
        img, bg = np.asarray(image)[box], np.asarray(background)[box]
        shade = _shadow_like(img[rows, cols], bg[rows, cols], float(low) * float(noise))
        cand[rows[shade], cols[shade]] = False
    if not cand.any():
        return out
    k = np.ones((3, 3), np.uint8)
    sub = _box(cand.view(np.uint8), 2)  # the growth happens only about the candidates (their 3 x 3 squares inside)
    m_s, d_s, c_s = mb[sub], d[sub], cand[sub]  # views: the growth writes into mb
    dm = np.where(m_s != 0, d_s, 0.0).astype(np.float32)
    frac = np.float32(fraction)
    grew = False
    rings = 0
    while rings < int(depth):
        front = c_s & cv2.dilate(m_s, k).astype(bool)
        if not front.any():
            break
        ref = cv2.dilate(dm, k)
        add = front & (d_s >= frac * ref)
        if not add.any():
            break
        grew = True
        rings += 1
        m_s[add] = 1
        dm[add] = d_s[add]
        c_s &= ~add
    if grew and rings < int(depth) and float(outer) < float(fraction):
        _outer_ring(m_s, d_s, c_s, dm, m[box][sub], np.float32(outer), int(depth))
    if grew:
        grown = mb.astype(bool)
        out[box] = _fill_holes(grown) if fill_holes else grown
    return out


def _outer_ring(m_s, d_s, c_s, dm, seed, frac, depth):
    """One more ring, in place, where the growth added pixels (within ``depth`` of them): the candidates
    next to the grown mask whose difference is at least ``frac`` of the largest of their mask neighbours'."""
    import cv2

    k = np.ones((3, 3), np.uint8)
    added = (m_s != 0) & ~seed
    # a shaded rim grows along the outline, each added pixel beside another; an added pixel alone is a speck
    # (impulse noise next to the outline), which must not bring a ring of its own
    beside = cv2.boxFilter(added.view(np.uint8), cv2.CV_16U, (3, 3), normalize=False, borderType=cv2.BORDER_CONSTANT)
    added &= beside >= 2
    reach = 2 * depth + 1
    near = cv2.dilate(added.view(np.uint8), cv2.getStructuringElement(cv2.MORPH_RECT, (reach, reach))).astype(bool)
    front = c_s & near & cv2.dilate(m_s, k).astype(bool)
    add = front & (d_s >= frac * cv2.dilate(dm, k))
    m_s[add] = 1


def rim_near(seed: np.ndarray, grown: np.ndarray, *, reach: int = RIM_DEPTH) -> np.ndarray | None:
    """Where a rim was grown: the pixels within ``reach`` px (chessboard) of those :func:`grow_rim` added to
    ``seed`` (None: none added).

    :func:`coverage`'s ``near``.  The shade that made :func:`grow_rim` add pixels falls along the outline
    beyond them too, where the seed already reached the outline; as far as the growth may reach (``RIM_DEPTH``).
    Measured at 1 mm, 36 views: reach 2 / 6 / 10 px gave -2.34 / -1.67 / -1.20 % on the ``aaa-3`` rim render
    and -0.185 / -0.172 / -0.159 % on the sample (-0.213 % without the rim step).
    """
    import cv2

    added = np.asarray(grown, dtype=bool) & ~np.asarray(seed, dtype=bool)
    box = _box(added.view(np.uint8), int(reach))
    if box is None:
        return None
    near = np.zeros(added.shape, dtype=bool)
    kernel = cv2.getStructuringElement(cv2.MORPH_RECT, (2 * int(reach) + 1, 2 * int(reach) + 1))
    near[box] = cv2.dilate(added[box].view(np.uint8), kernel).astype(bool)
    return near


def _rim_mask(diff, image, background, t, clean, *, noise, depth=RIM_DEPTH):
    """The silhouette at threshold ``t`` (:func:`clean_mask` with ``clean``'s options), its dim rim kept
    (:func:`grow_rim`, ``depth`` 0 or ``noise`` 0: none), and where that rim was kept (:func:`rim_near`,
    :func:`coverage`'s ``near``): ``(mask, near)``."""
    seed = clean_mask(diff > t, **clean)
    mask = grow_rim(seed, diff, image, background, noise=noise, depth=depth, fill_holes=clean.get("fill_holes", True))
    return mask, rim_near(seed, mask)


def _shadow_like(img, bg, tol):
    """(N,) bool: colours ``img`` (N, 3) that are a darker copy of the background's ``bg`` (N, 3), within
    ``tol`` grey levels (the colour distance of the residual after the best scaling of the background, as
    :func:`difference`)."""
    i = np.asarray(img, np.float32)
    b = np.asarray(bg, np.float32)
    bb = np.maximum((b * b).sum(axis=1), 1.0)
    g = (i * b).sum(axis=1) / bb
    r = i - g[:, None] * b
    return (g < 1.0) & (np.sqrt((r * r).sum(axis=1) / 3.0) < tol)


def coverage(image: np.ndarray, background: np.ndarray, mask: np.ndarray, *, window: int = 5,
             near: np.ndarray | None = None) -> np.ndarray:
    """Sub-pixel silhouette: the fraction of each pixel covered by the specimen.

    A pixel on the silhouette's edge that the specimen covers by a fraction
    ``a`` shows the blend ``I = a F + (1 - a) B`` of the specimen's colour
    ``F`` and the background ``B`` (anti-aliasing, or the camera's pixel
    integration).  ``B`` is the background model; ``F`` is taken from the
    nearest pixels wholly inside the mask (mean over a ``window`` square);
    ``a`` is the least-squares solution ``(I - B).(F - B) / |F - B|^2``.
    Pixels away from the mask's edge are 0 or 1 exactly.

    Parameters
    ----------
    image : (H, W) or (H, W, 3) uint8
    background : (H, W) or (H, W, 3) float
    mask : (H, W) bool
        The cleaned silhouette (:func:`clean_mask`).
    window : int, px
        Size of the square over which the specimen's colour is averaged.
    near : (H, W) bool, optional
        Where the specimen's shade falls toward its outline (a rim kept by
        :func:`grow_rim`, :func:`rim_near`).  There the mask's own edge pixels
        count as covered (1: they passed the rim's contrast test, their
        dimness is their shade), and the pixels just outside take ``F`` from
        their nearest specimen pixels (the inner ones in the 3 x 3 square, else
        the mask's): the mean of the whole window would be brighter than the
        rim and take a covered pixel for a partly covered one.  On the
        rim-shaded ``aaa-3`` render (36 views, noise 3) the coverage's sum is
        then 0.3 % under the exact one (``near`` from :func:`rim_near`), 1.9 %
        without ``near``.

    Returns
    -------
    (H, W) float32 in [0, 1]
    """
    image = np.asarray(image)
    background = np.asarray(background)
    m8 = np.asarray(mask, dtype=np.uint8)
    if m8.shape != image.shape[:2]:
        raise ValueError(f"mask {m8.shape} and image {image.shape[:2]} differ in size")
    cov = np.zeros(m8.shape, dtype=np.float32)
    # only the mask's box (widened by the edge band and the window) takes part
    box = _box(m8, 2 + int(window) // 2 + 1)
    if box is not None:
        nb = None if near is None else np.asarray(near, dtype=bool)[box]
        cov[box] = _coverage_in(image[box], background[box], m8[box], window, nb)
    return cov


def _coverage_in(image, background, m8, window, near=None):
    """:func:`coverage` of a crop whose border lies outside the mask's edge band and window."""
    import cv2

    img = np.asarray(image, np.float32)
    bg = np.asarray(background, np.float32)
    if img.ndim == 2:
        img = img[..., None]
    if bg.ndim == 2:
        bg = bg[..., None]
    if img.shape[2] != bg.shape[2]:
        img, bg = _luma(img) if img.shape[2] == 3 else img[..., 0], _luma(bg) if bg.shape[2] == 3 else bg[..., 0]
        img, bg = img[..., None], bg[..., None]
    k = np.ones((3, 3), np.uint8)
    inner = cv2.erode(m8, k, borderType=cv2.BORDER_REPLICATE)
    outer = cv2.dilate(m8, k).astype(bool)
    band = outer & ~inner.astype(bool)
    cov = inner.astype(np.float32)
    rows, cols = np.nonzero(band)
    if rows.size == 0:
        return cov
    w = (int(window), int(window))
    weight = cv2.boxFilter(inner.astype(np.float32), -1, w, normalize=False)[rows, cols]
    fg = np.stack(
        [cv2.boxFilter(img[..., c] * inner, -1, w, normalize=False)[rows, cols] for c in range(img.shape[2])], axis=-1
    )
    with np.errstate(invalid="ignore", divide="ignore"):
        fg = fg / weight[:, None]
    if near is not None and near[rows, cols].any():
        _nearest_colour(img, inner, m8, rows, cols, near[rows, cols], fg, weight)
    b = bg[rows, cols]
    d_img = img[rows, cols] - b
    d_fg = fg - b
    den = (d_fg * d_fg).sum(axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        a = (d_img * d_fg).sum(axis=-1) / den
    # edge pixels with no inside neighbour in the window (or no contrast) keep the binary mask
    ok = (weight > 0) & (den > 1.0)
    if near is not None:  # a kept rim's own pixels are covered: dim by their shade, not by their coverage
        ok &= ~(near[rows, cols] & (m8[rows, cols] != 0))
    cov[rows, cols] = np.where(ok, np.clip(a, 0.0, 1.0), m8[rows, cols].astype(np.float32))
    return cov


def _nearest_colour(img, inner, m8, rows, cols, sel, fg, weight):
    """Replace, in place, the specimen's colour ``fg`` (and ``weight``) of the band pixels ``sel`` by the mean of
    their nearest specimen pixels: the inner ones in the 3 x 3 square, else the mask's (the window's mean stays
    where neither has one); at the image's border the edge pixels stand for the ones beyond."""
    idx = np.flatnonzero(sel)
    h, w_ = inner.shape
    r = np.clip(rows[idx][:, None] + np.array([-1, -1, -1, 0, 0, 0, 1, 1, 1]), 0, h - 1)
    c = np.clip(cols[idx][:, None] + np.array([-1, 0, 1, -1, 0, 1, -1, 0, 1]), 0, w_ - 1)
    colours = img[r, c]  # (N, 9, channels)
    done = np.zeros(idx.size, dtype=bool)
    for src in (inner, m8):
        w8 = (src[r, c] != 0).astype(np.float32)  # (N, 9)
        w = w8.sum(axis=1)
        take = ~done & (w > 0)
        if take.any():
            fg[idx[take]] = (colours[take] * w8[take, :, None]).sum(axis=1) / w[take, None]
            weight[idx[take]] = w[take]
            done |= take
        if done.all():
            break


def silhouette(image: np.ndarray, background: np.ndarray, *, threshold: float | None = None,
               mode: Literal["color", "grey"] = "color", floor: float = 0.0, noise: float = 0.0,
               **clean: Any) -> Silhouette:
    """Silhouette of one view by background subtraction.

    Parameters
    ----------
    image : (H, W) or (H, W, 3) uint8
    background : (H, W) or (H, W, 3) float
        From :func:`background_model`.
    threshold : float, optional
        Grey levels; :func:`auto_threshold` of the difference image when omitted.
    mode : {'color', 'grey'}
    floor : float
        Lowest automatic threshold (e.g. from the background noise).
    noise : float
        The background's noise (:func:`background_noise`), grey levels: > 0 keeps the
        dim rim connected to the silhouette at the automatic threshold (:func:`grow_rim`;
        a threshold given is used as it is); 0 (default) does not.
    **clean
        Options of :func:`clean_mask`.

    Returns
    -------
    Silhouette
    """
    diff = difference(image, background, mode=mode)
    t = auto_threshold(diff, floor=floor) if threshold is None else float(threshold)
    if t <= 0:
        raise ValueError(f"threshold must be > 0 grey levels, got {t}")
    mask, near = _rim_mask(diff, image, background, t, clean, noise=noise if threshold is None else 0.0)
    return Silhouette(mask, coverage(image, background, mask, near=near), t, "subtraction")
