"""Textured specimens with concavities no silhouette shows (for the photo-consistency tests).

Nothing in organlab was tuned on these: their shapes, their texture and (with
``make_session(..., hard=True)``) the hard lamp are new to every default.

* :class:`BowlSpecimen` -- a squat rounded solid with bowl-shaped dents on
  its flanks (concave in both directions);
* :class:`GrooveSaddleSpecimen` -- a bulging solid with one deep, narrow
  vertical groove and a broad depression whose centre is a saddle (concave
  around the axis, convex along it).

Both are star solids about the table axis, ``rho <= r(phi, z)``: a ring of
cameras sees, at every height, about the convex hull of the cross-section,
so every dent, groove and depression lies inside every silhouette.  Their
exact volumes come from Gauss-Legendre quadrature of ``r^2 / 2``
(:class:`organlab.synthetic._specimens._StarSolid`, error far below 0.01 %).

The texture (:func:`photo_albedo`) is multi-scale filtered noise in 3-D
(Gaussian-filtered white noise at 1.5, 4 and 10 mm, plus a fine grain),
mapped to a tissue palette with colour variation (a second field shifts the
hue toward yellow, a third adds darker, vessel-like blotches): no periodic or
procedural pattern a measure could be tuned to.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from ._specimens import _StarSolid, _Union

_CACHE: dict = {}
_PAD = 6.0  # mm beyond the bounds covered by the noise grids
_OCTAVES = ((0.5, 1.5, 0.45), (1.0, 4.0, 0.35), (2.0, 10.0, 0.20))  # (grid step mm, sigma mm, weight)


def _noise_fields(seed, lo, hi):
    key = (int(seed), tuple(np.round(lo, 3)), tuple(np.round(hi, 3)))
    if key not in _CACHE:
        rng = np.random.default_rng([int(seed), 2207])
        fields = []
        for channel in range(3):
            octs = []
            for step, sigma, weight in _OCTAVES:
                if channel and step < 1.0:  # colour fields: coarse only
                    continue
                shape = tuple(int(np.ceil((h - l + 2 * _PAD) / step)) + 1 for l, h in zip(lo, hi))
                f = ndimage.gaussian_filter(rng.standard_normal(shape).astype(np.float32), sigma / step, mode="wrap")
                f /= f.std() + 1e-12
                octs.append((step, weight, f))
            fields.append(octs)
        _CACHE[key] = fields
    return _CACHE[key]


def _sample(octs, p, lo):
    v = np.zeros(len(p))
    wsum = 0.0
    for step, weight, f in octs:
        c = ((p - (lo - _PAD)) / step).T
        v += weight * ndimage.map_coordinates(f, c, order=1, mode="nearest")
        wsum += weight**2
    return v / np.sqrt(wsum)


_PINK = np.array([214.0, 132.0, 120.0])
_DEEP = np.array([118.0, 38.0, 44.0])
_FAT = np.array([226.0, 196.0, 120.0])
_VESSEL = np.array([84.0, 40.0, 72.0])


def photo_albedo(points, *, seed=0, bounds=((-60.0, -60.0, -5.0), (60.0, 60.0, 110.0))):
    """Photographic-looking tissue colour of surface points (multi-scale filtered noise).

    Parameters
    ----------
    points : (N, 3) float64, mm, world (table) frame
    seed : int
        Which noise.
    bounds : ((3,), (3,)) float
        Box the noise grids cover, mm (points outside get the border's value).

    Returns
    -------
    (N, 3) float64
        RGB albedo, 0-255 scale.

    Examples
    --------
    >>> a = photo_albedo(np.array([[0.0, 30.0, 40.0], [0.0, 30.0, 41.0]]))
    >>> a.shape, bool((a >= 0).all() and (a <= 255).all())
    ((2, 3), True)
    """
    p = np.asarray(points, np.float64).reshape(-1, 3)
    lo, hi = (np.asarray(b, np.float64) for b in bounds)
    lum, hue, ves = _noise_fields(seed, lo, hi)
    s = 0.5 + 0.5 * np.tanh(1.1 * _sample(lum, p, lo))
    col = _DEEP + s[:, None] * (_PINK - _DEEP)
    y = np.clip(0.5 * _sample(hue, p, lo) - 0.2, 0.0, 0.6)
    col = col + y[:, None] * (_FAT - col)
    b = np.clip((_sample(ves, p, lo) - 0.8) / 0.8, 0.0, 0.7)
    col = col + b[:, None] * (_VESSEL - col)
    return np.clip(col, 0.0, 255.0)


class _TexturedStar(_Union):
    texture_seed = 0

    def __init__(self, terms, height, name, seed):
        star = _StarSolid(np.array(terms, dtype=np.float64), 0.0, float(height))
        r = star.r_max
        super().__init__([star], star.volume, (np.array([-r, -r, 0.0]), np.array([r, r, float(height)])), name)
        self.star = star
        self.texture_seed = int(seed)

    def albedo(self, points):
        return photo_albedo(points, seed=self.texture_seed, bounds=self.bounds)


class BowlSpecimen(_TexturedStar):
    """A rounded solid (radius about 36 mm, 0 <= z <= 85 mm) with ``n_bowls`` bowl-shaped dents.

    Each dent is ``depth`` mm deep at its centre, a von Mises bump in the
    table angle (half width about 11 degrees) times ``sin^2`` in height over
    26 mm, so it is round and concave in both directions.

    Examples
    --------
    >>> s = BowlSpecimen()
    >>> round(s.volume / 1000, 1), bool(s.inside(np.array([[0.0, 0.0, 40.0]]))[0])
    (373.7, True)
    """

    def __init__(self, *, n_bowls=4, depth=9.0, name="bowls", seed=11):
        if not 0 <= depth < 20 or n_bowls < 0:
            raise ValueError("need n_bowls >= 0 and 0 <= depth < 20 mm")
        h = 85.0
        terms = [[34.0, 0, 0, 0, 0, 0, 0], [5.0, 1, -30.0, h + 30.0, 0, 0, 0], [1.5, 1, -5.0, h + 5.0, 1, 3, 0.4]]
        self.bowl_angles = [0.5 + 2 * np.pi * k / n_bowls for k in range(int(n_bowls))]
        for k, mu in enumerate(self.bowl_angles):
            z0 = 18.0 + 10.0 * (k % 3)
            terms.append([-float(depth), 1, z0, z0 + 26.0, 2, 26.0, mu])
        super().__init__(terms, h, name, seed)


class GrooveSaddleSpecimen(_TexturedStar):
    """A bulging solid (radius 30-37 mm, 0 <= z <= 90 mm) with a deep groove and a saddle.

    The groove runs vertically from z = 12 to 80 mm, ``groove_depth`` mm deep
    and narrow (von Mises, half width about 7 degrees); opposite it a broad
    depression (``saddle_depth`` mm, half width about 30 degrees) crosses the
    convex bulge, so its centre is a saddle.

    Examples
    --------
    >>> s = GrooveSaddleSpecimen()
    >>> round(s.volume / 1000, 1)
    314.3
    """

    def __init__(self, *, groove_depth=10.0, saddle_depth=7.0, name="groove-saddle", seed=23):
        h = 90.0
        terms = [[30.0, 0, 0, 0, 0, 0, 0], [7.0, 1, -8.0, h + 8.0, 0, 0, 0],
                 [-float(groove_depth), 1, 12.0, 80.0, 2, 70.0, 1.2],
                 [-float(saddle_depth), 1, 5.0, 85.0, 2, 4.0, 1.2 + np.pi]]
        super().__init__(terms, h, name, seed)
