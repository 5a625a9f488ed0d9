"""The shared geometry kernels (organlab.surface._geom) are the numpy expressions they stand for, to the bit.

The closest-point code and the remesher both build on them, and the finished meshes are compared by sha1 across
changes: a kernel whose operations drift from numpy's order (``(a + b) + c``, ``np.cross``'s products) moves a
vertex by an ulp and the mesh by more (the remesher's decisions are discrete).  Bytes compared: -0.0 and 0.0 differ.
"""

import numpy as np
import pytest

from organlab.surface._geom import _centroid, _normal, _normal3
from organlab.surface._remesh import _centroids


@pytest.mark.parametrize("scale", [1e-3, 1.0, 1e3])
def test_normal_and_centroid_are_numpys_bits(scale):
    # random triangles about a far origin (coordinates of 100 mm scale with sub-mm edges, as a surface in the world
    # frame), some with repeated corners (a null face: its cross product exactly 0)
    rng = np.random.default_rng(11)
    v = 100.0 + scale * rng.standard_normal((90, 3))
    f = rng.integers(0, len(v), (120, 3))
    f[:5, 1] = f[:5, 0]
    want = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    got = np.array([_normal(v[a], v[b], v[c]) for a, b, c in f])
    got3 = np.array([_normal3(*v[a], *v[b], *v[c]) for a, b, c in f])
    assert want.tobytes() == got.tobytes() == got3.tobytes()
    distinct = (f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])
    assert not got[~distinct].any() and got[distinct].any(axis=1).all()  # null faces exactly 0, no other
    mean = v[f].mean(axis=1)
    assert mean.tobytes() == np.array([[_centroid(v, a, b, c, k) for k in range(3)] for a, b, c in f]).tobytes()
    out = np.empty((len(f), 3))
    _centroids(v, f.astype(np.int64), out)  # fit_faces' centroids, through the shared kernel
    assert mean.tobytes() == out.tobytes()
