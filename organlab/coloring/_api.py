"""Public entry points of :mod:`organlab.coloring`."""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from typing import Literal

import numpy as np

from ..camera import Camera
from ..grid import VoxelGrid
from ._auto import auto_support, auto_threshold, exposure_gains, image_noise, normalise
from ._auto import guard as _guard
from ._common import (
    DEFAULT_SUPPORT,
    DEFAULT_THRESHOLD,
    ColoringResult,
    _check_inputs,
    _check_occupancy,
    _completeness_rule,
)
from ._methods import _owned, _space_carving, _surface, _voxel_coloring
from ._statistics import _rgb, _Stats

_MEASURES = ("pooled", "between", "trimmed", "normalized", "shading")


def color_voxels(
    images: Sequence[np.ndarray],
    cameras: Sequence[Camera],
    occupancy: np.ndarray | None,
    grid: VoxelGrid,
    *,
    threshold: float | Literal["auto"] | None = DEFAULT_THRESHOLD,
    method: str = "voxel_coloring",
    start: str = "hull",
    completeness: float | None = None,
    masks: Sequence[np.ndarray] | None = None,
    measure: str = "between",
    support: int | Literal["auto"] | None = DEFAULT_SUPPORT,
    progress: Callable[[int, int], object] | None = None,
    exposure: bool = False,
    guard: bool = False,
) -> ColoringResult:
    """Carve the voxels whose colours disagree between the views.

    See the module docstring for the algorithms, the visibility constraint
    and why voxels no view sees are kept.

    Parameters
    ----------
    images : sequence of (H, W, 3) or (H, W) uint8
        The views, RGB (or grey), one per camera.
    cameras : sequence of Camera
        The calibrated camera of each view, ``image_size == (W, H)``.
    occupancy : (nx, ny, nz) bool or None
        The visual hull on ``grid`` (e.g. from :func:`organlab.carving.carve`).
        Only needed with ``start="hull"``.
    grid : VoxelGrid
    threshold : float or 'auto'
        Photo-consistency threshold: largest standard deviation (grey levels,
        ``sqrt`` of the mean per-channel variance) of a kept voxel's visible
        pixels.  ``'auto'`` (or None): measured on the candidates' surface
        voxels and the pixel noise (:mod:`organlab.coloring._auto`).
    method : {'voxel_coloring', 'space_carving'}
        Seitz & Dyer's single layered pass (needs the ordinal visibility
        constraint), or multi-pass carving with exact visibility (any cameras).
    start : {'hull', 'roi'}
        Candidates: the hull's voxels, or every voxel of the grid.
    completeness : None, int >= 1 or float in (0, 1)
        Voxels with fewer visible pixels (a count, or a fraction of their
        in-image, non-background footprint pixels over all views) are kept
        untested.
    masks : sequence of (H, W) bool, optional
        Silhouettes (True = specimen).  Background pixels are never used for
        colours; a voxel seen mostly through background in a view is carved.
    measure : {'pooled', 'between', 'trimmed', 'normalized', 'shading'}
        ``'pooled'``: the standard deviation of all visible pixels pooled
        over the views (Seitz & Dyer); ``'between'``: of the per-view mean
        colours (weighted by pixel counts), blind to the texture inside one
        footprint; ``'trimmed'``: ``'between'`` without the most deviant view
        (robust to a highlight seen in one view); ``'normalized'``: ``'trimmed'``
        of the per-view mean colours scaled to a common brightness (blind to
        shading that changes with the view and to exposure; RGB only);
        ``'shading'``: the spread of the view colours about a Lambertian
        shading curve of the table angle (turntable, lamp fixed to the
        camera), robust to one deviant view.
    support : int or 'auto'
        Spatial support of a carve: an inconsistent voxel is carved only if
        at least ``support`` inconsistent voxels (itself included) lie in its
        3 x 3 neighbourhood within its layer (3 x 3 x 3 for space carving).
        ``1`` is the plain per-voxel test.  Concavities are regions; a lone
        inconsistent voxel on a true surface (a texture edge, a crease) is
        kept, which stops it from opening a hole that the sweep would then
        dig deeper.  ``'auto'``: ``DEFAULT_SUPPORT`` at and above the
        automatic threshold, one more voxel per robust deviation of the
        candidates' surface measure the threshold lies below it, at most 9
        (:mod:`organlab.coloring._auto`): a low threshold is exceeded by the
        true surface's residuals at scattered voxels, a concavity's lid as a
        region.
    progress : callable(done, total), optional
        Called after every layer (or pass).
    exposure : bool
        Divide every view by its exposure gain, measured on the candidates'
        surface voxels, before the test.
    guard : bool
        Silhouette guard (needs ``masks``): carved voxels are put back where
        the carved model would leave a silhouette pixel unexplained that the
        candidates explained, so the model still projects onto every
        silhouette.

    Returns
    -------
    ColoringResult

    Raises
    ------
    VisibilityConstraintError
        ``method="voxel_coloring"`` with cameras that allow no layered sweep.
    ValueError
        Mismatched numbers of images, cameras and masks, an image that is not
        ``(H, W)`` / ``(H, W, 3)`` uint8 or not its camera's size, an
        occupancy that is not bool of ``grid.shape``, or an invalid option.
    TypeError
        A camera that is not a :class:`~organlab.camera.Camera` or a grid that
        is not a :class:`~organlab.grid.VoxelGrid`.

    Examples
    --------
    >>> import tempfile
    >>> import organlab as ol
    >>> from organlab.synthetic import with_true_cameras
    >>> s = ol.load_session(with_true_cameras("sample_sessions/aaa_phantom", tempfile.mkdtemp() + "/aaa", step=6))
    >>> cal, _ = ol.calibration_for(s)
    >>> cameras, grid, sils = cal.cameras(s), ol.VoxelGrid.from_session(s, voxel_size=4.0), ol.silhouettes(s)
    >>> hull = ol.carve([sil.mask for sil in sils], cameras, grid)
    >>> r = ol.color_voxels([s.read(v.image) for v in s.views], cameras, hull, grid, masks=[sil.mask for sil in sils])
    >>> int(hull.sum()), int(r.occupancy.sum()), r.n_carved  # colouring only removes voxels
    (4011, ..., ...)
    >>> bool(r.occupancy.sum() <= hull.sum()) and not (r.occupancy & ~hull).any()
    True
    """
    t0 = time.perf_counter()
    stack, cameras, cams, bg = _check_inputs(images, cameras, grid, masks)
    if method not in ("voxel_coloring", "space_carving"):
        raise ValueError(f"method must be 'voxel_coloring' or 'space_carving', got {method!r}")
    if start == "hull":
        if occupancy is None:
            raise ValueError("start='hull' needs the visual hull as occupancy (or use start='roi')")
        candidates = _check_occupancy(occupancy, grid)
    elif start == "roi":
        candidates = np.ones(grid.shape, dtype=bool)
    else:
        raise ValueError(f"start must be 'hull' or 'roi', got {start!r}")
    automatic = threshold is None or (isinstance(threshold, str) and threshold == "auto")
    if not automatic and (
        isinstance(threshold, bool) or not isinstance(threshold, (int, float, np.integer, np.floating)) or not threshold >= 0
    ):
        raise ValueError(f"threshold must be a number >= 0 (grey levels) or 'auto', got {threshold!r}")
    min_pix, min_frac = _completeness_rule(completeness)
    if measure not in _MEASURES:
        raise ValueError(f"measure must be one of {_MEASURES}, got {measure!r}")
    if guard and masks is None:
        raise ValueError("guard=True needs the silhouettes (masks=)")
    auto_sup = isinstance(support, str) and support == "auto"
    if not auto_sup and (isinstance(support, bool) or not isinstance(support, (int, np.integer)) or not 1 <= support <= 27):
        raise ValueError(f"support must be an integer in 1..27 (voxels) or 'auto', got {support!r}")
    progress = progress or (lambda done, total: None)

    _Stats.azimuth = np.array([np.arctan2(c.center[1], c.center[0]) for c in cameras]) if measure == "shading" else None
    _Stats.measure = measure
    try:
        stack, threshold, noise, gains, support = _prepare(
            stack, cams, bg, candidates, grid, threshold, automatic, exposure, measure, min_pix, support
        )
        run = _voxel_coloring if method == "voxel_coloring" else _space_carving
        occ, colors, colored, counts, sweep, iterations = run(
            stack, cams, cameras, bg, candidates, grid, threshold, measure, min_pix, min_frac, support, progress
        )
    finally:
        _Stats.azimuth = _Stats.measure = None
    n_restored = 0
    if guard:
        occ, n_restored = _guard(occ, candidates, cameras, grid, masks)
    n_cand = int(np.count_nonzero(candidates))
    return ColoringResult(
        occupancy=occ,
        colors=colors,
        colored=colored,
        n_candidates=n_cand,
        n_carved=n_cand - int(np.count_nonzero(occ)),
        n_carved_background=counts["carved_bg"],
        n_visible=int(np.count_nonzero(colored)),
        n_hidden=counts["hidden"],
        n_untested=counts["untested"],
        seconds=time.perf_counter() - t0,
        method=method,
        sweep=sweep,
        iterations=iterations,
        threshold=threshold,
        automatic=automatic,
        n_restored=n_restored,
        noise=noise,
        gains=gains,
        support=support,
    )


def _prepare(stack, cams, bg, candidates, grid, threshold, automatic, exposure, measure, min_pix, support):
    """Exposure normalisation, the automatic threshold and support: (stack, threshold, noise, gains, support)."""
    noise = gains = None
    auto_sup = isinstance(support, str)
    if not (automatic or exposure or auto_sup) or not candidates.any():
        return stack, (float(threshold) if not automatic else 1.0), noise, gains, (DEFAULT_SUPPORT if auto_sup else support)
    ijk = np.argwhere(_surface(candidates)).astype(np.int64)
    st = _owned(stack, cams, bg, ijk, grid)
    if exposure:
        g = exposure_gains(st)
        gains = tuple(float(x) for x in g)
        stack = normalise(stack, g)
        if automatic or auto_sup:
            st = _owned(stack, cams, bg, ijk, grid)
    if automatic or auto_sup:
        noise = image_noise(stack)
        t_auto, details = auto_threshold(st, measure, noise, min_pix)
        threshold = t_auto if automatic else threshold
        if auto_sup:
            support = auto_support(threshold, details, DEFAULT_SUPPORT)
        if not automatic:
            noise = None
    return stack, float(threshold), noise, gains, support



def voxel_colors(images: Sequence[np.ndarray], cameras: Sequence[Camera], occupancy: np.ndarray, grid: VoxelGrid, *,
                 masks: Sequence[np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Colour the surface voxels of an occupancy, without carving.

    Every view renders an item buffer of the surface voxels (each footprint
    pixel goes to the surface voxel nearest the camera); a voxel's colour is
    the mean of the pixels it owns, over all views.  For mesh vertex colours.

    Parameters
    ----------
    images : sequence of (H, W, 3) or (H, W) uint8
    cameras : sequence of Camera
    occupancy : (nx, ny, nz) bool
    grid : VoxelGrid
    masks : sequence of (H, W) bool, optional
        Background pixels (False) are not used.

    Returns
    -------
    colors : (nx, ny, nz, 3) uint8
        RGB; zeros where a voxel is empty, interior or seen by no view.
    """
    stack, cameras, cams, bg = _check_inputs(images, cameras, grid, masks)
    occ = _check_occupancy(occupancy, grid)
    colors = np.zeros(grid.shape + (3,), np.uint8)
    ijk = np.argwhere(_surface(occ)).astype(np.int64)
    if len(ijk) == 0:
        return colors
    st = _owned(stack, cams, bg, ijk, grid)
    seen = st.n_vis > 0
    ki = ijk[seen]
    colors[ki[:, 0], ki[:, 1], ki[:, 2]] = _rgb(st.mean()[seen], stack.shape[3])
    return colors
