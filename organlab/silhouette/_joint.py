"""Private workers of :mod:`organlab.silhouette`: silhouettes from all the views together (the joint step).

After the first, per-view pass (subtraction or keying), every view is
segmented again with the model of the views together as a prior:

1. the *prior*: the visual hull that survives up to ``TOLERANCE`` views
   carving it (:class:`organlab.carving.ProgressiveCarver`, bounding-box
   test, on a grid of about ``VOXEL_PX`` pixel footprints in the box that
   the first pass's hull fills), projected into each view (its voxels'
   boundary faces, found once a round, filled as
   :func:`organlab.raster.model_mask` fills them).  A part that one or two
   views miss (a dark notch, a shaded rim, a dark paint patch) stays in this
   hull, so it projects into the views that miss it;
2. the *required voxels*: the same carving counts, per voxel, the views that
   carve it and, where one view alone carves it, which one.  The exact hull
   (no view carves) is projected into every view; a silhouette pixel outside
   it is *unexplained*.  A voxel that one view ``i`` alone carves and whose
   centre falls on an unexplained pixel of another view is *required* of view
   ``i`` (:func:`required_by_others`): that view sees the specimen there, and
   only view ``i`` denies it (the dino's shadowed chin notch: views that see
   it lit lose its rays to the one view that sees it as dark as the backdrop);
3. the *colour evidence*: each view's difference image (the distance to the
   background model, grey levels, or Delta E to the backdrop) is compared
   with the background's own statistics, measured in a ring just outside the
   prior's projection (mean, MAD, 99.5th percentile);
4. *required pixels* (applied after rules 5 and 6, to what they left): the
   projection of the voxels required of a view, widened by
   ``NEED_BRIDGE_PX`` (the voxels project coarsely), where
   its difference exceeds the ring's mean by ``NEED_SD`` deviations (not the
   backdrop: a pixel that shows the backdrop contradicts the others, and
   stays out) and in parts that touch the silhouette and hold a required
   pixel, is added; on its new outline only pixels that show
   ``EDGE_FRACTION`` of the contrast around (rule 5's sub-pixel test).  A pixel no
   other view needs is never added by this rule, so a concavity that only
   this view sees through (the stand seen through a gap) stays carved;
5. *edge growth* (sub-pixel rule): a pixel next to the silhouette and
   inside the prior is added where it differs from the background beyond
   the ring's 99.5th percentile and by at least ``EDGE_FRACTION`` (0.6) of the contrast of
   the silhouette's pixels around it (an edge pixel covered by a fraction ``a``
   of the specimen shows ``a`` times that contrast: the rule adds the pixels
   the specimen covers by more than half, the ones a global threshold drops
   where the specimen's edge is shaded);
6. *regions*: a connected part of the prior's
   projection, eroded by its slack (the voxels' size and the bounding-box
   test's margin), that the silhouette misses is added whole when its mean
   difference exceeds the background ring's (by 4 standard errors, and half
   a standard deviation): dark, but not the background;
7. *removal*: silhouette pixels beyond the prior's projection (widened by its
   slack) are dropped: nothing the other views see explains them (a cast
   shadow on the plate, a strip of the stand);
8. repeat with the new silhouettes until no pixel changes (at most
   ``ITERATIONS`` rounds).

Keyed views (Delta E to one backdrop colour, no model of the background
per pixel) get rules 4 and 7 only.  Against one colour, the shadowed parts
of a dark specimen, a dark stand and the shadows beside it have the same
Delta E (the dinoSparseRing photos: 2-10 for all three): a region (rule 6)
has no colour evidence, and the edge rule's contrast, taken from the
silhouette's pixels around, follows the pixels it added into the stand
(1 491 px of it in dinoSR0001 through the gap between leg and body).

Given masks are never changed (they are priors for the others).  A correct
silhouette is not grown: every pixel of it is explained, so no voxel is
required; beyond it the prior's projection is only its slack (rejected by
rule 6's erosion), and edge pixels the specimen covers by half or less fail
rule 5.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence

import numpy as np

from ..camera import Camera
from ..carving import ProgressiveCarver
from ..grid import VoxelGrid
from ..raster import MeshRaster, voxel_boundary_quads

#: Views that may carve a voxel of the prior (the hull of the others, ``TOLERANCE`` views allowed to miss a part).
TOLERANCE = 2
#: The prior's voxel size, in pixel footprints at the box's centre.
VOXEL_PX = 1.5
#: Largest number of voxels of the prior's grid (its voxels grow beyond it).
MAX_VOXELS = 6_000_000
ITERATIONS = 3
#: Edge growth: rounds (px) per iteration, and the window (px) whose silhouette pixels give the contrast.
EDGE_ROUNDS = 4
CONTRAST_WINDOW = 5
#: Edge rule: least difference, as a fraction of the contrast around (a half-covered pixel shows 0.5; the
#: margin absorbs the specimen's shading and texture across the window).
EDGE_FRACTION = 0.6
#: The background ring outside the prior's projection (px).
RING_PX = (3, 15)
#: Region rule: smallest region (px), margin in standard errors and in standard deviations.
MIN_REGION = 6
REGION_SE = 4.0
REGION_SD = 1.0
#: Region rule: largest region, fraction of the silhouette (a notch or a patch, not a piece of the stand).
REGION_FRACTION = 0.1
#: Removal is skipped in a view where it would take more than this fraction of the silhouette (the prior is
#: then what is wrong: other views that lost a part).
REMOVE_FRACTION = 0.1
#: Least background deviation of the region rule (grey levels or Delta E: quantised, noiseless backdrops have MAD 0).
SD_FLOOR = 1.0
#: Required rule: least difference, in the background ring's deviations above its mean; other views whose
#: unexplained pixels must vote for a voxel.
NEED_SD = 3.0
NEED_SUPPORT = 1
#: Unexplained pixels lie beyond this distance (px) of the exact hull's projection: closer is the prior's voxels
#: (about 1.5 px), not views that disagree.
EXPLAIN_PX = 1
#: Required rule: how far (px) the part added may reach beyond the required voxels' projection (to join it to
#: the silhouette: the voxels' projection is coarse).
NEED_BRIDGE_PX = 2
#: Views needed for the joint step to mean anything ("auto").
MIN_VIEWS = 8


def _disk(r):
    import cv2

    r = int(r)
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))


def _dilate(m, r):
    import cv2

    if r <= 0:
        return m.copy()
    return cv2.dilate(m.astype(np.uint8), _disk(r)) > 0


def _erode(m, r):
    import cv2

    if r <= 0:
        return m.copy()
    return cv2.erode(m.astype(np.uint8), _disk(r), borderType=cv2.BORDER_CONSTANT, borderValue=0) > 0


def footprint_mm(cameras: Sequence[Camera], point) -> float:
    """Mean pixel footprint (mm per px) of the cameras at a point."""
    return float(np.mean([c.pixel_footprint(np.asarray(point, float)) for c in cameras]))


def _carve_tolerant(masks, cameras, lo, hi, voxel, *, sole=False):
    """The tolerant hull; with ``sole``, also the carving counts and, per voxel carved by one view, which."""
    grid = VoxelGrid.from_roi(lo, hi, voxel)
    carver = ProgressiveCarver(grid, tolerance=TOLERANCE)
    if not sole:
        for m, c in zip(masks, cameras):
            carver.add_view(m, c)
        return grid, carver.occupancy
    # which view carved a voxel that one view carves, from the counts c_i after each view i (0 before, then 1 from
    # the view k that carves it): sum_i i (c_i - c_{i-1}) = (n - 1) c_{n-1} - sum_{i < n-1} c_i = k.  One sum per
    # view instead of comparing the counts before and after it (0.6 of the step's 9 CPU s on the dino, 3 rounds)
    n = len(masks)
    acc = np.zeros(grid.shape, np.uint16 if (TOLERANCE + 1) * n < 2**16 else np.int64)  # counts <= TOLERANCE + 1
    for i, (m, c) in enumerate(zip(masks, cameras)):
        carver.add_view(m, c)
        if i < n - 1:
            acc += carver.carve_counts
    counts = carver.carve_counts
    one = counts == 1
    who = np.full(grid.shape, -1, np.int16)
    who[one] = (n - 1) - acc[one].astype(np.int64)
    return grid, (counts, who)


def prior_hull(masks: Sequence[np.ndarray], cameras: Sequence[Camera], box: tuple, *,
               sole: bool = False) -> tuple[VoxelGrid, np.ndarray]:
    """The tolerant hull (``TOLERANCE`` views may carve a voxel) of masks, on a grid of ~``VOXEL_PX`` px footprints.

    Coarse first (the box in ~48 voxels along its largest side) to find where
    the hull lies, then fine in that part of the box.  With ``sole``, the
    second value is ``(counts, who)`` instead: the views carving each voxel
    (up to ``TOLERANCE + 1``) and, where one view carves it, which one (else -1).
    """
    lo, hi = (np.asarray(v, float) for v in box)
    coarse = float((hi - lo).max()) / 48.0
    g, occ = _carve_tolerant(masks, cameras, lo, hi, coarse)
    if not occ.any():
        return _carve_tolerant(masks, cameras, lo, hi, coarse, sole=True) if sole else (g, occ)
    idx = np.argwhere(occ)
    a, b = idx.min(axis=0) - 1, idx.max(axis=0) + 2
    lo2 = np.maximum(lo, lo + a * coarse)
    hi2 = np.minimum(hi, lo + b * coarse)
    fp = footprint_mm(cameras, 0.5 * (lo2 + hi2))
    voxel = VOXEL_PX * fp if math.isfinite(fp) else coarse / 4
    voxel = max(voxel, (float(np.prod(hi2 - lo2)) / MAX_VOXELS) ** (1.0 / 3.0))
    return _carve_tolerant(masks, cameras, lo2, hi2, voxel, sole=sole)


def required_by_others(grid: VoxelGrid, counts: np.ndarray, who: np.ndarray, masks: Sequence[np.ndarray],
                       explained: Sequence[np.ndarray], cameras: Sequence[Camera], *,
                       support: int = 1) -> np.ndarray:
    """Voxels one view alone carves that other views' silhouettes need: ``grid.shape`` int16, the carving view or -1.

    A voxel carved by exactly one view ``i`` is *required* when its centre
    projects, in at least ``support`` other views, onto a silhouette pixel
    that the exact hull (``counts == 0``; its projection ``explained``)
    leaves unexplained: those views see something there that only view ``i``
    denies.
    """
    out = np.full(grid.shape, -1, np.int16)
    idx = np.argwhere(counts == 1)
    if not len(idx):
        return out
    pts = grid.centers(idx)
    sole = who[tuple(idx.T)]
    votes = np.zeros(len(idx), np.int32)
    for j, (m, e, cam) in enumerate(zip(masks, explained, cameras)):
        if e is None:
            continue
        miss = m & ~e  # e: the exact hull's projection, widened by EXPLAIN_PX
        if not miss.any():
            continue
        todo = np.flatnonzero((votes < support) & (sole != j))  # a voxel with its votes is not projected again
        if not len(todo):
            break
        uv = _project(cam, pts[todo])
        ok = np.isfinite(uv).all(axis=1)
        u = np.floor(uv[ok, 0] + 0.5).astype(np.int64)
        v = np.floor(uv[ok, 1] + 0.5).astype(np.int64)
        h, w = m.shape
        inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
        hit = np.zeros(len(u), bool)
        hit[inside] = miss[v[inside], u[inside]]
        votes[todo[np.flatnonzero(ok)[hit]]] += 1
    keep = votes >= support
    out[tuple(idx[keep].T)] = sole[keep]
    return out


def _project(cam, pts):
    """``cam.project(pts)``; one matrix product for a camera without distortion (the same pixels to ~1e-9 px)."""
    if np.any(cam.dist):
        return cam.project(pts)
    M = cam.K @ cam.R
    b = cam.K @ np.asarray(cam.t, float).ravel()
    # (M @ pts.T).T, not pts @ M.T: the same values (bit for bit on the dino's 15 cameras), but OpenBLAS's threads
    # took 58 against 16 ms CPU (248 / 140 against 64 / 39 ms wall) per 205 000 points (the dino's 15 cameras,
    # 10 alternating runs, load 11 on 2 cores)
    uvw = (M @ pts.T).T + b
    with np.errstate(divide="ignore", invalid="ignore"):
        w = np.where(uvw[:, 2] > 0, uvw[:, 2], np.nan)
        return uvw[:, :2] / w[:, None]


def _raster_of(idx, grid):
    """``MeshRaster`` of the boundary faces of the voxels ``idx`` ((n, 3) int, n > 0) of ``grid``, found in their
    bounding box only (a few voxels of a large grid)."""
    a, b = idx.min(axis=0), idx.max(axis=0) + 1
    occ = np.zeros(tuple(b - a), bool)
    occ[tuple((idx - a).T)] = True
    sub = VoxelGrid(tuple(np.asarray(grid.origin, float) + a * grid.voxel_size), grid.voxel_size, tuple(b - a))
    return MeshRaster(*voxel_boundary_quads(occ, sub))


def _required_voxels(need_who, n_views):
    """Per view, the voxels (``(n, 3)`` int indices, or None) that ``need_who`` requires of it: one pass over the
    grid instead of one per view."""
    idx = np.argwhere(need_who >= 0)
    out = [None] * n_views
    if not len(idx):
        return out
    views = need_who[tuple(idx.T)]
    order = np.argsort(views, kind="stable")
    idx, views = idx[order], views[order]
    cuts = np.searchsorted(views, np.arange(n_views + 1))
    for i in range(n_views):
        if cuts[i + 1] > cuts[i]:
            out[i] = idx[cuts[i]:cuts[i + 1]]
    return out


def _stats(d, ring):
    v = d[ring]
    if v.size < 50:
        return None
    med = float(np.median(v))
    sd = 1.4826 * float(np.median(np.abs(v - med)))
    return float(np.mean(v)), max(sd, SD_FLOOR), float(np.percentile(v, 99.5))


def _required_pixels(d, mask, need, prior, slack, level):
    """Rule 4: the parts of the prior within ``slack`` px of ``need`` that differ from the background (``d > level``),
    touch ``mask`` and hold a pixel of ``need`` (the voxels' projection is coarse: the part that joins it to the
    silhouette is taken with it); on the new outline, only pixels showing ``EDGE_FRACTION`` of the contrast of the
    silhouette's pixels around (as rule 5: a pixel covered by half or less shows half the contrast or less)."""
    import cv2

    zone = _dilate(need, NEED_BRIDGE_PX) & prior & ~mask & (d > level)
    if not zone.any():
        return zone
    n, lab = cv2.connectedComponents(zone.astype(np.uint8), connectivity=8)
    ok = np.zeros(n, bool)
    ok[np.unique(lab[_dilate(mask, 1) & zone])] = True
    has = np.zeros(n, bool)
    has[np.unique(lab[need & zone])] = True
    ok &= has
    ok[0] = False
    add = ok[lab]
    new = mask | add
    contrast = cv2.dilate(np.where(new, d, 0).astype(np.float32), np.ones((CONTRAST_WINDOW,) * 2, np.uint8))
    rim = add & _dilate(~new, 1)
    return add & ~(rim & (d < EDGE_FRACTION * contrast))


def _edge_grow(d, mask, allowed, hi_level, rounds):
    """Grow ``mask`` ring by ring into ``allowed`` by the sub-pixel rule; returns the grown mask."""
    import cv2

    m = mask.copy()
    k = np.ones((3, 3), np.uint8)
    for _ in range(rounds):
        cand = (cv2.dilate(m.astype(np.uint8), k) > 0) & ~m & allowed
        if not cand.any():
            break
        contrast = cv2.dilate(np.where(m, d, 0).astype(np.float32), np.ones((CONTRAST_WINDOW,) * 2, np.uint8))
        ok = cand & (d > hi_level) & (d >= EDGE_FRACTION * contrast)
        if not ok.any():
            break
        m |= ok
    return m


def _regions(d, missing, stats, mask, ring):
    """The connected parts of ``missing`` next to ``mask`` whose mean difference is not the background's
    next to them (the background ring within ``RING_PX[1]`` px of the part; the whole ring's when too few)."""
    import cv2

    n, lab, st, _ = cv2.connectedComponentsWithStats(missing.astype(np.uint8), connectivity=8)
    out = np.zeros(missing.shape, bool)
    if n <= 1:
        return out
    area = st[:, cv2.CC_STAT_AREA]
    touch = np.zeros(n, bool)
    touch[np.unique(lab[_dilate(mask, 1) & missing])] = True
    big = REGION_FRACTION * np.count_nonzero(mask)
    edge = _dilate(mask, 1)
    for k in np.flatnonzero(touch & (area >= MIN_REGION) & (area <= big)):
        if k == 0:
            continue
        x, y, w, h = st[k, :4]
        r = 2 * RING_PX[1]
        sl = (slice(max(y - r, 0), y + h + r), slice(max(x - r, 0), x + w + r))
        part = lab[sl] == k
        near = ring[sl] & _dilate(part, r)
        v = d[sl][near]
        if v.size >= 30:
            med = float(np.median(v))
            mean_b, sd_b = float(np.mean(v)), max(1.4826 * float(np.median(np.abs(v - med))), SD_FLOOR)
        else:
            mean_b, sd_b = stats[0], stats[1]
        core = part & ~edge[sl]  # the pixels next to the silhouette blend with it: judged by the edge rule
        a = float(np.count_nonzero(core))
        if a < MIN_REGION:
            continue
        if float(d[sl][core].mean()) > mean_b + max(REGION_SE * sd_b / np.sqrt(a), REGION_SD * sd_b):
            out[sl] |= part
    return out


def refine_view(d: np.ndarray, mask: np.ndarray, prior: np.ndarray, slack: int, *, keyed: bool = False,
                need: np.ndarray | None = None) -> tuple[np.ndarray, dict]:
    """One view's joint refinement: its difference image against the prior's projection.

    Parameters
    ----------
    d : (H, W) float32
        The view's difference image (grey levels or Delta E).
    mask : (H, W) bool
        Its silhouette so far.
    prior : (H, W) bool
        The projection of the tolerant hull of the views.
    slack : int, px
        How far the prior's projection may overshoot the specimen's outline
        (voxel size and bounding-box margin).
    keyed : bool
        A keyed view (Delta E to one backdrop colour): the required rule and
        the removal only, not the edge and region rules (module docstring).
    need : (H, W) bool, optional
        The projection of the voxels only this view carves that other views
        require (:func:`required_by_others`).

    Returns
    -------
    mask : (H, W) bool
    info : dict
        ``added_required``, ``added_edge``, ``added_regions``, ``removed`` (px).
    """
    ring = _dilate(prior, RING_PX[1] + slack) & ~_dilate(prior, RING_PX[0] + slack)
    st = _stats(d, ring)
    info = {"added_required": 0, "added_edge": 0, "added_regions": 0, "removed": 0}
    out = mask.copy()
    if st is not None and not keyed:
        grown = _edge_grow(d, out, prior, st[2], EDGE_ROUNDS)
        deep = _erode(prior, slack)
        parts = _regions(d, deep & ~grown, st, grown, ring)
        if parts.any():
            grown2 = _edge_grow(d, grown | parts, prior, st[2], EDGE_ROUNDS)
            info["added_regions"] = int(np.count_nonzero(grown2 & ~grown))
        else:
            grown2 = grown
        info["added_edge"] = int(np.count_nonzero(grown & ~out))
        out = grown2
    if st is not None and need is not None and need.any():  # after the rules above: what they left
        req = _required_pixels(d, out, need, prior, slack, st[0] + NEED_SD * st[1])
        info["added_required"] = int(np.count_nonzero(req))
        out |= req
    keep = _dilate(prior, slack)
    removed = out & ~keep
    if np.count_nonzero(removed) <= REMOVE_FRACTION * np.count_nonzero(out):
        info["removed"] = int(np.count_nonzero(removed & mask))
        out &= ~removed
    else:
        info["removal_skipped_px"] = int(np.count_nonzero(removed))
    return out, info


def joint_masks(masks: Sequence[np.ndarray], differences: Sequence[np.ndarray | None], cameras: Sequence[Camera],
                box: tuple, *, iterations: int = ITERATIONS, keyed: bool = False) -> tuple[list[np.ndarray], dict]:
    """Masks of every view refined together (module docstring); views without a difference image are kept.

    ``keyed=True`` (views keyed against one backdrop colour) leaves out the edge and region rules: see
    the module docstring.

    Returns
    -------
    masks : list of (H, W) bool
    summary : dict
        ``iterations``, ``seconds``, ``voxel_mm``, and ``views``: per view
        ``added`` and ``removed`` (px, against the first pass) and the
        rules' shares of the last round.
    """
    t0 = time.perf_counter()
    first = [np.asarray(m, bool) for m in masks]
    cur = [m.copy() for m in first]
    editable = [d is not None for d in differences]
    lo, hi = (np.asarray(v, float) for v in box)
    box2 = (lo, hi)
    rounds, voxel, last = 0, None, [None] * len(cur)
    for _ in range(int(iterations)):
        grid, (counts, who) = prior_hull(cur, cameras, box2, sole=True)
        hull = counts <= TOLERANCE
        voxel = grid.voxel_size
        if not hull.any():
            break
        shapes = [np.shape(m)[:2] for m in cur]
        exact = MeshRaster(*voxel_boundary_quads(counts == 0, grid))
        explained = [_dilate(exact.mask(c, sh), EXPLAIN_PX) for c, sh in zip(cameras, shapes)]
        need_who = required_by_others(grid, counts, who, cur, explained, cameras, support=NEED_SUPPORT)
        rounds += 1
        changed = 0
        new = []
        # the hull's boundary faces once per round, projected into every view (as raster.model_mask of the
        # occupancy, which finds them again per view: 60 % of the step's time on the dino's 15 views)
        raster = MeshRaster(*voxel_boundary_quads(hull, grid))
        required = _required_voxels(need_who, len(cameras))
        for i, cam in enumerate(cameras):
            if not editable[i]:
                new.append(cur[i])
                continue
            fp = cam.pixel_footprint(np.asarray(grid.origin) + 0.5 * voxel * np.asarray(grid.shape))
            slack = int(math.ceil(2.5 * voxel / fp)) if math.isfinite(fp) and fp > 0 else 3
            prior = raster.mask(cam, np.shape(differences[i])[:2])
            need = None if required[i] is None else _raster_of(required[i], grid).mask(cam, shapes[i])
            m, last[i] = refine_view(np.asarray(differences[i], np.float32), cur[i], prior, slack, keyed=keyed,
                                     need=need)
            changed += int(np.count_nonzero(m != cur[i]))
            new.append(m)
        cur = new
        if changed == 0:
            break
    views = []
    for i in range(len(cur)):
        row = {"added": int(np.count_nonzero(cur[i] & ~first[i])), "removed": int(np.count_nonzero(first[i] & ~cur[i]))}
        if last[i] is not None:
            row["last_round"] = last[i]
        views.append(row)
    summary = {"iterations": rounds, "seconds": round(time.perf_counter() - t0, 3),
               "voxel_mm": None if voxel is None else round(float(voxel), 4), "views": views}
    return cur, summary
