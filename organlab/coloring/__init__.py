"""Voxel colouring and space carving: the concavities no silhouette shows.

A visual hull cannot remove a concavity that lies inside every silhouette;
colour can: a hull voxel filling a concavity projects, in the views that see
it, onto different surface points, so its pixels disagree.  This package
removes the voxels whose pixels disagree, by Seitz & Dyer's layered voxel
colouring or by space carving with exact visibility; :func:`photo_carve`
(``method='photo'``) decides by patch NCC between neighbouring views instead,
which holds on real texture.  The theory (ordinal
visibility constraint, footprints, consistency measures, why a solid is
returned) is in ``docs/coloring.md``.

Private modules: ``_kernels`` (numba footprints and item buffers),
``_visibility`` (sweep order, threads), ``_statistics`` (consistency),
``_methods`` (the two methods), ``_api`` (the public functions), ``_photo``
and ``_photo_kernels`` (the photo method), ``_where`` (where it carved).
"""

import numpy as np

from ..grid import VoxelGrid
from ._api import color_voxels, voxel_colors
from ._common import DEFAULT_SUPPORT, DEFAULT_THRESHOLD, ColoringResult, VisibilityConstraintError
from ._photo import DEFAULT_PHOTO_THRESHOLD, photo_carve
from ._visibility import check_ordinal_visibility
from ._where import carved_depth_picture, carved_where

#: How the pipeline colours: a measure blind to view-dependent shading and
#: highlights, exposure normalised per view, the silhouette guard on, and the
#: support grows as the threshold goes below the automatic one (``'auto'``).
PIPELINE_OPTIONS = {"measure": "shading", "exposure": True, "guard": True, "support": "auto"}


def report_entry(result: ColoringResult, candidates: np.ndarray, grid: VoxelGrid) -> dict:
    """The ``coloring`` entry of report.json: threshold, automatic, removed volume (mm^3), guard, noise.

    For ``method='photo'`` also ``regions``, ``depth_map`` (:func:`carved_where`) and ``passes``.

    Parameters
    ----------
    result : ColoringResult
    candidates : (nx, ny, nz) bool
        The occupancy colouring started from (the hull).
    grid : VoxelGrid
    """
    entry = {
        "threshold": result.threshold,
        "automatic": result.automatic,
        "removed_volume_mm3": grid.volume_of(candidates) - grid.volume_of(result.occupancy),
        "method": result.method,
        "restored_by_guard": result.n_restored,
        "noise": result.noise,
        "exposure_gains": None if result.gains is None else [round(g, 4) for g in result.gains],
        "support": result.support,
    }
    if result.method == "photo":  # where and how deep it carved (the picture's data)
        entry.update(carved_where(candidates, result.occupancy, grid), passes=result.iterations)
    return entry

__all__ = [
    "VisibilityConstraintError",
    "ColoringResult",
    "color_voxels",
    "voxel_colors",
    "check_ordinal_visibility",
    "DEFAULT_THRESHOLD",
    "DEFAULT_SUPPORT",
    "PIPELINE_OPTIONS",
    "report_entry",
    "photo_carve",
    "DEFAULT_PHOTO_THRESHOLD",
    "carved_where",
    "carved_depth_picture",
]
