"""Private numba kernels of :mod:`organlab.silhouette`: the same numbers as the
numpy expressions they replace, computed in one pass and in parallel.

* :func:`median_frames` -- ``np.median(stack, axis=0).astype(np.float32)`` of
  uint8 frames (the median of integers is exact): for up to :data:`_NETWORK_MAX`
  frames a selection network of numpy minima and maxima (no numba: 0.034 s CPU
  against the kernel's 0.11 s for the sample's 20 frames of 640 x 480 x 3),
  else a per-pixel histogram in numba;
* :func:`std_frames` -- ``stack.astype(np.float32).std(axis=0, ddof=1)`` of
  uint8 frames, as numpy evaluates it (float32 sums over the frames in
  order, the mean and the variance divided in float64 and rounded to float32,
  float32 square root), in one pass without the float32 copy of the stack;
* :func:`color_distance` -- ``difference``'s colour distance,
  ``float32(float64(sqrt(float32 sum of squares)) / sqrt(3))``, as numpy
  evaluates it (float32 squares summed left to right, float32 square root);
* :func:`split_above` -- ``x[x > t]`` and ``x[~(x > t)]`` of a 1-D float32 array in one pass, into
  buffers given (Li's threshold iterations, :func:`organlab.silhouette._subtract._li_threshold`).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange


#: Most frames :func:`median_frames` sorts with numpy minima and maxima (its comparisons grow as
#: the square of the frames, the numba kernel's work linearly: estimated even at about 40 frames from the 20-frame timings).
_NETWORK_MAX = 32


def median_frames(stack):
    """Per-pixel median over axis 0 of ``(N, P)`` uint8, as float32 ``(P,)``.

    Equal to ``np.median(stack, axis=0).astype(np.float32)`` (integers: the middle value, or the
    mean of the two middle values for even ``N``, exact in float32).
    """
    n = stack.shape[0]
    if n > _NETWORK_MAX:
        return _median_histogram(stack)
    # bubble passes of a sorting network, element-wise over the pixels: after pass i the i + 1
    # largest values of each pixel lie sorted at the top, so n - lo passes place both middle ranks
    rows = list(np.array(stack, dtype=np.uint8))  # copies: the caller's frames stay as they are
    lo, hi = (n - 1) // 2, n // 2
    spare = np.empty_like(rows[0])
    for i in range(n - lo):
        for j in range(n - 1 - i):
            a, b = rows[j], rows[j + 1]
            np.minimum(a, b, out=spare)
            np.maximum(a, b, out=b)
            rows[j], spare = spare, a
    return (rows[lo].astype(np.float32) + rows[hi]) / np.float32(2.0)


@njit(cache=True, parallel=True)
def _median_histogram(stack):
    """Per-pixel median over axis 0 of ``(N, P)`` uint8, as float32 ``(P,)``.

    The middle value (mean of the two middle values for even ``N``) of each
    pixel's ``N`` values, read from its histogram between its extremes: the
    median of integers is exact, so this equals
    ``np.median(stack, axis=0).astype(np.float32)``.
    """
    n, p = stack.shape
    out = np.empty(p, dtype=np.float32)
    step = 1024
    lo_rank = (n - 1) // 2
    hi_rank = n // 2
    for b in prange((p + step - 1) // step):
        counts = np.zeros(256, dtype=np.int32)
        for i in range(b * step, min(p, b * step + step)):
            vmin = 255
            vmax = 0
            for k in range(n):
                v = stack[k, i]
                counts[v] += 1
                vmin = min(vmin, v)
                vmax = max(vmax, v)
            # walk the histogram between the pixel's extremes (a few bins: frames differ by noise)
            seen = 0
            lo = -1
            hi = -1
            for v in range(vmin, vmax + 1):
                seen += counts[v]
                counts[v] = 0
                if lo < 0 and seen > lo_rank:
                    lo = v
                if hi < 0 and seen > hi_rank:
                    hi = v
            out[i] = np.float32((lo + hi) / 2.0)
    return out


@njit(cache=True, nogil=True)
def color_distance(img, bg):
    """``(H, W, 3)`` uint8 image, ``(H, W, 3)`` float32 background -> ``(H, W)`` float32."""
    h, w, _ = img.shape
    out = np.empty((h, w), dtype=np.float32)
    s3 = math.sqrt(3.0)
    for r in range(h):
        for c in range(w):
            d0 = np.float32(img[r, c, 0]) - bg[r, c, 0]
            d1 = np.float32(img[r, c, 1]) - bg[r, c, 1]
            d2 = np.float32(img[r, c, 2]) - bg[r, c, 2]
            s = d0 * d0 + d1 * d1 + d2 * d2
            out[r, c] = np.float32(np.float64(np.sqrt(s)) / s3)
    return out


@njit(cache=True, nogil=True)
def std_frames(stack):
    """Per-pixel standard deviation (``ddof=1``) over axis 0 of ``(N, P)`` uint8, as float32 ``(P,)``.

    numpy's ``std`` on the float32 stack: the frames summed in order in float32, the sum divided
    by N (in float64, then rounded to float32: the same as a float32 division), the squared float32
    deviations summed in order, divided by N - 1 likewise, float32 square root.  Pixels in chunks
    that stay in cache, the frames read row by row.
    """
    n, p = stack.shape
    out = np.empty(p, dtype=np.float32)
    step = 4096
    acc = np.empty(step, dtype=np.float32)
    mean = np.empty(step, dtype=np.float32)
    for b0 in range(0, p, step):
        m = min(step, p - b0)
        for i in range(m):
            acc[i] = np.float32(stack[0, b0 + i])
        for k in range(1, n):
            for i in range(m):
                acc[i] += np.float32(stack[k, b0 + i])
        for i in range(m):
            mean[i] = np.float32(np.float64(acc[i]) / n)
            d = np.float32(stack[0, b0 + i]) - mean[i]
            acc[i] = d * d
        for k in range(1, n):
            for i in range(m):
                d = np.float32(stack[k, b0 + i]) - mean[i]
                acc[i] += d * d
        for i in range(m):
            out[b0 + i] = np.sqrt(np.float32(np.float64(acc[i]) / (n - 1)))
    return out


@njit(cache=True, nogil=True)
def split_above(x, t, above, below):
    """``x[x > t]`` into ``above[:n_above]`` and ``x[~(x > t)]`` into ``below[:n_below]``, in ``x``'s order.

    ``x`` (N,) float32, ``t`` a float32 scalar, ``above`` and ``below`` (N,) float32 buffers (overwritten);
    returns ``(n_above, n_below)``.  The same elements in the same order as numpy's boolean indexing, so
    ``np.mean(above[:n_above])`` is ``np.mean(x[x > t])`` to the bit.
    """
    na = 0
    nb = 0
    for i in range(x.shape[0]):
        v = x[i]
        if v > t:
            above[na] = v
            na += 1
        else:
            below[nb] = v
            nb += 1
    return na, nb


def warm_kernels() -> None:
    """Load the kernels above from numba's cache, ahead of the first silhouettes.

    The first cached kernel a process loads also loads numba's own registries (about 0.5 s CPU,
    Python holding the GIL); the ``reconstruct`` command does it on a thread while the session's
    images are decoded (cv2 releases the GIL).  Tiny inputs of the dtypes and layouts the stage
    passes: the same compiled specialisations.
    """
    _median_histogram(np.zeros((1, 1), np.uint8))  # the carving's parallel kernels share its threading layer
    std_frames(np.zeros((2, 1), np.uint8))
    color_distance(np.zeros((1, 1, 3), np.uint8), np.zeros((1, 1, 3), np.float32))
    z = np.zeros(1, np.float32)
    split_above(z, np.float32(0.0), z.copy(), z.copy())
