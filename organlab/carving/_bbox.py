"""Visual hull by the thesis's bounding-box test.

The test, for one voxel and one view
------------------------------------
The 8 corners of the voxel are projected through the full camera model
(:meth:`organlab.camera.Camera.project`, with distortion and skew).  The
axis-aligned bounding box ``[umin, umax] x [vmin, vmax]`` of the 8 projected
points (pixel coordinates, pixel centres are integers, so pixel ``(u, v)``
covers ``[u - 0.5, u + 0.5] x [v - 0.5, v + 0.5]``) covers every pixel whose
square meets the closed box, i.e. the columns and rows

    ``c0 = ceil(umin - 0.5) .. c1 = floor(umax + 0.5)``,
    ``r0 = ceil(vmin - 0.5) .. r1 = floor(vmax + 0.5)``

(at least one column and one row: a box touching a pixel's edge covers it).
The view *carves* the voxel if none of these pixels is a silhouette pixel.
Conservative rules, so that a view never carves what it cannot see:

* pixels outside the image are unknown and count as silhouette: a voxel whose
  pixel range reaches outside the image (``c0 < 0``, ``r0 < 0``,
  ``c1 > width - 1`` or ``r1 > height - 1``) is not carved by that view;
* a voxel with a corner on or behind the camera plane (``Z_cam <= 0``, for
  which :meth:`Camera.project` returns NaN) is not carved by that view.

A voxel is kept if at most ``tolerance`` views carve it (``tolerance=0``: kept
in every view, the classic visual hull).

:func:`carve_reference` applies this test to every voxel and view in plain
vectorized numpy.  :func:`carve` decides the same test coarse to fine with
summed-area tables and gives exactly the same occupancy.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from ..camera import Camera
from ..grid import VoxelGrid
from ..masks import Silhouette
from ..nbcam import pack_camera
from . import _bbox_numba as nbk

__all__ = ["carve", "carve_reference", "ProgressiveCarver"]


# --------------------------------------------------------------- validation
def _check_grid(grid):
    if not isinstance(grid, VoxelGrid):
        raise TypeError(f"grid must be an organlab.grid.VoxelGrid, got {type(grid).__name__}")


def _check_view(mask, camera, index=None):
    where = "" if index is None else f" {index}"
    if not isinstance(camera, Camera):
        raise TypeError(f"camera{where} must be an organlab.camera.Camera, got {type(camera).__name__}")
    m = np.asarray(mask.mask if isinstance(mask, Silhouette) else mask)
    if m.ndim != 2:
        raise ValueError(f"mask{where} must be a 2-D (H, W) array, got shape {m.shape}")
    if m.dtype != bool:
        if not (np.issubdtype(m.dtype, np.integer) or np.issubdtype(m.dtype, np.floating)):
            raise ValueError(f"mask{where} must be a bool (or numeric, non-zero = silhouette) array, got {m.dtype}")
        m = m != 0
    w, h = camera.image_size
    if m.shape != (h, w):
        raise ValueError(
            f"mask{where} has shape (H, W) = {m.shape} but its camera's image_size (width, height) is {(w, h)}"
        )
    return m


def _check_views(masks, cameras):
    masks = list(masks) if not isinstance(masks, np.ndarray) or masks.ndim == 3 else [masks]
    cameras = [cameras] if isinstance(cameras, Camera) else list(cameras)
    if len(masks) != len(cameras):
        raise ValueError(f"got {len(masks)} masks but {len(cameras)} cameras: give one camera per mask")
    if len(masks) == 0:
        raise ValueError("no views: give at least one mask and its camera")
    return [_check_view(m, c, i) for i, (m, c) in enumerate(zip(masks, cameras))], cameras


def _check_tolerance(tolerance):
    if isinstance(tolerance, bool) or not isinstance(tolerance, (int, np.integer)) or not 0 <= tolerance < 65535:
        raise ValueError(
            f"tolerance must be an integer in [0, 65534] (views allowed to carve a kept voxel), got {tolerance!r}"
        )
    return int(tolerance)


# ----------------------------------------------------------------- helpers
def _corner_axes(grid):
    """Corner coordinates along x, y, z: three 1-D arrays of n + 1 values, mm.

    Every implementation takes its corners from here so that they project the
    very same floating-point points.
    """
    vs = grid.voxel_size
    return tuple(grid.origin[i] + (np.arange(grid.shape[i] + 1) - 0.5) * vs for i in range(3))


def _sat(mask):
    """Summed-area table ``S`` of a bool mask, shape ``(H + 1, W + 1)``.

    ``S[r, c]`` = number of silhouette pixels in rows ``< r`` and columns ``< c``.
    """
    h, w = mask.shape
    dtype = np.int32 if h * w < 2**31 else np.int64
    s = np.zeros((h + 1, w + 1), dtype=dtype)
    np.cumsum(np.cumsum(mask, axis=0, dtype=dtype), axis=1, dtype=dtype, out=s[1:, 1:])
    return s


def _project(camera, points):
    """``camera.project`` without warnings for points near the camera plane."""
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        return camera.project(points)


def _box_corners(a):
    """The 8 corner views ``a[i:, j:, k:]`` of an ``(a+1, b+1, c+1)`` corner array."""
    return [
        a[i : a.shape[0] - 1 + i, j : a.shape[1] - 1 + j, k : a.shape[2] - 1 + k]
        for i in (0, 1)
        for j in (0, 1)
        for k in (0, 1)
    ]


def _carved_from_box(umin, umax, vmin, vmax, sat, width, height, min_pixels):
    """The bounding-box test on boxes already known (any shape, NaN = behind).

    Returns ``carved``: the box lies in the image and covers fewer than
    ``min_pixels`` silhouette pixels.
    """
    with np.errstate(invalid="ignore", over="ignore"):
        c0 = np.ceil(umin - 0.5)
        c1 = np.floor(umax + 0.5)
        r0 = np.ceil(vmin - 0.5)
        r1 = np.floor(vmax + 0.5)
        # NaN (a corner on or behind the camera plane) compares False
        inside = (c0 >= 0) & (r0 >= 0) & (c1 <= width - 1) & (r1 <= height - 1)
    c0 = c0[inside].astype(np.intp)
    c1 = c1[inside].astype(np.intp) + 1
    r0 = r0[inside].astype(np.intp)
    r1 = r1[inside].astype(np.intp) + 1
    count = sat[r1, c1] - sat[r0, c1] - sat[r1, c0] + sat[r0, c0]
    carved = np.zeros(np.shape(umin), dtype=bool)
    carved[inside] = count < min_pixels
    return carved


def _carved_by_view(uv, sat, width, height, min_pixels=1):
    """Which voxels of a block one view carves, from projected corners.

    Parameters
    ----------
    uv : (a + 1, b + 1, c + 1, 2) float64, px
        Projected corners of an ``(a, b, c)`` block of voxels.
    sat : (H + 1, W + 1) int
        Summed-area table of the view's mask.

    Returns
    -------
    carved : (a, b, c) bool
    """
    cu = _box_corners(uv[..., 0])
    cv = _box_corners(uv[..., 1])
    # np.minimum / np.maximum propagate NaN: a corner behind the camera
    # makes the whole box NaN, which never carves.
    return _carved_from_box(
        np.minimum.reduce(cu), np.maximum.reduce(cu), np.minimum.reduce(cv), np.maximum.reduce(cv),
        sat, width, height, min_pixels,
    )


def _exact_carved(flat, grid, axes, sat, camera, min_pixels):
    """The reference test on a few voxels given by flat (C-order) indices."""
    ix, iy, iz = np.unravel_index(flat, grid.shape)
    ax, ay, az = axes
    pts = np.empty((flat.size, 8, 3))
    n = 0
    for i in (0, 1):
        for j in (0, 1):
            for k in (0, 1):
                pts[:, n, 0] = ax[ix + i]
                pts[:, n, 1] = ay[iy + j]
                pts[:, n, 2] = az[iz + k]
                n += 1
    uv = _project(camera, pts.reshape(-1, 3)).reshape(flat.size, 8, 2)
    u = uv[..., 0]
    v = uv[..., 1]
    return _carved_from_box(u.min(1), u.max(1), v.min(1), v.max(1), sat, camera.width, camera.height, min_pixels)


def _reference_counts(masks, cameras, grid, chunk_voxels, min_pixels=1):
    """Number of views carving each voxel, plain numpy, chunked along x.

    Returns
    -------
    counts : grid.shape uint16
    """
    nx, ny, nz = grid.shape
    ax, ay, az = _corner_axes(grid)
    slab = max(1, int(chunk_voxels) // (ny * nz))
    counts = np.zeros(grid.shape, dtype=np.uint16)
    sats = [_sat(m) for m in masks]
    for x0 in range(0, nx, slab):
        x1 = min(nx, x0 + slab)
        X, Y, Z = np.meshgrid(ax[x0 : x1 + 1], ay, az, indexing="ij")
        pts = np.stack([X.ravel(), Y.ravel(), Z.ravel()], axis=1)
        del X, Y, Z
        for cam, sat in zip(cameras, sats):
            uv = _project(cam, pts).reshape(x1 - x0 + 1, ny + 1, nz + 1, 2)
            counts[x0:x1] += _carved_by_view(uv, sat, cam.width, cam.height, min_pixels)
    return counts


def _check_min_pixels(min_pixels):
    if isinstance(min_pixels, bool) or not isinstance(min_pixels, (int, np.integer)) or min_pixels < 1:
        raise ValueError(f"min_pixels must be an integer >= 1, got {min_pixels!r}")
    return int(min_pixels)


def _view_order(n):
    """Views in van der Corput order (0, n/2, n/4, 3n/4, ...): for views
    sorted by angle the first few are far apart and carve most early."""
    def radical_inverse(i):
        f, r = 0.5, 0.0
        while i:
            r += f * (i & 1)
            i >>= 1
            f /= 2
        return r

    return sorted(range(n), key=radical_inverse)


class _Engine:
    """Per-voxel carve counts plus a pyramid of alive counts, updated view by view."""

    def __init__(self, grid, tolerance, min_pixels, levels=4):
        self._nbk = nbk
        self.grid = grid
        self.tol = tolerance
        self.min_pixels = min_pixels
        self.axes = _corner_axes(grid)
        shape = np.array(grid.shape, dtype=np.int64)
        L = int(max(1, min(levels, int(np.ceil(np.log2(shape.max()))))))
        self.L = L
        self.dims = np.array([-(-shape // (1 << l)) for l in range(L + 1)], dtype=np.int64)
        sizes = np.prod(self.dims, axis=1)
        sizes[0] = 0  # level 0 is the counts array itself
        self.off = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64)
        self.pyr = np.zeros(int(sizes.sum()), dtype=np.int64)
        self.counts = np.zeros(grid.shape, dtype=np.uint16)
        nbk.build_pyramid(self.counts, self.pyr, self.off, self.dims, L, self.tol)
        self.tops = np.indices(self.dims[L]).reshape(3, -1).T.astype(np.int64)
        self._deferred = None

    def apply(self, mask, camera):
        nbk = self._nbk
        L = self.L
        n_tops = self.tops.shape[0]
        h, w = mask.shape
        sat = nbk.sat_of(mask) if h * w < 2**31 else _sat(mask)
        cap = 1 << (3 * L)
        if self._deferred is None:
            self._deferred = np.empty(n_tops * cap, dtype=np.int64)
            self._ndef = np.zeros(n_tops, dtype=np.int64)
        ax, ay, az = self.axes
        nbk.carve_view(
            pack_camera(camera), sat, camera.width, camera.height, ax, ay, az, self.counts, self.pyr,
            self.off, self.dims, L, self.tops, self.tol, self.min_pixels, self._deferred, self._ndef,
        )
        ndef = self._ndef
        (which,) = np.nonzero(ndef)
        if which.size:
            flat = np.concatenate([self._deferred[t * cap : t * cap + ndef[t]] for t in which])
            carved = _exact_carved(flat, self.grid, self.axes, sat, camera, self.min_pixels)
            nbk.kill_many(self.counts, self.pyr, self.off, self.dims, L, flat[carved], self.tol)

    @property
    def occupancy(self):
        return self.counts <= self.tol


# ------------------------------------------------------------------ public
def carve_reference(masks: Sequence[Silhouette | np.ndarray], cameras: Sequence[Camera], grid: VoxelGrid, *,
                    chunk_voxels: int = 2_000_000, min_pixels: int = 1) -> np.ndarray:
    """Visual hull by the thesis's bounding-box test, plain vectorized numpy.

    Every voxel is tested in every view (see the module docstring for the
    exact test): its 8 corners are projected with :meth:`Camera.project`, and
    the view carves it if no silhouette pixel lies in the pixel-rounded
    bounding box of the 8 projections.  Pixels outside the image and corners
    on or behind the camera plane never carve.  The yardstick for
    :func:`carve`, which gives the same occupancy much faster.

    Parameters
    ----------
    masks : sequence of (H, W) bool arrays, or of Silhouette
        Silhouettes, ``True`` = specimen; one per view.  Numeric arrays are
        accepted (non-zero = specimen); a :class:`~organlab.silhouette.Silhouette`
        gives its ``mask``.
    cameras : sequence of Camera
        The calibrated camera of each view; ``image_size == (W, H)``.
    grid : VoxelGrid
        The voxel space, mm, world frame.
    chunk_voxels : int
        Voxels processed at a time (bounds the memory: about 300 bytes per
        voxel of a chunk; the default needs about 0.6 GB).
    min_pixels : int
        A view keeps a voxel if at least this many silhouette pixels lie in
        its box (default 1: the thesis's test, any silhouette pixel).

    Returns
    -------
    occupancy : grid.shape bool
        ``True`` for voxels no view carves (axes x, y, z).

    Raises
    ------
    ValueError
        If the numbers of masks and cameras differ, there is no view, a mask
        is not 2-D or its shape is not the camera's ``(height, width)``.
    TypeError
        If a camera is not a :class:`Camera` or grid not a :class:`VoxelGrid`.
    """
    _check_grid(grid)
    masks, cameras = _check_views(masks, cameras)
    min_pixels = _check_min_pixels(min_pixels)
    if isinstance(chunk_voxels, bool) or not isinstance(chunk_voxels, (int, np.integer)) or chunk_voxels < 1:
        raise ValueError(f"chunk_voxels must be an integer >= 1, got {chunk_voxels!r}")
    return _reference_counts(masks, cameras, grid, chunk_voxels, min_pixels) == 0


def carve(masks: Sequence[Silhouette | np.ndarray], cameras: Sequence[Camera], grid: VoxelGrid, *, tolerance: int = 0,
          min_pixels: int = 1) -> np.ndarray:
    """Visual hull: the voxels that at most ``tolerance`` views carve.

    The same bounding-box test as :func:`carve_reference` (module docstring),
    with the same result voxel for voxel, decided coarse to fine: blocks of
    up to 16^3 voxels whose (conservatively bounded) projection holds no
    silhouette pixel are carved at once, blocks wholly inside the silhouette
    kept at once, and only blocks on the silhouette's edge refined, each test
    O(1) with a summed-area table of the mask (numba, parallel over blocks).

    Parameters
    ----------
    masks : sequence of (H, W) bool arrays, or of Silhouette
        Silhouettes, ``True`` = specimen; one per view.  Numeric arrays are
        accepted (non-zero = specimen); a :class:`~organlab.silhouette.Silhouette`
        gives its ``mask``.
    cameras : sequence of Camera
        The calibrated camera of each view; ``image_size == (W, H)``.
    grid : VoxelGrid
        The voxel space, mm, world frame.
    tolerance : int
        A voxel is kept if at most this many views carve it; 0 (default) is
        the classic visual hull.  k > 0 survives k bad silhouettes (a hole
        punched in a mask, a missed part) at the price of a looser hull where
        fewer than k + 1 views see past the specimen.
    min_pixels : int
        A view keeps a voxel only if at least this many silhouette pixels lie
        in its box (default 1: the thesis's test).  Noise: the box test is
        insensitive to pepper (false background pixels) inside the silhouette,
        since one silhouette pixel in the box keeps the voxel; isolated salt
        (false silhouette pixels) outside keeps the voxels behind it, which
        other views then carve, or ``min_pixels=2`` ignores.  Cleaning the
        silhouettes (``organlab.silhouette``) is the proper cure for both.

    Returns
    -------
    occupancy : grid.shape bool
        ``True`` for kept voxels (axes x, y, z).

    Raises
    ------
    ValueError
        If the numbers of masks and cameras differ, there is no view, a mask
        is not 2-D or its shape is not the camera's ``(height, width)``, or
        ``tolerance`` / ``min_pixels`` is not a valid integer.
    TypeError
        If a camera is not a :class:`Camera` or grid not a :class:`VoxelGrid`.

    Examples
    --------
    >>> import tempfile
    >>> import organlab as ol
    >>> from organlab.synthetic import with_true_cameras
    >>> s = ol.load_session(with_true_cameras("sample_sessions/aaa_phantom", tempfile.mkdtemp() + "/aaa", step=6))
    >>> cal, _ = ol.calibration_for(s)
    >>> grid = ol.VoxelGrid.from_session(s, voxel_size=4.0)
    >>> occupancy = ol.carve([sil.mask for sil in ol.silhouettes(s)], cal.cameras(s), grid)
    >>> occupancy.shape, occupancy.dtype, int(occupancy.sum())  # every voxel any part of which the views keep
    ((35, 35, 50), dtype('bool'), 4011)
    """
    _check_grid(grid)
    masks, cameras = _check_views(masks, cameras)
    tolerance = _check_tolerance(tolerance)
    min_pixels = _check_min_pixels(min_pixels)
    engine = _Engine(grid, tolerance, min_pixels)
    for i in _view_order(len(masks)):
        engine.apply(masks[i], cameras[i])
    return engine.occupancy


class ProgressiveCarver:
    """Carve view by view, keeping the current visual hull.

    Each :meth:`add_view` tests only the voxels still kept and removes what
    the new view carves; with ``tolerance`` it keeps per-voxel counts of
    carving views.  After adding all views, :attr:`occupancy` equals
    ``carve(masks, cameras, grid, tolerance=tolerance, min_pixels=min_pixels)``
    whatever the order of the views.

    Parameters
    ----------
    grid : VoxelGrid
        The voxel space, mm, world frame.
    tolerance : int
        As in :func:`carve`: a voxel stays while at most ``tolerance`` of the
        views added so far carve it.
    min_pixels : int
        As in :func:`carve`.
    """

    def __init__(self, grid: VoxelGrid, *, tolerance: int = 0, min_pixels: int = 1) -> None:
        _check_grid(grid)
        self.grid = grid
        self.tolerance = _check_tolerance(tolerance)
        self.min_pixels = _check_min_pixels(min_pixels)
        self._engine = _Engine(grid, self.tolerance, self.min_pixels)
        self._n_views = 0

    @property
    def n_views(self) -> int:
        """Number of views added so far."""
        return self._n_views

    @property
    def occupancy(self) -> np.ndarray:
        """Current hull, ``grid.shape`` bool (a new array)."""
        return self._engine.occupancy

    @property
    def carve_counts(self) -> np.ndarray:
        """Number of views that carved each voxel, ``grid.shape`` uint16.

        Counting stops once a voxel is removed (at ``tolerance + 1``).
        """
        return self._engine.counts.copy()

    def add_view(self, mask: Silhouette | np.ndarray, camera: Camera) -> None:
        """Carve with one more view and return the new occupancy.

        Parameters
        ----------
        mask : (H, W) bool
            Silhouette, ``True`` = specimen.
        camera : Camera
            The view's camera, ``image_size == (W, H)``.

        Returns
        -------
        occupancy : grid.shape bool
        """
        m = _check_view(mask, camera)
        self._engine.apply(m, camera)
        self._n_views += 1
        return self.occupancy
