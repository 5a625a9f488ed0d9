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
2. the *colour evidence*: each view's difference image (the distance to the
   background model, grey levels, or Delta E to the backdrop) is compared
   with the background's own statistics, measured in a ring just outside the
   prior's projection (median, MAD, 99.5th percentile);
3. *edge growth* (sub-pixel rule): a pixel next to the silhouette and
   inside the prior is added where it differs from the background beyond
   the ring's 99.5th percentile and by at least ``EDGE_FRACTION`` (0.6) of the contrast of
   the silhouette's pixels around it (an edge pixel covered by a fraction ``a``
   of the specimen shows ``a`` times that contrast: the rule adds the pixels
   the specimen covers by more than half, the ones a global threshold drops
   where the specimen's edge is shaded);
4. *regions the others require*: a connected part of the prior's
   projection, eroded by its slack (the voxels' size and the bounding-box
   test's margin), that the silhouette misses is added whole when its mean
   difference exceeds the background ring's (by 4 standard errors, and half
   a standard deviation): dark, but not the background;
5. *removal*: silhouette pixels beyond the prior's projection (widened by its
   slack) are dropped: nothing the other views see explains them (a cast
   shadow on the plate, a strip of the stand);
6. repeat with the new silhouettes until no pixel changes (at most
   ``ITERATIONS`` rounds).

Given masks are never changed (they are priors for the others).  A correct
silhouette is not grown: beyond it the prior's projection is only its slack
(rejected by region 4's erosion), and edge pixels the specimen covers by half
or less fail rule 3.
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


def _carve_tolerant(masks, cameras, lo, hi, voxel):
    grid = VoxelGrid.from_roi(lo, hi, voxel)
    carver = ProgressiveCarver(grid, tolerance=TOLERANCE)
    for m, c in zip(masks, cameras):
        carver.add_view(m, c)
    return grid, carver.occupancy


def prior_hull(masks: Sequence[np.ndarray], cameras: Sequence[Camera], box: tuple) -> tuple[VoxelGrid, np.ndarray]:
    """The tolerant hull (``TOLERANCE`` views may carve a voxel) of masks, on a grid of ~``VOXEL_PX`` px footprints.

    Coarse first (the box in ~48 voxels along its largest side) to find where
    the hull lies, then fine in that part of the box.
    """
    lo, hi = (np.asarray(v, float) for v in box)
    coarse = float((hi - lo).max()) / 48.0
    g, occ = _carve_tolerant(masks, cameras, lo, hi, coarse)
    if not occ.any():
        return g, occ
    idx = np.argwhere(occ)
    a, b = idx.min(axis=0) - 1, idx.max(axis=0) + 2
    lo2 = np.maximum(lo, lo + a * coarse)
    hi2 = np.minimum(hi, lo + b * coarse)
    fp = footprint_mm(cameras, 0.5 * (lo2 + hi2))
    voxel = VOXEL_PX * fp if math.isfinite(fp) else coarse / 4
    voxel = max(voxel, (float(np.prod(hi2 - lo2)) / MAX_VOXELS) ** (1.0 / 3.0))
    return _carve_tolerant(masks, cameras, lo2, hi2, voxel)


def _stats(d, ring):
    v = d[ring]
    if v.size < 50:
        return None
    med = float(np.median(v))
    sd = 1.4826 * float(np.median(np.abs(v - med)))
    return float(np.mean(v)), max(sd, SD_FLOOR), float(np.percentile(v, 99.5))


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


def refine_view(d: np.ndarray, mask: np.ndarray, prior: np.ndarray, slack: int, *,
                regions: bool = True) -> tuple[np.ndarray, dict]:
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
    regions : bool
        Whether the region rule runs (the edge rule and the removal always do).

    Returns
    -------
    mask : (H, W) bool
    info : dict
        ``added_edge``, ``added_regions``, ``removed`` (px).
    """
    ring = _dilate(prior, RING_PX[1] + slack) & ~_dilate(prior, RING_PX[0] + slack)
    st = _stats(d, ring)
    info = {"added_edge": 0, "added_regions": 0, "removed": 0}
    out = mask.copy()
    if st is not None:
        grown = _edge_grow(d, out, prior, st[2], EDGE_ROUNDS)
        deep = _erode(prior, slack)
        parts = _regions(d, deep & ~grown, st, grown, ring) if regions else None
        if parts is not None and parts.any():
            grown2 = _edge_grow(d, grown | parts, prior, st[2], EDGE_ROUNDS)
            info["added_regions"] = int(np.count_nonzero(grown2 & ~grown))
        else:
            grown2 = grown
        info["added_edge"] = int(np.count_nonzero(grown & ~out))
        out = grown2
    keep = _dilate(prior, slack)
    removed = out & ~keep
    if np.count_nonzero(removed) <= REMOVE_FRACTION * np.count_nonzero(out):
        info["removed"] = int(np.count_nonzero(removed & mask))
        out &= ~removed
    else:
        info["removal_skipped_px"] = int(np.count_nonzero(removed))
    return out, info


def joint_masks(masks: Sequence[np.ndarray], differences: Sequence[np.ndarray | None], cameras: Sequence[Camera],
                box: tuple, *, iterations: int = ITERATIONS, regions: bool = True) -> tuple[list[np.ndarray], dict]:
    """Masks of every view refined together (module docstring); views without a difference image are kept.

    ``regions=False`` leaves out the region rule (4): keyed views (a backdrop colour, no model of the
    background per pixel) of a dark specimen have no colour evidence for it (see SilhouetteModel.joint).

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
        grid, hull = prior_hull(cur, cameras, box2)
        voxel = grid.voxel_size
        if not hull.any():
            break
        rounds += 1
        changed = 0
        new = []
        # the hull's boundary faces once per round, projected into every view (as raster.model_mask of the
        # occupancy, which finds them again per view: 60 % of the step's time on the dino's 15 views)
        raster = MeshRaster(*voxel_boundary_quads(hull, grid))
        for i, cam in enumerate(cameras):
            if not editable[i]:
                new.append(cur[i])
                continue
            fp = cam.pixel_footprint(np.asarray(grid.origin) + 0.5 * voxel * np.asarray(grid.shape))
            slack = int(math.ceil(2.5 * voxel / fp)) if math.isfinite(fp) and fp > 0 else 3
            prior = raster.mask(cam, np.shape(differences[i])[:2])
            m, last[i] = refine_view(np.asarray(differences[i], np.float32), cur[i], prior, slack, regions=regions)
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
