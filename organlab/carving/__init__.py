"""Voxel carving: the visual hull of silhouettes seen by calibrated cameras.

Public functions are re-exported from private modules:

* :func:`carve_reference` -- the thesis's test, written plainly in numpy (the
  yardstick every faster method is tested against, voxel for voxel);
* :func:`carve` -- the same bounding-box test decided coarse-to-fine with
  summed-area tables (fast);
* :class:`ProgressiveCarver` -- add views one at a time, keep the current hull;
* :func:`hull_field` -- a scalar field whose 0.5 level lies on the visual
  hull's surface, for sub-voxel surfaces; computed in a narrow band around
  the surface, and kept there with ``sparse=True`` (:class:`BandField`, with
  ``dense()``, ``occupancy()`` and ``mesh()``);
* :func:`carving_views` -- the first view that carves each voxel (carve by view);
* :func:`warm_kernels` -- load the hull field's kernels ahead of its first call.
"""

from ..bandfield import BandField
from ._bbox import ProgressiveCarver, carve, carve_reference
from ._by_view import carving_views
from ._field import hull_field, warm_kernels

__all__ = ["carve", "carve_reference", "ProgressiveCarver", "hull_field", "BandField", "carving_views", "warm_kernels"]
