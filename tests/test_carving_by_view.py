"""Carve by view: the first view that carves each voxel, checked against the
reference bounding-box test applied one view at a time."""

import numpy as np
import pytest
from test_carving import _scene, ring, sphere_mask

from organlab.carving import carve_reference, carving_views
from organlab.grid import VoxelGrid


@pytest.mark.parametrize("name", ["sphere-distorted", "random-blobs", "border-and-near"])
def test_first_carving_view_matches_single_view_reference(name):
    grid, cams, masks = _scene(name, np.random.default_rng(5))
    views = carving_views(masks, cams, grid)
    assert views.dtype == np.int16 and views.shape == grid.shape
    # kept voxels are exactly the reference hull
    np.testing.assert_array_equal(views == -1, carve_reference(masks, cams, grid))
    # each carved voxel: carved by its view alone, by no earlier view
    carved_by = np.stack([~carve_reference([m], [c], grid) for m, c in zip(masks, cams)])
    first = np.where(carved_by.any(axis=0), carved_by.argmax(axis=0), -1)
    np.testing.assert_array_equal(views, first)
    assert len(np.unique(views)) > 2  # more than one view carves something


def test_order_matters_and_inputs_untouched():
    grid = VoxelGrid.from_roi((-22, -22, -22), (22, 22, 22), 2.0)
    cams = ring(4, 250.0, 60.0, f=400.0)
    masks = [sphere_mask(c, (0.0, 0.0, 0.0), 15.0) for c in cams]
    before = [m.copy() for m in masks]
    fwd = carving_views(masks, cams, grid)
    rev = carving_views(masks[::-1], cams[::-1], grid)
    np.testing.assert_array_equal(fwd == -1, rev == -1)
    # view 0 claims everything it carves when first; reversed, it comes last
    assert (fwd == 0).sum() > (rev == 3).sum()
    for m, b in zip(masks, before):
        np.testing.assert_array_equal(m, b)


def test_bad_inputs():
    grid = VoxelGrid((0.0, 0.0, 0.0), 1.0, (2, 2, 2))
    cams = ring(2, 100.0, 0.0)
    with pytest.raises(ValueError, match="masks but"):
        carving_views([np.ones((72, 96), bool)], cams, grid)
    with pytest.raises(TypeError, match="VoxelGrid"):
        carving_views([np.ones((72, 96), bool)] * 2, cams, "grid")
