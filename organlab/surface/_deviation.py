"""How far one surface lies from another: closest points on a triangle mesh (numpy and scipy only).

:func:`closest_points` finds, for each query point, the nearest point of a mesh among the
triangles whose centroids are nearest to it (a k-d tree of the centroids); :func:`surface_deviation`
measures a finished surface against the raw marching-cubes one both ways (the finished surface's
vertices and face centres to the raw surface, the raw vertices to the finished one), so a thin part
the finishing shaved off shows as well as a bump it added.
"""

from __future__ import annotations

import numpy as np

from ..mesh import Mesh

#: Candidate triangles per query point (by centroid distance).  Marching-cubes and remeshed triangles
#: are within a factor of a few of one size, so the nearest triangle is nearly always among the nearest
#: centroids: measured on the 1 mm dino's marching-cubes mesh against a brute-force search over all
#: 57 442 faces, 300 points scattered 0.7 mm about it, 298 exact and 2 within 0.0017 mm.
_K = 8


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


class _Surface:
    """A mesh prepared for closest-point queries (its centroid tree built once)."""

    def __init__(self, mesh):
        from scipy.spatial import cKDTree

        self.v = np.asarray(mesh.vertices, dtype=np.float64)
        self.f = np.asarray(mesh.faces, dtype=np.int64)
        self.tree = cKDTree(self.v[self.f].mean(axis=1))
        self.k = min(_K, len(self.f))

    def closest(self, points, *, chunk=65536):
        """``(closest (N, 3), distance (N,), face (N,))`` for ``points`` ``(N, 3)``."""
        points = np.asarray(points, dtype=np.float64)
        n = len(points)
        best = np.empty((n, 3))
        dist = np.empty(n)
        face = np.empty(n, dtype=np.int64)
        for s in range(0, n, chunk):
            p = points[s:s + chunk]
            _, cand = self.tree.query(p, k=self.k)
            cand = cand.reshape(len(p), -1)
            tri = self.f[cand.ravel()]
            q = _tri_closest(np.repeat(p, cand.shape[1], axis=0), self.v[tri[:, 0]], self.v[tri[:, 1]], self.v[tri[:, 2]])
            d2 = ((q - np.repeat(p, cand.shape[1], axis=0)) ** 2).sum(axis=1).reshape(len(p), -1)
            j = d2.argmin(axis=1)
            rows = np.arange(len(p))
            best[s:s + chunk] = q.reshape(len(p), -1, 3)[rows, j]
            dist[s:s + chunk] = np.sqrt(d2[rows, j])
            face[s:s + chunk] = cand[rows, j]
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
    rs = _Surface(raw) if raw_surface is None else raw_surface
    fv, ff = np.asarray(finished.vertices), np.asarray(finished.faces)
    pts = np.concatenate([fv, fv[ff].mean(axis=1)])
    _, d_out, _ = rs.closest(pts)
    _, d_in, _ = _Surface(finished).closest(raw.vertices)

    def figures(d):
        d = d / voxel_size
        return {"mean_voxels": round(float(d.mean()), 4), "p99_voxels": round(float(np.percentile(d, 99)), 4),
                "max_voxels": round(float(d.max()), 4)}

    a, b = figures(d_out), figures(d_in)
    return {"mean_voxels": max(a["mean_voxels"], b["mean_voxels"]), "max_voxels": max(a["max_voxels"], b["max_voxels"]),
            "finished_to_raw": a, "raw_to_finished": b}
