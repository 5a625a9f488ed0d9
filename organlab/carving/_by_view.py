"""Carve by view: which view removed each carved voxel.

The visual hull tells what is kept; when a silhouette is wrong (a bad mask,
a mislabelled angle) the question is *which view cut where*.
:func:`carving_views` answers it with the thesis's bounding-box test
(:func:`organlab.carving.carve`): the views are applied in their given order
through :class:`~organlab.carving.ProgressiveCarver`, and each voxel records
the first view that carves it.  The voxels no view carves (``-1``) are exactly
``carve(masks, cameras, grid)``.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from ..camera import Camera
from ..grid import VoxelGrid
from ..masks import Silhouette
from ._bbox import ProgressiveCarver, _check_grid, _check_views

__all__ = ["carving_views"]


def carving_views(masks: Sequence[Silhouette | np.ndarray], cameras: Sequence[Camera], grid: VoxelGrid, *,
                  min_pixels: int = 1) -> np.ndarray:
    """The first view (in the given order) that carves each voxel.

    Parameters
    ----------
    masks : sequence of (H, W) bool arrays
        Silhouettes, ``True`` = specimen; one per view.
    cameras : sequence of Camera
        The calibrated camera of each view; ``image_size == (W, H)``.
    grid : VoxelGrid
        The voxel space, mm, world frame.
    min_pixels : int
        As in :func:`organlab.carving.carve`.

    Returns
    -------
    views : (nx, ny, nz) int16
        Index into ``masks`` of the first view whose bounding-box test carves
        the voxel; ``-1`` for kept voxels (``views == -1`` equals
        ``carve(masks, cameras, grid, min_pixels=min_pixels)``).

    Raises
    ------
    ValueError
        Mismatched masks and cameras, no view, more than 32767 views, or a
        mask whose shape is not its camera's ``(height, width)``.
    TypeError
        A camera that is not a Camera or a grid that is not a VoxelGrid.
    """
    _check_grid(grid)
    masks, cameras = _check_views(masks, cameras)
    if len(masks) > np.iinfo(np.int16).max:
        raise ValueError(f"at most 32767 views fit an int16 view index, got {len(masks)}")
    carver = ProgressiveCarver(grid, tolerance=0, min_pixels=min_pixels)
    views = np.full(grid.shape, -1, dtype=np.int16)
    kept = np.ones(grid.shape, dtype=bool)
    for i, (mask, camera) in enumerate(zip(masks, cameras)):
        now = carver.add_view(mask, camera)
        views[kept & ~now] = i
        kept = now
    return views
