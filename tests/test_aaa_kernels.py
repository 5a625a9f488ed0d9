"""The AAA measures' compiled shortcuts against the plain computations they replace, on scenes
the sample never saw: the sections' band sampling (state-valued pixels off the contours) and the
sac volume's nearest centreline points."""

import numpy as np
import pytest
from scipy.spatial import cKDTree

from organlab.raster import iso_contours
from organlab.surface import _aaa
from organlab.surface._sampling import FieldSampler
from tests.test_surface_scale import _band, _tube


@pytest.mark.parametrize("block, voxel", [(4, 1.5), (3, 1.5), (4, 1.0)])
def test_band_planes_trace_the_fields_contours(block, voxel):
    """``_sample_planes(..., level)`` on a band field (pixels whose voxels lie in one inside or outside
    block take the block's value unless a square they are in may cross the level) against the field's
    own samples everywhere: every pixel off those squares keeps its side, every other pixel the field's
    value bit for bit, and ``organlab.raster.iso_contours`` traces the same contours, point for point.  Planes at random
    centres and tilts through a tilted, swollen tube, windows of steps 1 and 3, levels on and beside the
    block values; block 3 takes the division path (4: shifts); voxels of 1 mm the
    multiplication by the inverse (1.5 mm: the division).  Measured: equal everywhere (and the
    sample's measures at 1 and 0.25 mm bit-identical to the plain sampling's)."""
    f, grid, p0, a = _tube(voxel, tilt_deg=20.0, r0=7.0, bulge=10.0)
    band, _ = _band(f, grid, block=block)
    assert (band.states == 2).any() and (band.states == 1).any() and (band.states == 0).any()
    sample = FieldSampler(band, grid.origin, grid.voxel_size, -0.5)
    rng = np.random.default_rng(11)
    planes, windows = [], []
    for _ in range(24):
        c = p0 + rng.uniform(20, 110) * a + rng.normal(0, 3, 3)
        t = a + rng.normal(0, 0.4, 3)
        pl = _aaa._Plane(c, t / np.linalg.norm(t), rng.uniform(8, 40), rng.choice([0.5, 0.75, 1.0]))
        n, step = len(pl.g), int(rng.choice([1, 3]))
        i0, j0 = rng.integers(0, n // 3, 2)
        planes.append(pl)
        windows.append((i0, n - rng.integers(0, n // 3), j0, n - rng.integers(0, n // 3), step))
    n_state = n_contours = 0
    for level in (0.5, 0.0, 1.2, 1.5, -0.5, 1.4999995):
        want = _aaa._sample_planes(sample, planes, windows)
        got = _aaa._sample_planes(sample, planes, windows, level)
        for w, g in zip(want, got):
            diff = w != g
            n_state += diff.sum()
            np.testing.assert_array_equal(w > level, g > level)
            # a pixel holding a state's value is in no square whose corners lie on both sides
            up = w > level
            mixed = np.zeros_like(up)
            sq = (up[:-1, :-1] != up[1:, :-1]) | (up[:-1, :-1] != up[:-1, 1:]) | (up[:-1, :-1] != up[1:, 1:])
            for da in (0, 1):
                for db in (0, 1):
                    mixed[da : da + sq.shape[0], db : db + sq.shape[1]] |= sq
            assert not (diff & mixed).any()
            pw, ow = iso_contours(np.ascontiguousarray(w), level)
            pg, og = iso_contours(np.ascontiguousarray(g), level)
            np.testing.assert_array_equal(ow, og)
            np.testing.assert_array_equal(pw, pg)
            n_contours += len(ow) - 1
    assert n_state > 10_000 and n_contours > 50  # the shortcut was taken, and there were contours to trace


def test_sac_volume_counts_the_trees_nearest_points():
    """``_sac_volume``'s compiled nearest-point scan against ``cKDTree.query``'s nearest points: random
    voxel sets and centrelines, including points on voxel centres (exact ties, left to the tree),
    repeated points, voxel sizes off a power of two.  Measured: the same volume in all 60 cases."""
    rng = np.random.default_rng(4)
    for trial in range(60):
        shape = tuple(rng.integers(3, 25, 3))
        inside = rng.random(shape) < 0.6
        vs = [1.0, 0.5, 0.7, 0.25][trial % 4]
        origin = rng.integers(-5, 5, 3).astype(float) * (vs if trial % 2 else 1.3)
        k = int(rng.integers(1, 40))
        if trial % 3 == 0:
            c = origin + rng.integers(0, 25, (k, 3)) * vs
        else:
            c = origin + rng.random((k, 3)) * np.array(shape) * vs
        if trial % 5 == 0:
            c = np.concatenate([c, c[: k // 2]])
        arc = np.sort(rng.random(len(c))) * 100
        s0, s1 = np.sort(rng.random(2) * 100)
        _, near = cKDTree(c).query(origin + np.argwhere(inside) * vs)
        want = float(((arc[near] >= s0) & (arc[near] <= s1)).sum() * vs**3)
        assert _aaa._sac_volume(inside, origin, vs, c, arc, s0, s1) == want


def test_distances_with_runs_of_outside_are_scipys():
    """``_distance_sq`` (each line's runs of outside voxels reduced to their ends) against scipy's exact
    distances on masks of many short runs: sparse random voxels, thin rods, a hollow shell, an empty box.
    Measured: equal everywhere."""
    from scipy import ndimage

    rng = np.random.default_rng(8)
    masks = [rng.random((23, 17, 29)) < p for p in (0.05, 0.3, 0.9)]
    rods = np.zeros((20, 21, 22), dtype=bool)
    rods[::4, 3:18, ::5] = True
    x, y, z = np.meshgrid(*[np.linspace(-1, 1, 25)] * 3, indexing="ij")
    shell = np.abs(x**2 + y**2 + z**2 - 0.5) < 0.15
    masks += [rods, shell, np.zeros((5, 6, 7), dtype=bool)]
    for m in masks:
        p = np.pad(m, 1)
        np.testing.assert_array_equal(_aaa._distance_sq(p), np.rint(ndimage.distance_transform_edt(p) ** 2))


@pytest.mark.parametrize("block", [4, 3])
def test_voxels_above_are_the_samplers(block):
    """``_voxels_above`` (the lumen's voxels at the grid's own size, read block by block) against
    ``FieldSampler.above(lo, shape, 1, level)`` (the field's trilinear samples at the voxel centres): a
    tilted, swollen tube (not the sample) with speckle in its band, random boxes (at the grid's edges
    too, cutting blocks), levels on and beside the block values.  Measured: equal everywhere."""
    f, grid, _, _ = _tube(2.0, tilt_deg=25.0, r0=6.0, bulge=8.0)
    rng = np.random.default_rng(block)
    f = np.where((f > -0.5) & (f < 1.5), f + rng.normal(0, 0.05, f.shape).astype(np.float32), f)
    band, _ = _band(f, grid, block=block)
    assert (band.states == 2).any() and (band.states == 1).any() and (band.states == 0).any()
    sample = FieldSampler(band, grid.origin, grid.voxel_size, -0.5)
    n = np.asarray(grid.shape)
    for trial in range(12):
        lo = rng.integers(0, n // 2) if trial % 3 else np.zeros(3, dtype=int)
        hi = n if trial % 4 == 0 else rng.integers(lo + 1, n + 1)
        for level in (0.5, -0.5, 1.5, 0.3, 1.2):
            want = sample.above(lo, hi - lo, 1, level)
            got = _aaa._voxels_above(band.states, band.index, band.values, block, lo.astype(np.int64),
                                     (hi - lo).astype(np.int64), level)
            np.testing.assert_array_equal(got, want)


def test_closed_contours_around_the_centre_are_skimages():
    """``_closed_around`` (contours and the point-in-polygon test compiled, ``_around``) against the plain
    computation it replaces: ``skimage.measure.find_contours``, the closed ones of 4 points or more holding the
    centre by ``skimage.measure.points_in_poly``, the smallest by area.  Random smooth images with nested and
    side-by-side blobs (not the sample's sections), NaN holes, and contours through the centre pixel itself
    (the centre on a contour's vertex and on its edges: integer images at level 0.5 put vertices on pixel
    centres' midpoints, which the centres ``(n - 1) / 2`` hit for even sizes).  Measured: the same contour,
    point for point, and the same area, in every case (and none chosen in some)."""
    from skimage.measure import find_contours, points_in_poly

    def plain(img, level, centre):
        best = None
        for ct in find_contours(img, level):
            if len(ct) < 4 or np.abs(ct[0] - ct[-1]).max() > 1e-9 or not points_in_poly(centre, ct)[0]:
                continue
            x, y = ct[:, 0], ct[:, 1]
            area = 0.5 * abs(np.dot(x, np.roll(y, 1)) - np.dot(y, np.roll(x, 1)))
            if best is None or area < best[1]:
                best = (ct, area)
        return best

    rng = np.random.default_rng(3)
    n_none = n_found = n_many = 0
    for trial in range(400):
        n = int(rng.integers(5, 40))
        r, c = np.mgrid[:n, :n].astype(float)
        img = np.zeros((n, n))
        for b in range(int(rng.integers(1, 5))):  # the first blob about the centre (a section), the others anywhere
            cr, cc = (n / 2 + rng.normal(0, 1, 2)) if b == 0 else rng.uniform(0, n, 2)
            w = rng.uniform(1, n / 5) if b == 0 else rng.uniform(1, n / 3)
            h = rng.uniform(0.6, 2.0)
            img += h * np.exp(-((r - cr) ** 2 + (c - cc) ** 2) / w**2)
            if b == 0 and trial % 3 == 1:  # a crater: a ring above the level, two closed contours around the centre
                img -= h * np.exp(-((r - cr) ** 2 + (c - cc) ** 2) / (0.5 * w) ** 2)
        if trial % 2:  # a border below the level: the contours close
            img[[0, -1]] = img[:, [0, -1]] = 0.0
        if trial % 3 == 0:
            img = np.round(img * 2) / 2  # plateaus on the level: contour points on pixels and midpoints
        if trial % 7 == 0:
            img[rng.integers(0, n, 3), rng.integers(0, n, 3)] = np.nan
        level = 0.5 if trial % 2 else float(rng.uniform(0.2, 1.0))
        centre = np.array([[(n - 1) / 2] * 2]) if trial % 4 else rng.integers(0, n, (1, 2)).astype(float) / 2
        want, got = plain(img, level, centre), _aaa._closed_around(img, level, centre)
        if want is None:
            assert got is None
            n_none += 1
            continue
        np.testing.assert_array_equal(got[0], want[0])
        assert got[1] == want[1]
        n_found += 1
        n_many += sum(len(ct) >= 4 and points_in_poly(centre, ct)[0] for ct in find_contours(img, level)) > 1
    assert n_none > 100 and n_found > 150 and n_many > 5  # measured 212, 188 and 13 of 400
