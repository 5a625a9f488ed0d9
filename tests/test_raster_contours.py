"""organlab.raster.iso_contours, the compiled contour tracer of the poses check's outlines and the AAA measures'
sections, against the function it stands in for, ``skimage.measure.find_contours``."""

import numpy as np
import pytest

from organlab.raster import iso_contours


def test_contours_are_skimages():
    """``iso_contours`` gives skimage.measure.find_contours's contours exactly.

    The same contours in the same order, each with the same points in the same order from the same start:
    random noise, smooth fields (level at their median), integer images whose vertices lie exactly on
    the level (the degenerate squares skimage skips and the points two contours share), and smooth fields
    with NaN pixels (their squares left out).  Measured: equal, array for array, on 3000 such images (90 142
    contours; before the NaN kind) and on the sample's sections at 1 mm and its 36 outlines; 500 here.
    """
    from scipy import ndimage
    from skimage.measure import find_contours

    rng = np.random.default_rng(7)
    n = 0
    for t in range(500):
        h, w = rng.integers(2, 40, 2)
        kind = t % 5
        if kind == 0:
            img, level = rng.random((h, w)), 0.5
        elif kind == 1:
            img = ndimage.gaussian_filter(rng.random((h, w)), 2)
            level = float(np.median(img))
        elif kind == 2:
            img, level = rng.integers(0, 3, (h, w)).astype(float), 1.0
        elif kind == 3:
            img, level = rng.integers(0, 2, (h, w)).astype(float), 0.5
        else:
            img = ndimage.gaussian_filter(rng.random((h, w)), 2)
            level = float(np.median(img))
            img[rng.random((h, w)) < 0.05] = np.nan
        want = find_contours(img, level)
        pts, offs = iso_contours(img, level)
        assert pts.dtype == np.float64 and offs.dtype == np.int64
        assert len(offs) - 1 == len(want)
        for k, ct in enumerate(want):
            np.testing.assert_array_equal(pts[offs[k] : offs[k + 1]], ct)
        n += len(want)
    assert n > 5000  # measured 14 133: the images do have contours


def test_contours_of_a_disc_and_of_nothing():
    """A disc's coverage (1 inside, 0 outside, bool in): one closed contour whose area is the disc's to
    within the staircase's error; an image without the level: no contour (empty arrays of the promised
    shapes).  Measured: 1 contour, area 1 251.5 px2 against pi 20^2 = 1 256.6 (0.4 % below), its centroid on the
    disc's centre (the disc is symmetric about it on the pixel grid)."""
    yy, xx = np.mgrid[:64, :64]
    disc = (yy - 31.5) ** 2 + (xx - 30.0) ** 2 <= 20.0**2
    pts, offs = iso_contours(disc, 0.5)
    assert len(offs) == 2 and (pts[0] == pts[-1]).all()
    y, x = pts[:, 0], pts[:, 1]
    cross = x[:-1] * y[1:] - x[1:] * y[:-1]  # the polygon's area and centroid (shoelace)
    area = 0.5 * cross.sum()
    cx, cy = ((x[:-1] + x[1:]) * cross).sum() / (6 * area), ((y[:-1] + y[1:]) * cross).sum() / (6 * area)
    assert abs(abs(area) / (np.pi * 20.0**2) - 1) < 0.02
    assert abs(cx - 30.0) < 0.02 and abs(cy - 31.5) < 0.02
    pts, offs = iso_contours(np.zeros((5, 7)), 0.5)
    assert pts.shape == (0, 2) and offs.tolist() == [0]


def test_contours_refuse_bad_input():
    with pytest.raises(ValueError, match="image must be 2-D"):
        iso_contours(np.zeros((3, 3, 3)), 0.5)
    with pytest.raises(ValueError, match="level must be finite"):
        iso_contours(np.zeros((3, 3)), np.nan)
    with pytest.raises(ValueError, match="level must be a number"):
        iso_contours(np.zeros((3, 3)), "half")
