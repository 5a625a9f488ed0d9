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
