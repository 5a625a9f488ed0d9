"""Sub-voxel visual hull: a scalar field whose 0.5 level is the hull's surface.

A binary voxel model puts its surface on voxel faces, so its volume error is
of the order of the voxel size times the surface area.  :func:`hull_field`
instead samples, at every voxel centre, how far the centre lies inside the
visual hull, so that marching cubes at level 0.5 places the surface between
voxel centres, within a small fraction of a voxel of the true hull.

Method
------
1. For each view, a signed distance image (px, inside positive) to the
   silhouette's outline, exact near the outline and sub-pixel:

   * the outline crosses every lattice edge between two neighbouring pixel
     centres of opposite class (coverage ``>= 0.5`` vs ``< 0.5``).  Where it
     crosses is estimated from the coverage of the pixels along that row (or
     column): with area coverage, the pixels from a fully covered one to an
     empty one hold exactly the length of the row inside the silhouette, so
     ``crossing = (first full pixel) - 0.5 + sum(coverage)``, exact for a
     straight outline at any angle (walks are limited to 3 pixels each side
     and the crossing is kept between the two pixel centres).  A bool mask
     puts the crossing half-way between the pixel centres;
   * the crossings are joined cell by cell by marching squares (saddles
     resolved by the mean coverage of the cell) into line segments, and the
     Euclidean distance to the nearest segment is computed exactly for every
     pixel within a band around the outline (wide enough for one voxel,
     at most 32 px); further away ``cv2.distanceTransform`` of the two
     classes is used (those values only need to be large: the field is
     clipped at one voxel).
2. Every voxel centre is projected with the full camera model (distortion
   and skew); the distance image is sampled bilinearly there and converted to
   mm at the voxel's depth, ``d_mm = d_px * Z_cam / sqrt(det J)``, with ``J``
   the local Jacobian (px per unit of normalized image coordinate) of the
   projection, i.e. ``f`` corrected for the local magnification of the lens
   distortion.
3. The field is ``0.5 + m / voxel_size`` clipped to ``[-0.5, 1.5]``, where ``m``
   is the minimum over views of ``d_mm`` (with ``tolerance=k``: the
   ``(k + 1)``-th smallest, so the ``k`` most negative views of each voxel
   are ignored).  The 0.5 level is then where the nearest silhouette outline
   passes through the voxel's viewing ray, i.e. the hull's surface.  The
   values are clipped at one voxel (not half a voxel) from the surface:
   marching cubes interpolates linearly between neighbouring voxel centres,
   one voxel apart, so both ends of an edge that crosses the surface must
   keep their true values for the crossing to land in the right place.
   Any padding value ``< 0.5`` (e.g. 0) closes the surface at the grid's
   faces.

Views that cannot see a voxel do not constrain it: a voxel whose centre lies
on or behind a camera's image plane (``Z_cam <= 0``) or projects outside the
image (beyond the outer edge of the border pixels) is neither carved nor
kept by that view.  A voxel constrained by fewer than ``min_views`` views is
set to -0.5 (empty).

Only voxels within a voxel of the surface hold anything but the clip values,
so :func:`hull_field` computes the field in a narrow band
(:mod:`organlab.carving._band`): the same values as computing it at every
voxel (``_dense_field``, kept as the yardstick), at a cost that grows with the
surface's area instead of the grid's volume.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import numpy as np
from numba import njit, prange

from ..bandfield import BandField
from ..camera import Camera
from ..grid import VoxelGrid
from ..masks import Silhouette, as_arrays
from ..nbcam import pack_camera
from ._band import band_field
from ._bbox import _check_grid
from ._sample import insert_smallest, view_dmm

__all__ = ["hull_field"]

_WALK = 3  # pixels walked each side of a crossing to find saturated coverage
_SAT = 1.0 - 1e-6
_EMPTY = 1e-6
_MAX_BAND = 32


# ---------------------------------------------------------------- validation
def _as_coverage(silhouette, camera, index):
    if not isinstance(camera, Camera):
        raise TypeError(f"camera {index} must be an organlab.camera.Camera, got {type(camera).__name__}")
    s = np.asarray(silhouette)
    if s.ndim != 2:
        raise ValueError(f"silhouette {index} must be a 2-D (H, W) array, got shape {s.shape}")
    w, h = camera.image_size
    if s.shape != (h, w):
        raise ValueError(
            f"silhouette {index} has shape (H, W) = {s.shape} but its camera's image_size (width, height) is {(w, h)}"
        )
    if s.dtype == bool:
        return s.astype(np.float32)
    if not np.issubdtype(s.dtype, np.floating):
        raise ValueError(
            f"silhouette {index} must be a bool mask or a float coverage image in [0, 1], got dtype {s.dtype} "
            "(use mask > 0 for a label image or image / 255.0 for 8-bit coverage)"
        )
    c = s.astype(np.float32)
    if not np.all(np.isfinite(c)) or c.min() < 0.0 or c.max() > 1.0:
        raise ValueError(f"silhouette {index}: float coverage must be finite and within [0, 1]")
    return c


# ------------------------------------------------------ signed distance (px)
@njit(cache=True, nogil=True)
def _crossing(line, k, inside_first):
    """Crossing of the outline between samples ``k`` and ``k + 1`` of a line.

    Returns the position along the line (in samples), within ``[k, k + 1]``.
    """
    n = line.shape[0]
    if inside_first:
        j0 = k
        while line[j0] < _SAT and j0 > 0 and k - j0 < _WALK and line[j0 - 1] >= 0.5:
            j0 -= 1
        j1 = k + 1
        while line[j1] > _EMPTY and j1 < n - 1 and j1 - k - 1 < _WALK and line[j1 + 1] < 0.5:
            j1 += 1
        s = 0.0
        for j in range(j0, j1 + 1):
            s += line[j]
        pos = j0 - 0.5 + s
    else:
        j0 = k
        while line[j0] > _EMPTY and j0 > 0 and k - j0 < _WALK and line[j0 - 1] < 0.5:
            j0 -= 1
        j1 = k + 1
        while line[j1] < _SAT and j1 < n - 1 and j1 - k - 1 < _WALK and line[j1 + 1] >= 0.5:
            j1 += 1
        s = 0.0
        for j in range(j0, j1 + 1):
            s += line[j]
        pos = j1 + 0.5 - s
    if pos < k:
        pos = float(k)
    elif pos > k + 1:
        pos = float(k + 1)
    return pos


@njit(cache=True, nogil=True)
def _segment_update(dist, ax, ay, bx, by, band):
    """Lower ``dist`` (px) to the distance from each pixel centre to segment a-b."""
    h, w = dist.shape
    c0 = max(int(math.floor(min(ax, bx))) - band, 0)
    c1 = min(int(math.ceil(max(ax, bx))) + band, w - 1)
    r0 = max(int(math.floor(min(ay, by))) - band, 0)
    r1 = min(int(math.ceil(max(ay, by))) + band, h - 1)
    dx = bx - ax
    dy = by - ay
    ll = dx * dx + dy * dy
    for r in range(r0, r1 + 1):
        for c in range(c0, c1 + 1):
            px = c - ax
            py = r - ay
            t = 0.0
            if ll > 0.0:
                t = (px * dx + py * dy) / ll
                if t < 0.0:
                    t = 0.0
                elif t > 1.0:
                    t = 1.0
            ex = px - t * dx
            ey = py - t * dy
            d = math.sqrt(ex * ex + ey * ey)
            if d < dist[r, c]:
                dist[r, c] = d


@njit(cache=True, nogil=True)
def _transition_box(inside):
    """Rows and columns of the cells (2 x 2 pixel centres) that hold a class change.

    Returns ``(r0, r1, c0, c1)``, inclusive; ``r1 < r0`` when there is none.
    """
    h, w = inside.shape
    rmin, rmax, cmin, cmax = h, -1, w, -1
    for r in range(h):
        for c in range(w):
            a = inside[r, c]
            if (c + 1 < w and inside[r, c + 1] != a) or (r + 1 < h and inside[r + 1, c] != a):
                rmin = min(rmin, r)
                rmax = max(rmax, r)
                cmin = min(cmin, c)
                cmax = max(cmax, c)
    # a horizontal edge of row r borders cells r - 1 and r; a vertical edge of column c, cells c - 1 and c
    return max(rmin - 1, 0), min(rmax, h - 2), max(cmin - 1, 0), min(cmax, w - 2)


@njit(cache=True, nogil=True)
def _outline_distance(cov, band):
    """Unsigned distance (px) from pixel centres to the outline, exact within ``band``.

    Pixels farther than ``band`` from the outline keep the value ``band + 1``.
    Only the cells within the box of class changes are visited.
    """
    h, w = cov.shape
    inside = np.empty((h, w), dtype=np.bool_)
    for r in range(h):
        for c in range(w):
            inside[r, c] = cov[r, c] >= 0.5
    dist = np.full((h, w), band + 1.0)
    R0, R1, C0, C1 = _transition_box(inside)
    if R1 < R0 or C1 < C0:
        return dist, inside
    # hx[r - R0, c - C0]: column position of the crossing on row r between c and c + 1
    hx = np.full((R1 - R0 + 2, C1 - C0 + 1), np.nan)
    # vy[r - R0, c - C0]: row position of the crossing on column c between r and r + 1
    vy = np.full((R1 - R0 + 1, C1 - C0 + 2), np.nan)
    for r in range(R0, R1 + 2):
        for c in range(C0, C1 + 1):
            if inside[r, c] != inside[r, c + 1]:
                hx[r - R0, c - C0] = _crossing(cov[r, :], c, inside[r, c])
    for c in range(C0, C1 + 2):
        col = cov[:, c]
        for r in range(R0, R1 + 1):
            if inside[r, c] != inside[r + 1, c]:
                vy[r - R0, c - C0] = _crossing(col, r, inside[r, c])
    px = np.empty(4)
    py = np.empty(4)
    for r in range(R0, R1 + 1):
        for c in range(C0, C1 + 1):
            # edges in order: top, right, bottom, left
            n = 0
            t = hx[r - R0, c - C0]
            rt = vy[r - R0, c + 1 - C0]
            bt = hx[r + 1 - R0, c - C0]
            lf = vy[r - R0, c - C0]
            if math.isnan(t) and math.isnan(rt) and math.isnan(bt) and math.isnan(lf):
                continue
            if not math.isnan(t):
                px[n] = t
                py[n] = r
                n += 1
            if not math.isnan(rt):
                px[n] = c + 1
                py[n] = rt
                n += 1
            if not math.isnan(bt):
                px[n] = bt
                py[n] = r + 1
                n += 1
            if not math.isnan(lf):
                px[n] = c
                py[n] = lf
                n += 1
            if n == 2:
                _segment_update(dist, px[0], py[0], px[1], py[1], band)
            elif n == 4:
                # saddle: corners tl, br share a class, tr, bl the other
                centre = 0.25 * (
                    np.float64(cov[r, c]) + np.float64(cov[r, c + 1]) + np.float64(cov[r + 1, c])
                    + np.float64(cov[r + 1, c + 1])
                )
                tl_in = inside[r, c]
                if (centre >= 0.5) == tl_in:
                    # tl and br connected through the centre: cut off tr and bl
                    _segment_update(dist, px[0], py[0], px[1], py[1], band)  # top-right
                    _segment_update(dist, px[2], py[2], px[3], py[3], band)  # bottom-left
                else:
                    # cut off tl and br
                    _segment_update(dist, px[3], py[3], px[0], py[0], band)  # left-top
                    _segment_update(dist, px[1], py[1], px[2], py[2], band)  # right-bottom
    return dist, inside


@njit(cache=True, nogil=True)
def _signed(dist, inside):
    """``np.where(inside, dist, -dist).astype(float32)``."""
    h, w = dist.shape
    out = np.empty((h, w), dtype=np.float32)
    for r in range(h):
        for c in range(w):
            out[r, c] = dist[r, c] if inside[r, c] else -dist[r, c]
    return out


def _signed_distance(coverage, band, *, far_field=True):
    """Signed distance image, px, inside positive, float32 ``(H, W)``.

    Exact within ``band`` px of the outline; farther, ``cv2.distanceTransform``
    values when ``far_field``, else ``+-(band + 1)``.
    """
    import cv2

    cov = np.ascontiguousarray(coverage)
    if cov.dtype not in (np.float32, np.float64):
        cov = cov.astype(np.float64)
    h, w = cov.shape
    if h < 2 or w < 2:
        raise ValueError(f"silhouettes must be at least 2 x 2 pixels, got {cov.shape}")
    dist, inside = _outline_distance(cov, int(band))
    far = dist > band if far_field else None
    if far_field and far.any():
        ins = inside.astype(np.uint8)
        if ins.all() or not ins.any():
            # no outline at all: everything equally far (the field is clipped anyway)
            dt = np.full(cov.shape, np.float32(4 * (h + w)))
        else:
            d_in = cv2.distanceTransform(ins, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
            d_out = cv2.distanceTransform(1 - ins, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
            dt = np.where(inside, d_in, d_out) - 0.5
        dist = np.where(far, np.maximum(dt, band + 1.0), dist)
    return _signed(dist, inside)


# --------------------------------------------------------- voxel accumulation
@njit(cache=True, parallel=True)
def _accumulate(sdf, cp, origin, vs, shape, best, seen, lim):
    """Fold one view into the per-voxel ``k + 1`` smallest distances (mm).

    ``cp`` is the packed camera (:func:`organlab.nbcam.pack_camera`).
    ``best`` is ``(N, k + 1)`` float32 sorted ascending per row.
    """
    h, w = sdf.shape
    nx, ny, nz = shape[0], shape[1], shape[2]
    kk = best.shape[1]
    for i in prange(nx):
        x = origin[0] + i * vs
        for j in range(ny):
            y = origin[1] + j * vs
            base = (i * ny + j) * nz
            for k in range(nz):
                n = base + k
                if best[n, kk - 1] <= -lim:
                    continue  # already carved by k + 1 views: stays empty
                z = origin[2] + k * vs
                ok, dmm = view_dmm(sdf, h, w, cp, x, y, z, lim)
                if ok:
                    seen[n] += 1
                    insert_smallest(best[n], dmm)


def _band_px(camera, grid):
    """Band of exact distances, px: one voxel at the grid's nearest depth, with margin.

    Returns ``(band, far_field)``: ``far_field`` is True when the band had to
    be capped at ``_MAX_BAND`` px and distances beyond it are needed.
    """
    lo, hi = grid.bounds
    corners = np.array([[a, b, c] for a in (lo[0], hi[0]) for b in (lo[1], hi[1]) for c in (lo[2], hi[2])])
    zmin = camera.world_to_camera(corners)[:, 2].min()
    if zmin <= grid.voxel_size:
        return _MAX_BAND, True
    f = math.sqrt(camera.K[0, 0] * camera.K[1, 1])
    band = math.ceil(grid.voxel_size * f * 1.5 / zmin + 2.0)
    return int(min(max(band, 3), _MAX_BAND)), band > _MAX_BAND


def hull_field(
    silhouettes: Sequence[Silhouette | np.ndarray],
    cameras: Sequence[Camera],
    grid: VoxelGrid,
    *,
    tolerance: int = 0,
    min_views: int = 1,
    progress: Callable[[int, int], object] | None = None,
    sparse: bool = False,
) -> np.ndarray | BandField:
    """Field sampled at voxel centres whose 0.5 level is the visual hull's surface.

    The value at a voxel centre is ``0.5 + m / voxel_size`` clipped to
    ``[-0.5, 1.5]``, where ``m`` (mm) is the smallest signed distance, over the
    views, between the centre's viewing ray and the silhouette's outline
    (inside positive), measured in the image with sub-pixel accuracy and
    converted to mm at the centre's depth (see the module docstring).
    Marching cubes at level 0.5 on this field (padded with 0) gives the hull's
    surface between voxel centres, nearly as accurate at 2 mm as at 1 mm.

    Parameters
    ----------
    silhouettes : sequence of (H, W) bool or float arrays, or of Silhouette
        One per view (a :class:`~organlab.silhouette.Silhouette` gives its
        ``coverage``): a bool mask (``True`` = specimen) or a float coverage
        image in ``[0, 1]`` (the fraction of each pixel covered by the
        specimen, e.g. an anti-aliased or soft-thresholded silhouette; the
        outline is where coverage crosses 0.5, located sub-pixel).
    cameras : sequence of Camera
        The calibrated camera of each view, ``image_size == (W, H)``.
    grid : VoxelGrid
        The voxel space, mm, world frame.
    tolerance : int
        Views ignored per voxel: the ``tolerance`` most negative views of each
        voxel do not count (robustness to a few bad silhouettes).  0 = the
        classic visual hull.
    min_views : int
        Voxels constrained by fewer views (seen in fewer images, or all
        behind the cameras) are set to -0.5 (empty).  Views that cannot see a
        voxel (behind the camera or outside the image) never constrain it.
        ``min_views=0`` keeps voxels that no view sees (value 1.5).  With
        ``tolerance=k``, a voxel constrained by ``k`` views or fewer is
        not carved (the ``k`` views it may ignore are all it has).
    progress : callable(done, total), optional
        Called after each view's distance image.
    sparse : bool
        Return the field as a :class:`~organlab.carving.BandField` (values
        stored only in blocks the surface crosses; ``.dense()``,
        ``.occupancy()``, ``.mesh()``) instead of the dense array.

    Returns
    -------
    field : grid.shape float32, or BandField when ``sparse``
        In ``[-0.5, 1.5]``, axes x, y, z; > 0.5 inside the hull, 0.5 on its
        surface, -0.5 (1.5) one voxel or more outside (inside).

    Raises
    ------
    ValueError
        Mismatched numbers of silhouettes and cameras, a silhouette whose
        shape is not its camera's image size, integer images, coverage out of
        ``[0, 1]``, or a negative ``tolerance`` / ``min_views``.
    TypeError
        A camera that is not a :class:`~organlab.camera.Camera` or a grid that
        is not a :class:`~organlab.grid.VoxelGrid`.

    Notes
    -----
    Marching cubes at level 0.5 of the field padded by any value ``< 0.5``
    (e.g. ``np.pad(field, 1)``) gives a closed surface.

    The field is computed in a narrow band (:mod:`organlab.carving._band`):
    blocks of voxels that every view sees at least a voxel inside the
    silhouette, or that a view sees at least a voxel outside, are decided
    coarse to fine with summed-area tables and filled with the clip values;
    only the blocks the surface crosses are computed voxel by voxel.  The
    values are those of the field computed at every voxel (tested: 0
    differences).  Memory: the views' distance images (4 bytes per pixel and
    view, 12 with the tables) plus a byte and an index per block of 4^3
    voxels and the band's values; time and memory grow with the surface's
    area, not the grid's volume (``benchmarks/bench_stages.py``).

    Examples
    --------
    >>> import tempfile
    >>> import organlab as ol
    >>> from organlab.synthetic import with_true_cameras
    >>> s = ol.load_session(with_true_cameras("sample_sessions/aaa_phantom", tempfile.mkdtemp() + "/aaa", step=6))
    >>> cal, _ = ol.calibration_for(s)
    >>> grid = ol.VoxelGrid.from_session(s, voxel_size=4.0)
    >>> field = ol.hull_field(ol.silhouettes(s), cal.cameras(s), grid, sparse=True)
    >>> field
    BandField(shape=(35, 35, 50), block=4, band_blocks=167, 0.0 MB)
    >>> field.n_inside() * grid.voxel_size**3  # mm^3 (the phantom: 165 661 mm^3; 6 views leave the hull larger)
    176448.0
    """
    _check_grid(grid)
    if isinstance(silhouettes, np.ndarray) and silhouettes.ndim == 2:
        silhouettes = [silhouettes]
    cameras = [cameras] if isinstance(cameras, Camera) else list(cameras)
    silhouettes = as_arrays(silhouettes, "coverage")
    if len(silhouettes) != len(cameras):
        raise ValueError(f"got {len(silhouettes)} silhouettes but {len(cameras)} cameras: give one camera per silhouette")
    if len(cameras) == 0:
        raise ValueError("no views: give at least one silhouette and its camera")
    for name, value in (("tolerance", tolerance), ("min_views", min_views)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 0:
            raise ValueError(f"{name} must be an integer >= 0, got {value!r}")
    tolerance = int(tolerance)
    if not isinstance(sparse, (bool, np.bool_)):
        raise ValueError(f"sparse must be True or False, got {sparse!r}")
    # validate everything before computing anything
    coverages = [_as_coverage(s, c, i) for i, (s, c) in enumerate(zip(silhouettes, cameras))]

    sdfs = _distance_images(coverages, cameras, grid, progress)
    field = band_field(sdfs, cameras, grid, tolerance=tolerance, min_views=min_views)
    return field if sparse else field.dense()


def _distance_images(coverages, cameras, grid, progress=None):
    """The views' signed distance images (px), computed in threads (the kernels release the GIL).

    Returns a ``(V, H, W)`` float32 array when all views have one size, else a list.
    """
    import os
    from concurrent.futures import ThreadPoolExecutor

    def one(i):
        band, far_field = _band_px(cameras[i], grid)
        return _signed_distance(coverages[i], band, far_field=far_field)

    n = len(cameras)
    shapes = {c.shape for c in coverages}
    # one (V, H, W) array when the views share a size (no second copy when stacking)
    sdfs = np.empty((n, *shapes.pop()), dtype=np.float32) if len(shapes) == 1 else [None] * n
    with ThreadPoolExecutor(max_workers=max(1, min(n, os.cpu_count() or 1))) as pool:
        for i, sdf in enumerate(pool.map(one, range(n))):
            sdfs[i] = sdf
            if progress is not None:
                progress(i + 1, n)
    return sdfs


def _dense_field(coverages, cameras, grid, *, tolerance=0, min_views=1):
    """The hull field computed at every voxel (the yardstick of the band field).

    ``coverages``: float32 ``(H, W)`` images already validated.
    """
    lim = grid.voxel_size
    n = grid.n_voxels
    best = np.full((n, tolerance + 1), np.float32(lim), dtype=np.float32)
    seen = np.zeros(n, dtype=np.uint16 if len(cameras) < 65535 else np.uint32)
    origin = np.asarray(grid.origin, dtype=np.float64)
    shape = np.asarray(grid.shape, dtype=np.int64)
    for cov, cam in zip(coverages, cameras):
        band, far_field = _band_px(cam, grid)
        sdf = _signed_distance(cov, band, far_field=far_field)
        _accumulate(sdf, pack_camera(cam), origin, float(grid.voxel_size), shape, best, seen, np.float32(lim))
    m = best[:, tolerance].astype(np.float64)
    field = np.clip(0.5 + m / grid.voxel_size, -0.5, 1.5)
    if min_views > 0:
        field[seen < min_views] = -0.5
    return field.reshape(grid.shape).astype(np.float32)


def warm_kernels() -> None:
    """Load the hull field's numba kernels from their cache, ahead of the first :func:`hull_field`.

    A hull of one tiny view (a square silhouette, 8 x 8 px) in a grid of 8^3 voxels: the dtypes and
    layouts the stage passes, so the same compiled specialisations (the distance image's, the band's
    classification and values, the inside count, the occupancy).  The ``reconstruct`` command calls it
    on its loading thread while the silhouettes run: 0.2 s CPU of kernel loads (measured alone, after
    the silhouettes' kernels) that were the hull stage's (issue 24).
    """
    K = np.array([[8.0, 0.0, 3.5], [0.0, 8.0, 3.5], [0.0, 0.0, 1.0]])
    camera = Camera(K, np.zeros(5), np.eye(3), np.array([0.0, 0.0, 20.0]), image_size=(8, 8))
    cov = np.zeros((8, 8), np.float32)
    cov[2:6, 2:6] = 1.0
    grid = VoxelGrid((-3.5, -3.5, -3.5), 1.0, (8, 8, 8))
    field = hull_field([cov], [camera], grid, sparse=True)
    field.n_inside()
    field.occupancy()
