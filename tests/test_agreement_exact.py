"""The agreement's OpenCV distance and erosion give scipy's values exactly (organlab.agreement)."""

import numpy as np
import pytest
from scipy import ndimage

from organlab.agreement import _distance_to_background, _erode


@pytest.mark.parametrize("seed", range(6))
def test_distance_and_erosion_equal_scipy(seed):
    """On blobs and noise that touch the image's edges (where scipy counts outside as not background
    for the distance and as background for the erosion), small and at the sample's image size."""
    rng = np.random.default_rng(seed)
    shape = (480, 640) if seed < 2 else tuple(rng.integers(3, 120, 2))
    s = ndimage.binary_opening(rng.random(shape) < rng.uniform(0.6, 0.97), iterations=int(rng.integers(0, 3)))
    if seed == 0:
        s[:] = True
        s[0, 0] = False  # a single background pixel: the largest distances the image can hold
    where = rng.random(shape) < 0.5
    np.testing.assert_array_equal(_distance_to_background(s, where), ndimage.distance_transform_edt(s)[where])
    np.testing.assert_array_equal(_erode(s), ndimage.binary_erosion(s))


def test_distance_falls_back_to_scipy_where_float32_could_round():
    """A box whose squared diagonal reaches 2^22 px^2 (float32 distances may round a squared distance)
    and a box with no background take scipy's transform: same values."""
    s = np.ones((1500, 1500), bool)
    s[0, :3] = False
    where = np.zeros_like(s)
    where[-1, -5:] = True
    np.testing.assert_array_equal(_distance_to_background(s, where), ndimage.distance_transform_edt(s)[where])
    full = np.ones((5, 7), bool)
    np.testing.assert_array_equal(_distance_to_background(full, full), ndimage.distance_transform_edt(full)[full])


def test_hull_masks_made_ahead_give_the_same_figures():
    """view_agreement with the carved surface's masks made ahead (organlab.agreement.hull_masks, as the engine
    makes them beside the finishing) gives every figure of the one that makes them itself; masks of another
    count or shape are refused.  A sphere seen by 6 cameras, its hull carved at 4 mm (the raw IoU differs from
    the model's, so a wrong mask would show)."""
    from organlab.agreement import hull_masks, view_agreement
    from organlab.carving import hull_field
    from organlab.grid import VoxelGrid
    from organlab.surface import mesh_from_field
    from organlab.synthetic import Sphere, default_camera, render_masks

    cams = [default_camera((160, 120)).at_table_angle(a) for a in range(0, 360, 60)]
    sils = [c >= 0.5 for c in render_masks(Sphere(center=(0, 0, 40), radius=20), cams)]
    grid = VoxelGrid.from_roi((-40, -40, 0), (40, 40, 80), 4.0)
    raw = mesh_from_field(hull_field(sils, cams, grid, sparse=True), grid)
    coarse = VoxelGrid.from_roi((-40, -40, 0), (40, 40, 80), 8.0)
    model = mesh_from_field(hull_field(sils, cams, coarse, sparse=True), coarse)
    masks = hull_masks(raw, cams, sils)
    assert len(masks) == 6 and all(m.shape == (120, 160) and m.dtype == bool and m.any() for m in masks)
    ahead = view_agreement(model, cams, sils, voxel_size=4.0, hull_mesh=raw, hull_masks=masks)
    itself = view_agreement(model, cams, sils, voxel_size=4.0, hull_mesh=raw)
    assert ahead.views == itself.views and ahead.worst == itself.worst and ahead.warnings == itself.warnings
    assert any(v["raw_iou"] != v["iou"] for v in itself.views)
    with pytest.raises(ValueError, match="hull_masks"):
        view_agreement(model, cams, sils, voxel_size=4.0, hull_mesh=raw, hull_masks=masks[:5])
    with pytest.raises(ValueError, match="shape"):
        view_agreement(model, cams, sils, voxel_size=4.0, hull_mesh=raw, hull_masks=[m[:-1] for m in masks])
    with pytest.raises(ValueError, match="hull_mesh"):
        view_agreement(model, cams, sils, voxel_size=4.0, hull_masks=masks)


def _plain_mask(mesh, cam, shape):
    """The written-out raster the masks replace: every face whose three vertices lie in front of the camera,
    every pixel of its box tested by the three edge functions (``organlab.raster._fill``'s expressions),
    nothing skipped."""
    import math

    uv, z = cam.project(np.asarray(mesh.vertices, dtype=np.float64), return_depth=True)
    out = np.zeros(shape, dtype=bool)
    h, w = shape
    for f in np.asarray(mesh.faces):
        if not (z[f] > 0).all():
            continue
        (ax, ay), (bx, by), (cx, cy) = uv[f]
        area = (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)
        if area == 0.0:
            continue
        sgn = 1.0 if area > 0 else -1.0
        for r in range(max(math.ceil(min(ay, by, cy)), 0), min(math.floor(max(ay, by, cy)), h - 1) + 1):
            for col in range(max(math.ceil(min(ax, bx, cx)), 0), min(math.floor(max(ax, bx, cx)), w - 1) + 1):
                e0 = sgn * ((bx - ax) * (r - ay) - (by - ay) * (col - ax))
                e1 = sgn * ((cx - bx) * (r - by) - (cy - by) * (col - bx))
                e2 = sgn * ((ax - cx) * (r - cy) - (ay - cy) * (col - cx))
                if e0 >= 0.0 and e1 >= 0.0 and e2 >= 0.0:
                    out[r, col] = True
    return out


@pytest.mark.parametrize("seed", [0, 1])
def test_hull_masks_are_the_plain_raster(seed):
    """organlab.agreement.hull_masks (the raster skipping pixels already set, triangles whose box holds no pixel
    centre, and faces behind the camera through their NaN pixels) against the plain raster above: a sphere's
    hull carved at 3 mm (not the sample), a random triangle soup (open, overlapping, ten faces degenerate), and
    the hull moved 10 mm before the first camera and 25 mm aside (partly behind its plane), seen by 3 cameras
    at random table angles.  Measured: the same masks, pixel for pixel (and, outside this test, on the sample
    at 1 and 0.5 mm and the dino at 1 and 0.5 mm against 672b505's raster)."""
    from organlab.agreement import hull_masks
    from organlab.carving import hull_field
    from organlab.grid import VoxelGrid
    from organlab.mesh import Mesh
    from organlab.surface import mesh_from_field
    from organlab.synthetic import Sphere, default_camera, render_masks

    rng = np.random.default_rng(seed)
    cams = [default_camera((160, 120)).at_table_angle(a) for a in rng.uniform(0, 360, 3)]
    sils = [c >= 0.5 for c in render_masks(Sphere(center=(0, 0, 40), radius=20), cams)]
    grid = VoxelGrid.from_roi((-40, -40, 0), (40, 40, 80), 3.0)
    hull = mesh_from_field(hull_field(sils, cams, grid, sparse=True), grid)
    R = np.asarray(cams[0].R)
    ahead = cams[0].center + 10.0 * R[2] + 25.0 * R[0]  # 10 mm before the first camera, 25 mm aside
    v = rng.normal(0, 25, (300, 3)) + np.array([0, 0, 40])
    f = rng.integers(0, 300, (400, 3))
    f[:10, 2] = f[:10, 1]  # degenerate faces
    soup = Mesh(v, f)
    shifted = [Mesh(hull.vertices + (ahead - np.array([0.0, 0.0, 40.0])), hull.faces)]  # the 20 mm sphere moved there
    for mesh in [hull, soup, *shifted]:
        got = hull_masks(mesh, cams, [np.zeros((120, 160), bool)] * len(cams))
        for cam, g in zip(cams, got):
            np.testing.assert_array_equal(g, _plain_mask(mesh, cam, (120, 160)))
        assert got[0].sum() > 100  # measured 149 - 3 451 pixels in the first view
    depth = cams[0].world_to_camera(np.asarray(shifted[0].vertices, float))[:, 2]
    assert (depth <= 0).any()  # the moved sphere lies partly behind the first camera (and is seen: above)
