"""organlab.nbcam.undistort_points (the poses check's outline undistortion, compiled) against the function it
stands in for, organlab.camera.undistort: the same numbers bit for bit, and the inverse of the distortion."""

import numpy as np

from organlab.camera import distort, undistort
from organlab.nbcam import undistort_points


def test_undistort_points_is_camera_undistort_bit_for_bit():
    """Random lenses (barrel and pincushion, tangential terms, some beyond any real lens: where Newton's method
    diverges it must diverge alike) and points over a wide field, some NaN, and a lens without distortion (returned
    as given): equal arrays, NaN where NaN.  Measured: equal on 3000 such cases; 300 here."""
    rng = np.random.default_rng(11)
    for t in range(300):
        n = int(rng.integers(1, 800))
        xd = rng.uniform(-0.5, 0.5, (n, 2))
        if t % 7 == 0:
            xd[rng.integers(0, n)] = np.nan
        dist = rng.normal(0, [0.2, 0.1, 0.002, 0.002, 0.05])
        if t % 11 == 0:
            dist[:] = 0.0
        got = undistort_points(xd, dist)
        np.testing.assert_array_equal(got, undistort(xd, dist))


def test_undistort_points_inverts_the_distortion():
    """On the sample's lens (k1 -0.3, k2 0.1, p1 0.0012, p2 -0.0008) and on milder random ones, over a 640 x 480
    frame at f = 800 px (normalised |x| <= 0.4, |y| <= 0.3): ``distort(undistort_points(x)) == x`` to 1e-13.
    Measured: 1.1e-16 at worst; a lens whose distortion did not turn back would leave residuals of 1e-3 and more."""
    rng = np.random.default_rng(5)
    lenses = [np.array([-0.3, 0.1, 0.0012, -0.0008, 0.0])] + [rng.normal(0, [0.1, 0.05, 0.001, 0.001, 0.01])
                                                               for _ in range(20)]
    xd = np.column_stack([rng.uniform(-0.4, 0.4, 2000), rng.uniform(-0.3, 0.3, 2000)])
    worst = 0.0
    for dist in lenses:
        xn = undistort_points(xd, dist)
        assert np.abs(xn - xd).max() > 1e-4  # the lenses do distort
        worst = max(worst, float(np.abs(distort(xn, dist) - xd).max()))
    assert worst < 1e-13
