"""How far one surface lies from another: closest points on a triangle mesh (numpy, scipy and one numba kernel).

:func:`closest_points` finds, for each query point, the nearest point of a mesh among the
triangles whose centroids are nearest to it (a k-d tree of the centroids); :func:`surface_deviation`
measures a finished surface against the raw marching-cubes one both ways (the finished surface's
vertices and face centres to the raw surface, the raw vertices to the finished one), so a thin part
the finishing shaved off shows as well as a bump it added.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

import weakref

from ..mesh import Mesh

_SURFACES = weakref.WeakKeyDictionary()

#: Candidate triangles per query point (by centroid distance).  Marching-cubes and remeshed triangles
#: are within a factor of a few of one size, so the nearest triangle is nearly always among the nearest
#: centroids: measured on the 1 mm dino's marching-cubes mesh against a brute-force search over all
#: 57 442 faces, 300 points scattered 0.7 mm about it: k = 8 misses 2 by at most 0.0017 mm, k = 6 3 by
#: 0.014 mm, k = 4 9 by 0.099 mm.  The figures of a finished 1 mm sample are the same at 4, 6 and 8
#: (0.0324 / 0.7063 voxels); the k-d tree's query is most of the time (0.10 s at 4, 0.14 s at 8).
_K = 6

#: Queries of at least this many points run the k-d tree on all cores (threads cost more below).
_PARALLEL = 20_000


def _tri_closest(p, a, b, c):
    """Closest points of triangles ``abc`` to points ``p`` (all ``(N, 3)``), Ericson's regions, vectorised."""
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = np.einsum("ij,ij->i", ab, ap), np.einsum("ij,ij->i", ac, ap)
    bp = p - b
    d3, d4 = np.einsum("ij,ij->i", ab, bp), np.einsum("ij,ij->i", ac, bp)
    cp = p - c
    d5, d6 = np.einsum("ij,ij->i", ab, cp), np.einsum("ij,ij->i", ac, cp)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        den = va + vb + vc
        v = np.where(den != 0, vb / den, 0.0)
        w = np.where(den != 0, vc / den, 0.0)
        out = a + ab * v[:, None] + ac * w[:, None]  # inside the face
        # edges (later assignments win only where their region holds; regions are disjoint)
        t_ab = d1 / (d1 - d3)
        m = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
        out[m] = a[m] + t_ab[m, None] * ab[m]
        t_ac = d2 / (d2 - d6)
        m = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
        out[m] = a[m] + t_ac[m, None] * ac[m]
        t_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        m = (va <= 0) & ((d4 - d3) >= 0) & ((d5 - d6) >= 0)
        out[m] = b[m] + t_bc[m, None] * (c[m] - b[m])
    # vertices
    m = (d1 <= 0) & (d2 <= 0)
    out[m] = a[m]
    m = (d3 >= 0) & (d4 <= d3)
    out[m] = b[m]
    m = (d6 >= 0) & (d5 <= d6)
    out[m] = c[m]
    return out


@njit(cache=True, nogil=True)
def _closest_kernel(points, v, f, cand, best, dist, face):
    """For each point, the closest point over its candidate triangles (Ericson's regions, one at a time)."""
    for i in range(points.shape[0]):
        px, py, pz = points[i, 0], points[i, 1], points[i, 2]
        dbest = np.inf
        for j in range(cand.shape[1]):
            t = cand[i, j]
            a, b, c = f[t, 0], f[t, 1], f[t, 2]
            ax, ay, az = v[a, 0], v[a, 1], v[a, 2]
            abx, aby, abz = v[b, 0] - ax, v[b, 1] - ay, v[b, 2] - az
            acx, acy, acz = v[c, 0] - ax, v[c, 1] - ay, v[c, 2] - az
            apx, apy, apz = px - ax, py - ay, pz - az
            d1 = abx * apx + aby * apy + abz * apz
            d2 = acx * apx + acy * apy + acz * apz
            bpx, bpy, bpz = apx - abx, apy - aby, apz - abz
            d3 = abx * bpx + aby * bpy + abz * bpz
            d4 = acx * bpx + acy * bpy + acz * bpz
            cpx, cpy, cpz = apx - acx, apy - acy, apz - acz
            d5 = abx * cpx + aby * cpy + abz * cpz
            d6 = acx * cpx + acy * cpy + acz * cpz
            vc = d1 * d4 - d3 * d2
            vb = d5 * d2 - d1 * d6
            va = d3 * d6 - d5 * d4
            if d1 <= 0.0 and d2 <= 0.0:
                s_, t_ = 0.0, 0.0
            elif d3 >= 0.0 and d4 <= d3:
                s_, t_ = 1.0, 0.0
            elif vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
                s_, t_ = d1 / (d1 - d3), 0.0
            elif d6 >= 0.0 and d5 <= d6:
                s_, t_ = 0.0, 1.0
            elif vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
                s_, t_ = 0.0, d2 / (d2 - d6)
            elif va <= 0.0 and (d4 - d3) >= 0.0 and (d5 - d6) >= 0.0:
                w = (d4 - d3) / ((d4 - d3) + (d5 - d6))
                s_, t_ = 1.0 - w, w
            else:
                den = va + vb + vc
                s_, t_ = (vb / den, vc / den) if den != 0.0 else (0.0, 0.0)
            qx = ax + s_ * abx + t_ * acx
            qy = ay + s_ * aby + t_ * acy
            qz = az + s_ * abz + t_ * acz
            dd = (qx - px) ** 2 + (qy - py) ** 2 + (qz - pz) ** 2
            if dd < dbest:
                dbest = dd
                best[i, 0], best[i, 1], best[i, 2] = qx, qy, qz
                face[i] = t
        dist[i] = math.sqrt(dbest)


def _surface(mesh):
    """The :class:`_Surface` of ``mesh``, built once per mesh (meshes are immutable)."""
    got = _SURFACES.get(mesh)
    if got is None:
        got = _SURFACES[mesh] = _Surface(mesh)
    return got


class _Surface:
    """A mesh prepared for closest-point queries (its centroid tree built once)."""

    def __init__(self, mesh, tree=None):
        from scipy.spatial import cKDTree

        self.v = np.asarray(mesh.vertices, dtype=np.float64)
        self.f = np.asarray(mesh.faces, dtype=np.int64)
        # ``tree``: the centroid tree of a mesh with these faces and vertices at most a rounding apart (it
        # only picks the candidate faces; the distances are this mesh's own)
        self.tree = cKDTree(self.v[self.f].mean(axis=1)) if tree is None else tree
        self.k = min(_K, len(self.f))

    def closest(self, points, k=None):
        """``(closest (N, 3), distance (N,), face (N,))`` for ``points`` ``(N, 3)`` (among ``k`` candidate faces)."""
        points = np.ascontiguousarray(points, dtype=np.float64)
        n = len(points)
        best, dist, face = np.empty((n, 3)), np.empty(n), np.empty(n, dtype=np.int64)
        if n:
            # both cores for the large queries (the remesher's relaxations, the deviation): the same candidates
            _, cand = self.tree.query(points, k=self.k if k is None else min(k, len(self.f)),
                                      workers=-1 if n >= _PARALLEL else 1)
            _closest_kernel(points, self.v, self.f, np.ascontiguousarray(cand.reshape(n, -1), dtype=np.int64), best,
                            dist, face)
        return best, dist, face


def closest_points(points: np.ndarray, mesh: Mesh) -> tuple[np.ndarray, np.ndarray]:
    """The nearest point of ``mesh`` to each of ``points``, and its distance.

    Parameters
    ----------
    points : (N, 3) float64, mm, world frame
    mesh : Mesh
        World frame, mm.

    Returns
    -------
    closest : (N, 3) float64, mm
    distance : (N,) float64, mm

    Examples
    --------
    >>> import numpy as np
    >>> from organlab.mesh import Mesh
    >>> from organlab.surface import closest_points
    >>> tri = Mesh(np.array([[0.0, 0, 0], [2, 0, 0], [0, 2, 0]]), np.array([[0, 1, 2]]))
    >>> q, d = closest_points(np.array([[0.5, 0.5, 3.0], [-1.0, -1.0, 0.0]]), tri)
    >>> q.round(3).tolist(), d.round(3).tolist()
    ([[0.5, 0.5, 0.0], [0.0, 0.0, 0.0]], [3.0, 1.414])
    """
    q, d, _ = _Surface(mesh).closest(points)
    return q, d


def surface_deviation(finished: Mesh, raw: Mesh, *, voxel_size: float, raw_surface: _Surface | None = None) -> dict:
    """How far ``finished`` lies from ``raw``, both ways, in voxels.

    Parameters
    ----------
    finished, raw : Mesh
        World frame, mm.
    voxel_size : float, mm

    Returns
    -------
    dict
        ``mean_voxels`` and ``max_voxels``: the larger of the two directions' mean and maximum
        distance (the finished surface's vertices and face centres to ``raw``; ``raw``'s vertices to
        the finished surface), over ``voxel_size``; ``finished_to_raw`` and ``raw_to_finished``:
        each direction's ``mean_voxels``, ``p99_voxels``, ``max_voxels``.
    """
    rs = _surface(raw) if raw_surface is None else raw_surface
    return _deviation_figures(*_distances(finished, raw, rs), voxel_size)


#: :func:`_distances` runs its two directions side by side for raw surfaces up to this many vertices (the sample
#: at 1 mm: 28 864), one after the other above (0.25 mm: 930 k, where their arrays would add to the peak).
_SIDE_BY_SIDE = 200_000


def _distances(finished, raw, rs):
    """``(d_out, d_in)``, mm: ``finished``'s vertices then face centres to ``raw`` (prepared as ``rs``), and
    ``raw``'s vertices to ``finished`` (:func:`surface_deviation`'s figures come from these).

    Up to :data:`_SIDE_BY_SIDE` raw vertices the second direction (``finished``'s tree built, then queried) runs
    in a second thread while this one queries ``rs``: the same calls, so the same distances; both release the GIL
    (the k-d tree's query, the nogil kernel).  The 1 mm sample: 31 403 and 28 864 points, about 0.05 and 0.04 s
    CPU, the last step of the viewer's full update, when the AAA measures beside it are done.
    """
    fv, ff = np.asarray(finished.vertices), np.asarray(finished.faces)
    pts = np.concatenate([fv, fv[ff].mean(axis=1)])
    if len(raw.vertices) > _SIDE_BY_SIDE:
        _, d_out, _ = rs.closest(pts)
        _, d_in, _ = _Surface(finished).closest(raw.vertices)
        return d_out, d_in
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(1, thread_name_prefix="organlab-deviation") as pool:
        back = pool.submit(lambda: _Surface(finished).closest(raw.vertices)[1])
        _, d_out, _ = rs.closest(pts)
        return d_out, back.result()


def _deviation_figures(d_out, d_in, voxel_size):
    def figures(d):
        d = d / voxel_size
        return {"mean_voxels": round(float(d.mean()), 4), "p99_voxels": round(float(np.percentile(d, 99)), 4),
                "max_voxels": round(float(d.max()), 4)}

    a, b = figures(d_out), figures(d_in)
    return {"mean_voxels": max(a["mean_voxels"], b["mean_voxels"]), "max_voxels": max(a["max_voxels"], b["max_voxels"]),
            "finished_to_raw": a, "raw_to_finished": b}
