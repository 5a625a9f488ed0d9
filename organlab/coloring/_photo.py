"""Photo-consistency by patch NCC: per-view depth sweeps behind the current surface, fused into the hull.

See ``docs/coloring.md`` ("The photo method") for the formulation and why.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence

import cv2
import numpy as np

from ..camera import Camera
from ..grid import VoxelGrid
from ._auto import guard as _guard
from ._api import voxel_colors
from ._common import ColoringResult, _check_inputs, _check_occupancy
from ._photo_kernels import free_votes, surface_depth, warp_samples

#: Default evidence: NCC gain (best depth's score minus the surface's) a pixel needs to say "free".
DEFAULT_PHOTO_THRESHOLD = 0.25

_MIN_SCORE = 0.5  # the best depth's score must itself be a match (mean of the two best pairs' NCC)
_PEAK = 0.1  # NCC: how far below the best score the peak's front is taken
_MIN_STD = 2.0  # grey levels: windows flatter than this (either image) give no evidence
_NEIGHBOUR_DEG = (12.0, 40.0)  # angles between a view and the views it is compared with
_MAX_NEIGHBOURS = 4
_CHUNK = 16  # depth steps per box filter call (its channels)
_CONFIRM = 0.5  # NCC: where three or more pairs are valid at the best depth, the third best must match too


def _neighbours(cameras, centre):
    """For each view, up to 4 other views 12-40 degrees away (seen from ``centre``), nearest 25 degrees first."""
    dirs = np.array([c.center - centre for c in cameras], np.float64)
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    ang = np.degrees(np.arccos(np.clip(dirs @ dirs.T, -1.0, 1.0)))
    out = []
    for i in range(len(cameras)):
        cand = [j for j in range(len(cameras)) if j != i and _NEIGHBOUR_DEG[0] <= ang[i, j] <= _NEIGHBOUR_DEG[1]]
        cand.sort(key=lambda j: abs(ang[i, j] - 25.0))
        out.append(cand[:_MAX_NEIGHBOURS])
    return out


def _window_ncc(ref, warped, valid_ref, window):
    """NCC of ``window``-px square patches: ``ref (h, w)`` against ``warped (J, S, h, w)`` (NaN = invalid).

    ``_CHUNK`` depth steps at a time, as the channels of one box filter (each channel's sums are its
    own, so the figures are those of one slice at a time): temporaries of a few MB (whole-stack ones
    were ten arrays the size of ``warped``, hundreds of MB per view on the dino photos), and one
    filter call per chunk instead of per slice.
    """
    k = (window, window)

    def box(a):
        return cv2.boxFilter(a, -1, k, borderType=cv2.BORDER_CONSTANT).reshape(a.shape)

    ref = ref.astype(np.float32)
    mr, mrr = box(ref), box(ref * ref)
    vr = mrr - mr * mr
    vfrac = box(valid_ref.astype(np.float32))
    ref_good = ((vfrac > 0.999) & (vr > _MIN_STD**2))[..., None]
    ref3, mr3, vr3 = ref[..., None], mr[..., None], vr[..., None]
    J, S = warped.shape[:2]
    out = np.empty(warped.shape, np.float32)
    for j in range(J):
        for s0 in range(0, S, _CHUNK):
            ws = np.ascontiguousarray(warped[j, s0:s0 + _CHUNK].transpose(1, 2, 0))  # (h, w, c)
            ok = np.isfinite(ws)
            w = np.where(ok, ws, np.float32(0.0))
            fr = box(ok.astype(np.float32))
            mw, mww, mrw = box(w), box(w * w), box(ref3 * w)
            vw = mww - mw * mw
            cov = mrw - mr3 * mw
            good = (fr > 0.999) & ref_good & (vw > _MIN_STD**2)
            with np.errstate(invalid="ignore", divide="ignore"):
                ncc = cov / np.sqrt(vr3 * vw)
            out[j, s0:s0 + _CHUNK] = np.where(good, ncc, np.float32(np.nan)).transpose(2, 0, 1)
    return out


def _top2(ncc):
    """Mean of the two best view pairs' NCC, ``(S, h, w)``; NaN where fewer than two pairs are valid.

    The two largest by a running max / min over the pairs (the values a full sort along the pairs
    would put first, without sorting the whole ``(J, S, h, w)`` stack).
    """
    m1 = np.full(ncc.shape[1:], -np.inf, np.float32)
    m2 = m1.copy()
    for x in ncc:
        x = np.where(np.isfinite(x), x, np.float32(-np.inf))
        np.maximum(m2, np.minimum(m1, x), out=m2)
        np.maximum(m1, x, out=m1)
    s = 0.5 * (m1 + m2)
    return np.where(np.isfinite(s), s, np.nan)


def _view_evidence(i, nbrs, grey, fg, cams_packed, cameras, occ, grid, lo, hi, depth, dt, threshold, window, margin):
    """Free segments ``(dirs, t_from, t_to)`` of view ``i``'s pixels, and the pixels' count of evidence."""
    H, W = fg.shape[1:]
    ys, xs = np.nonzero(fg[i])
    if len(xs) == 0 or len(nbrs) < 2:
        return None
    y0, y1, x0, x1 = ys.min(), ys.max() + 1, xs.min(), xs.max() + 1
    cam = cameras[i]
    uu, vv = np.meshgrid(np.arange(x0, x1, dtype=np.float64), np.arange(y0, y1, dtype=np.float64))
    o, d = cam.rays(np.stack([uu.ravel(), vv.ravel()], axis=1))
    o = np.ascontiguousarray(o[0])
    d = np.ascontiguousarray(d)
    inside = fg[i, y0:y1, x0:x1].ravel() != 0
    t_s = surface_depth(o, d, occ, np.asarray(grid.origin, np.float64), float(grid.voxel_size), lo, hi,
                        0.3 * float(grid.voxel_size))
    t_s[~inside] = np.nan
    n_steps = int(np.ceil(depth / dt)) + 1
    J = len(nbrs)
    out = np.empty((J, n_steps, len(d)), np.float32)
    warp_samples(o, d, t_s, dt, n_steps, cams_packed[nbrs], grey[nbrs], fg[nbrs], out)
    h, w = y1 - y0, x1 - x0
    warped = out.reshape(J, n_steps, h, w)
    ref = grey[i, y0:y1, x0:x1]
    valid_ref = (fg[i, y0:y1, x0:x1] != 0) & np.isfinite(t_s.reshape(h, w))
    ncc = _window_ncc(ref, warped, valid_ref, window)
    score = _top2(ncc)  # (S, h, w)
    s0 = score[0]
    filled = np.where(np.isfinite(score), score, -np.inf)
    best = np.argmax(filled, axis=0)
    s_best = np.take_along_axis(filled, best[None], 0)[0]
    # the front of the peak: the nearest depth from which the score stays within _PEAK of the best;
    # a broad peak (a surface seen at a grazing angle, a slanted wall) stops the free ray early
    near = filled >= (s_best - _PEAK)[None]
    steps = np.arange(len(score))[:, None, None]
    beyond = (steps <= best[None]) & ~near
    front = np.where(beyond.any(0), (np.where(beyond, steps, -1).max(0) + 1), 0)
    free_to = front * dt - margin
    ok = np.isfinite(s0) & (s_best >= _MIN_SCORE) & (s_best - s0 >= threshold) & (free_to > 0)
    if len(ncc) > 2:  # the depth confirmed by a third pair wherever one is valid there
        at = np.take_along_axis(ncc, np.broadcast_to(best[None, None], (len(ncc), 1) + best.shape), 1)[:, 0]
        third = -np.sort(-np.where(np.isfinite(at), at, -np.inf), axis=0)[2]
        ok &= ~np.isfinite(third) | (third >= _CONFIRM)
    ok = ok.ravel()
    if not ok.any():
        return None
    t_from = t_s[ok]
    return d[ok], o, t_from, t_from + free_to.ravel()[ok]


def photo_carve(images: Sequence[np.ndarray], cameras: Sequence[Camera], occupancy: np.ndarray, grid: VoxelGrid, *,
                masks: Sequence[np.ndarray], threshold: float = DEFAULT_PHOTO_THRESHOLD, depth: float = 16.0,
                min_views: int = 2, window: int = 7, passes: int = 2, margin: float | None = None, guard: bool = True,
                progress: Callable[[int, int], object] | None = None) -> ColoringResult:
    """Carve the hull where patch NCC between neighbouring views finds the surface deeper.

    For every view, every silhouette pixel's ray meets the current surface
    at depth ``t``; points ``t + s * dt`` behind it (up to ``depth`` mm) are
    projected into the up-to-4 views 12-40 degrees away and the grey
    ``window`` x ``window`` patches around them compared with the view's own
    by normalised cross-correlation (blind to exposure and shading).  A
    depth's score is the mean NCC of its two best view pairs (so at least
    two pairs must agree; occluded or highlighted pairs drop out); where a
    third pair is valid at the best depth it must match too (NCC >= 0.5):
    smooth shading and sparse spots match two pairs by chance far more often
    than three.  Where the best depth scores at least 0.5 and ``threshold``
    more than the surface itself, the ray is free from the surface to one
    voxel before the front of that depth's peak: its voxels get a vote from
    this view.  Voxels with votes from
    ``min_views`` views are carved; the next pass starts from the carved
    surface (visibility from the current surface); finally the silhouette
    guard puts back every voxel a silhouette needs.

    Parameters
    ----------
    images : sequence of (H, W, 3) or (H, W) uint8
    cameras : sequence of Camera
    occupancy : (nx, ny, nz) bool
        The visual hull on ``grid``.
    grid : VoxelGrid
    masks : sequence of (H, W) bool
        Silhouettes (True = specimen).
    threshold : float
        NCC gain, in (0, 2): how much better than the current surface a
        deeper point must match before the ray in front of it is free.
    depth : float, mm
        How far behind the surface to look.
    min_views : int
        Views whose free rays must cross a voxel before it is carved.
    window : int
        Patch size, pixels (odd).
    passes : int
        Sweeps; each starts from the previous one's carved surface.
    margin : float, mm, optional
        How far in front of the matched depth a free ray stops (along the
        ray); default 1 voxel (carving right to the surface would cut
        the voxels the surface crosses, which the hull keeps).
    guard : bool
        Silhouette guard (see :func:`color_voxels`).
    progress : callable(done, total), optional

    Returns
    -------
    ColoringResult
        ``method='photo'``; ``threshold`` is the NCC gain, ``support`` is
        ``min_views``, ``iterations`` the passes run; ``colors`` are the carved
        model's surface colours (:func:`voxel_colors`).

    Examples
    --------
    >>> import tempfile
    >>> import organlab as ol
    >>> from organlab.synthetic import with_true_cameras
    >>> s = ol.load_session(with_true_cameras("sample_sessions/aaa_phantom", tempfile.mkdtemp() + "/aaa", step=6))
    >>> cal, _ = ol.calibration_for(s)
    >>> cameras, grid, sils = cal.cameras(s), ol.VoxelGrid.from_session(s, voxel_size=4.0), ol.silhouettes(s)
    >>> hull = ol.carve([sil.mask for sil in sils], cameras, grid)
    >>> r = photo_carve([s.read(v.image) for v in s.views], cameras, hull, grid, masks=[sil.mask for sil in sils])
    >>> r.method, bool(not (r.occupancy & ~hull).any())
    ('photo', True)
    """
    t_start = time.perf_counter()
    stack, cameras, cams, bg = _check_inputs(images, cameras, grid, masks)
    hull = _check_occupancy(occupancy, grid)
    if isinstance(threshold, bool) or not isinstance(threshold, (int, float, np.integer, np.floating)) or not 0 < threshold < 2:
        raise ValueError(f"threshold must be an NCC gain in (0, 2), got {threshold!r}")
    if not (isinstance(depth, (int, float, np.integer, np.floating)) and depth > 0):
        raise ValueError(f"depth must be a number of mm > 0, got {depth!r}")
    if isinstance(min_views, bool) or not isinstance(min_views, (int, np.integer)) or min_views < 1:
        raise ValueError(f"min_views must be an integer >= 1, got {min_views!r}")
    if isinstance(window, bool) or not isinstance(window, (int, np.integer)) or window < 3 or window % 2 == 0:
        raise ValueError(f"window must be an odd integer >= 3 (pixels), got {window!r}")
    if isinstance(passes, bool) or not isinstance(passes, (int, np.integer)) or passes < 1:
        raise ValueError(f"passes must be an integer >= 1, got {passes!r}")
    progress = progress or (lambda done, total: None)
    grey = np.ascontiguousarray(stack.astype(np.float32).mean(axis=3))
    fg = np.ascontiguousarray((bg == 0).astype(np.uint8))
    h = float(grid.voxel_size)
    origin = np.asarray(grid.origin, np.float64)
    occ = hull.copy()
    n_views = len(cameras)
    if occ.any():
        idx = np.argwhere(occ)
        centre = origin + 0.5 * (idx.min(0) + idx.max(0)) * h
    else:
        centre = origin
    nbrs = _neighbours(cameras, centre)
    # depth step: the distance that moves a point by about 0.5 px in a neighbour 25 degrees away
    px_mm = min(c.K[0, 0] / np.linalg.norm(c.center - centre) for c in cameras)
    dt = min(0.5 * h, 0.5 / (px_mm * np.sin(np.radians(25.0))))
    margin = 1.0 * h if margin is None else float(margin)
    total = passes * n_views
    done = 0
    carved_per_pass = []
    for _ in range(passes):
        idx = np.argwhere(occ)
        if len(idx) == 0:
            break
        lo = origin + (idx.min(0) - 0.5) * h
        hi = origin + (idx.max(0) + 0.5) * h
        occ8 = occ.astype(np.uint8)
        votes = np.zeros(grid.shape, np.int32)
        stamp = np.full(grid.shape, -1, np.int32)
        for i in range(n_views):
            ev = _view_evidence(i, nbrs[i], grey, fg, cams, cameras, occ8, grid, lo, hi, float(depth), dt,
                                float(threshold), int(window), margin)
            if ev is not None:
                d, o, t_from, t_to = ev
                free_votes(o, d, t_from, t_to, occ8, origin, h, votes, stamp, i)
            done += 1
            progress(done, total)
        carve = occ & (votes >= min_views)
        carved_per_pass.append(int(np.count_nonzero(carve)))
        if not carve.any():
            break
        occ = occ & ~carve
    n_restored = 0
    if guard:
        occ, n_restored = _guard(occ, hull, cameras, grid, masks)
    n_cand = int(np.count_nonzero(hull))
    colors = voxel_colors(images, cameras, occ, grid, masks=masks)
    colored = colors.any(axis=3)
    return ColoringResult(
        occupancy=occ, colors=colors, colored=colored,
        n_candidates=n_cand, n_carved=n_cand - int(np.count_nonzero(occ)), n_carved_background=0, n_visible=int(np.count_nonzero(colored)),
        n_hidden=0, n_untested=0, seconds=time.perf_counter() - t_start, method="photo", sweep=None,
        iterations=len(carved_per_pass), threshold=float(threshold), automatic=False, n_restored=n_restored,
        noise=None, gains=None, support=int(min_views))
