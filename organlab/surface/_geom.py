"""Small geometry kernels (numba) that the closest-point code (:mod:`._deviation`) and the remesher (:mod:`._remesh`)
both use: a face's normal (its edge vectors' cross product, not normalized) and its centroid.

One place for the arithmetic their compiled loops share: each kernel is the numpy expression it stands for, its
operations in numpy's order (so the same bits as ``np.cross(p1 - p0, p2 - p0)`` and ``v[f].mean(axis=1)``).  Below
both modules (:mod:`._remesh` imports :mod:`._deviation`, so neither could hold them for the other); imports
nothing of organlab.
"""

from __future__ import annotations

from numba import njit


@njit(cache=True, nogil=True, inline="always")
def _normal3(x0, y0, z0, x1, y1, z1, x2, y2, z2):
    """The cross product ``(p1 - p0) x (p2 - p0)`` of three points given by their coordinates: a face's normal,
    twice its area long (``np.cross``'s operations, in its order)."""
    ux, uy, uz = x1 - x0, y1 - y0, z1 - z0
    vx, vy, vz = x2 - x0, y2 - y0, z2 - z0
    return uy * vz - uz * vy, uz * vx - ux * vz, ux * vy - uy * vx


@njit(cache=True, nogil=True)
def _normal(p0, p1, p2):
    """:func:`_normal3` of three points given as arrays of 3 coordinates (the same arithmetic)."""
    return _normal3(p0[0], p0[1], p0[2], p1[0], p1[1], p1[2], p2[0], p2[1], p2[2])


@njit(cache=True, nogil=True, inline="always")
def _centroid(v, a, b, c, k):
    """Coordinate ``k`` of the centroid of vertices ``a``, ``b``, ``c`` of ``v``, as numpy's ``v[f].mean(axis=1)``
    (its sum from the first corner, then the division)."""
    return ((v[a, k] + v[b, k]) + v[c, k]) / 3.0
