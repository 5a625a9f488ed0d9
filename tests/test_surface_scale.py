"""The surface stage at fine voxels: AAA measures read from the band field (never
densified) and from a coarser centreline grid, against the dense path and the truth."""

import numpy as np
import pytest
from scipy import ndimage

from organlab.carving import BandField
from organlab.grid import VoxelGrid
from organlab.surface import measure_aaa
from organlab.surface._sampling import FieldSampler
from tests._shared_data import SAMPLE


def _band(dense, grid, block=8):
    """A BandField holding ``dense`` (values clipped to [-0.5, 1.5]), built block by block."""
    d = np.clip(dense, -0.5, 1.5).astype(np.float32)
    nb = -(-np.asarray(d.shape) // block)
    pad = np.full(nb * block, -0.5, dtype=np.float32)
    pad[: d.shape[0], : d.shape[1], : d.shape[2]] = d
    blocks = pad.reshape(nb[0], block, nb[1], block, nb[2], block).transpose(0, 2, 4, 1, 3, 5)
    states = np.full(tuple(nb), 2, dtype=np.int8)
    states[(blocks == -0.5).all(axis=(3, 4, 5))] = 0
    states[(blocks == 1.5).all(axis=(3, 4, 5))] = 1
    index = np.full(tuple(nb), -1, dtype=np.int32)
    index[states == 2] = np.arange((states == 2).sum())
    return BandField(grid, block, states, index, np.ascontiguousarray(blocks[states == 2])), d


def _tube(voxel, tilt_deg=10.0, r0=8.0, bulge=12.0, s_max=70.0, width=15.0):
    """A tube tilted from Z (ends cut within the sections the measures skip) with a Gaussian bulge: the hull field's shape (0.5 + distance in voxels, clipped)."""
    grid = VoxelGrid.from_roi([-35, -32, 0], [35, 32, 120], voxel)
    c = grid.centers().reshape(*grid.shape, 3)
    a = np.array([np.sin(np.radians(tilt_deg)), 0.0, np.cos(np.radians(tilt_deg))])
    p0 = np.array([-60.0 * a[0] / a[2], 0.0, 0.0])
    q = c - p0
    s = q @ a
    perp = np.linalg.norm(q - s[..., None] * a, axis=-1)
    radius = r0 + bulge * np.exp(-(((s - s_max) / width) ** 2))
    return np.clip(0.5 + (radius - perp) / voxel, -0.5, 1.5).astype(np.float32), grid, p0, a


def test_band_samples_equal_the_dense_fields():
    rng = np.random.default_rng(3)
    f, grid, *_ = _tube(2.0)
    band, dense = _band(f, grid, block=4)
    assert (band.states == 2).any() and (band.states == 1).any() and (band.states == 0).any()
    # points inside, on the edges and outside the grid (cval there)
    ijk = rng.uniform(-2, np.asarray(grid.shape) + 1, size=(20000, 3))
    ijk[:50] = np.round(ijk[:50])
    ijk[50:60, 0] = grid.shape[0] - 1  # on the last voxel plane: interpolated, not cval
    pts = grid.origin + ijk * grid.voxel_size
    want = ndimage.map_coordinates(dense, ijk.T, order=1, mode="constant", cval=-0.5)
    got_band = FieldSampler(band, grid.origin, grid.voxel_size, -0.5)(pts)
    got_dense = FieldSampler(dense, grid.origin, grid.voxel_size, -0.5)(pts)
    np.testing.assert_allclose(got_band, want, atol=1e-5)  # float32 values, float64 weights
    np.testing.assert_allclose(got_dense, want, atol=1e-6)
    # a coarse grid's occupancy: step 2 from voxel (1, 1, 1) samples between voxel centres
    coarse = FieldSampler(band, grid.origin, grid.voxel_size, -0.5).above((1, 1, 1), (10, 12, 14), 2, 0.5)
    ii = np.stack(np.meshgrid(*[1.5 + 2 * np.arange(n) for n in (10, 12, 14)], indexing="ij"), axis=-1)
    np.testing.assert_array_equal(coarse, ndimage.map_coordinates(dense, np.moveaxis(ii, -1, 0), order=1) > 0.5)


def test_above_on_the_band_equals_its_samples():
    """``above``'s one-pass kernel (inside and outside blocks read once) against the band's own trilinear
    samples point by point, bool for bool: steps 1-3, boxes running past the grid (cval there), levels on
    and beside the block values 1.5 and -0.5, where the shortcut must not decide."""
    f, grid, *_ = _tube(1.5, tilt_deg=25.0, r0=6.0, bulge=9.0)  # not the other tests' tube
    band, _ = _band(f, grid, block=4)
    assert (band.states == 2).any() and (band.states == 1).any() and (band.states == 0).any()
    s = FieldSampler(band, grid.origin, grid.voxel_size, -0.5)
    for step, lo in ((1, (0, 0, 0)), (2, (1, 2, 3)), (3, (2, 0, 1)), (2, (-3, -1, 0))):
        shape = -(-(np.asarray(grid.shape) + 4 - np.asarray(lo)) // step)  # past the far faces too
        ijk = np.stack(np.meshgrid(*[lo[d] + 0.5 * (step - 1) + step * np.arange(shape[d]) for d in range(3)],
                                   indexing="ij"), axis=-1)
        vals = s.at_indices(ijk)
        for level in (0.5, 0.0, 1.5, -0.5, 1.4999995, -0.4999995, 2.0):
            np.testing.assert_array_equal(s.above(lo, shape, step, level), vals > level)


def test_measure_aaa_on_the_band_equals_the_dense_field():
    f, grid, p0, a = _tube(1.0)
    band, dense = _band(f, grid)
    mb, md = measure_aaa(band, grid), measure_aaa(dense, grid)
    # the same voxels and sections: only the crop's margin and float rounding differ (measured < 1e-6 mm)
    np.testing.assert_allclose(mb.centreline, md.centreline, atol=1e-9)
    np.testing.assert_allclose(mb.feret_mm, md.feret_mm, atol=1e-4, equal_nan=True)
    assert mb.sac_volume_mm3 == md.sac_volume_mm3
    assert abs(mb.max_diameter_mm - 40.0) < 1.0


def test_a_coarser_centreline_grid_keeps_the_measures():
    f, grid, p0, a = _tube(0.5)
    band, _ = _band(f, grid)
    fine = measure_aaa(band, grid, centreline_voxel_mm=0.5)
    coarse = measure_aaa(band, grid, centreline_voxel_mm=1.0)
    assert coarse.params["centreline_voxel_mm"] == 1.0 and fine.params["centreline_voxel_mm"] == 0.5
    # same sections of the same field along a centreline found on 1 mm voxels (measured: max diameter
    # 39.985 vs 39.981 mm, neck 16.03 vs 16.06, sac volume 0.12 % apart, sac length 0.10 mm apart)
    assert abs(coarse.max_diameter_mm - fine.max_diameter_mm) < 0.1
    assert abs(coarse.neck_diameter_mm - fine.neck_diameter_mm) < 0.1
    assert coarse.sac_volume_mm3 == pytest.approx(fine.sac_volume_mm3, rel=0.01)
    assert abs(coarse.sac_length_mm - fine.sac_length_mm) < 0.5
    for m in (fine, coarse):  # and the truth: a 40 mm bulge, a 16 mm tube
        assert abs(m.max_diameter_mm - 40.0) < 0.5 and abs(m.neck_diameter_mm - 16.0) < 0.5
        q = m.centreline - p0
        # measured 0.51 mm on 1 mm voxels: the path runs on voxel centres, the axis (y = 0) lies between two
        assert np.median(np.linalg.norm(q - np.outer(q @ a, a), axis=1)) < m.params["centreline_voxel_mm"]


def test_pixel_footprint_sets_the_remesh_edge_floor():
    """reconstruct passes its cameras' pixel size at the specimen to finish_surface (sample: ~0.69 mm)."""
    import json

    from organlab.camera import Camera
    from organlab.grid import VoxelGrid
    from organlab.pipeline import pixel_footprint

    root = SAMPLE
    t = json.loads((root / "truth.json").read_text())
    c = t["camera"]
    cams = [Camera(c["K"], c["dist"], v["R"], v["t"], tuple(c["image_size"])) for v in t["views"]]
    grid = VoxelGrid.from_roi((-70, -70, 0), (70, 70, 200), 1.0)
    fp = pixel_footprint(cams, grid)
    # by hand: the distance of the camera centre to the roi's centre over the mean focal length
    # (the table turns the camera about the axis, so every view's depth is about the same)
    centre = np.array([0.0, 0.0, 100.0])
    depth = float((cams[0].R @ centre + cams[0].t)[2])
    assert fp == pytest.approx(depth / np.mean([c["K"][0][0], c["K"][1][1]]), rel=0.02)
    assert 0.6 < fp < 0.8  # the sample's 0.69 mm
    assert cams[0].pixel_footprint(cams[0].center - cams[0].R[2]) == float("inf")  # behind the camera
