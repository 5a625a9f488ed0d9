"""Visibility of :mod:`organlab.coloring`: the ordinal visibility constraint, occlusion reach, threads over views."""

from __future__ import annotations

from collections.abc import Sequence

import numba as nb
import numpy as np

from ..camera import Camera
from ._common import VisibilityConstraintError


def _n_threads():
    try:
        return max(1, int(nb.get_num_threads()))
    except Exception:  # pragma: no cover
        return 1


def _over_views(kernel, V, *args):
    """Run ``kernel(v0, v1, *args)`` on slices of the V views, one per thread.

    The kernels release the GIL; threads that wait do so passively, which
    keeps a shared, oversubscribed machine responsive (numba's OpenMP
    workers spin while they wait and slow every short parallel region).
    """
    n = min(_n_threads(), V)
    if n <= 1:
        kernel(0, V, *args)
        return
    from concurrent.futures import ThreadPoolExecutor

    global _POOL
    if _POOL is None or _POOL._max_workers < n:
        _POOL = ThreadPoolExecutor(max_workers=n, thread_name_prefix="organlab-coloring")
    edges = np.linspace(0, V, n + 1).astype(int)
    futures = [_POOL.submit(kernel, int(a), int(b), *args) for a, b in zip(edges[:-1], edges[1:]) if b > a]
    for f in futures:
        f.result()


_POOL = None



def _candidate_bounds(candidates, grid):
    idx = [np.flatnonzero(candidates.any(axis=tuple(a for a in range(3) if a != k))) for k in range(3)]
    lo_i = np.array([i[0] for i in idx])
    hi_i = np.array([i[-1] for i in idx])
    o = np.asarray(grid.origin)
    h = grid.voxel_size
    return o + (lo_i - 0.5) * h, o + (hi_i + 0.5) * h


def check_ordinal_visibility(cameras: Sequence[Camera], bounds_min: np.ndarray, bounds_max: np.ndarray) -> tuple[int, bool]:
    """Find a layered sweep that meets the ordinal visibility constraint.

    The constraint holds for sweep direction ``d`` if every camera centre lies
    strictly beyond the box along ``d``: ``d . C > max(d . X)`` over the box,
    for every camera.  Then a point can only be occluded by points with a
    larger ``d . X``, and planes ``d . X = const`` swept from the cameras'
    side (decreasing ``d . X``) visit every occluder first.  The six axis
    directions are tried, ``+z`` (cameras above, sweep top down) first.

    Parameters
    ----------
    cameras : sequence of Camera
    bounds_min, bounds_max : (3,) float, mm, world frame
        The box holding every voxel that may be occupied.

    Returns
    -------
    axis : int
        0, 1 or 2 (x, y, z): the layers are slabs normal to this axis.
    descending : bool
        True: layers are visited from the largest coordinate down.

    Raises
    ------
    VisibilityConstraintError
        When no axis direction has every camera beyond the box.
    """
    cameras = [cameras] if isinstance(cameras, Camera) else list(cameras)
    centres = np.array([c.center for c in cameras], dtype=np.float64).reshape(-1, 3)
    lo = np.asarray(bounds_min, dtype=np.float64)
    hi = np.asarray(bounds_max, dtype=np.float64)
    for axis, descending in ((2, True), (2, False), (0, True), (0, False), (1, True), (1, False)):
        if descending and np.all(centres[:, axis] > hi[axis]):
            return axis, True
        if not descending and np.all(centres[:, axis] < lo[axis]):
            return axis, False
    worst = int(np.argmin(centres[:, 2]))
    raise VisibilityConstraintError(
        f"the cameras break the ordinal visibility constraint of layered voxel colouring: camera {worst}'s "
        f"centre is at z = {centres[worst, 2]:.1f} mm, not above the top of the volume (z = {hi[2]:.1f} mm), "
        "and no other axis has every camera on one side of the volume; "
        "use method='space_carving' (exact visibility, any camera layout)"
    )



def _occlusion_reach(cameras, lo, hi, axis, descending):
    """How far (voxels, in-layer chessboard distance) a ray crossing one layer travels sideways.

    A pixel ray through a voxel of layer k reaches layer k - 1 (toward the
    cameras) within ``0.5 + 1 / tan(elevation)`` voxels of it, the elevation
    being the ray's angle to the layer planes; the smallest elevation of a
    ray from any camera to the candidates' box bounds it.
    """
    centres = np.array([c.center for c in cameras], dtype=np.float64)
    other = [d for d in range(3) if d != axis]
    rise = centres[:, axis] - hi[axis] if descending else lo[axis] - centres[:, axis]
    corners = np.array([[x, y] for x in (lo[other[0]], hi[other[0]]) for y in (lo[other[1]], hi[other[1]])])
    run = np.max(np.linalg.norm(centres[:, None, other] - corners[None], axis=2), axis=1)
    tan_min = float(np.min(rise / np.maximum(run, 1e-9)))
    if not tan_min > 1e-6:
        return None
    return int(np.ceil(0.5 + 1.0 / tan_min))


def _all_within(occ2d, reach):
    """True where every cell within chessboard distance ``reach`` is occupied (False beyond the edges)."""
    if reach is None:
        return np.zeros(occ2d.shape, bool)
    from scipy import ndimage

    return ndimage.minimum_filter(occ2d.astype(np.uint8), size=2 * reach + 1, mode="constant", cval=0).astype(bool)

