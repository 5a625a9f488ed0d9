"""How far one surface lies from another: closest points on a triangle mesh (numpy, scipy and one numba kernel).

:func:`closest_points` finds, for each query point, the nearest point of a mesh among the
triangles whose centroids are nearest to it (a uniform grid of the centroids, numba); :func:`surface_deviation`
measures a finished surface against the raw marching-cubes one both ways (the finished surface's
vertices and face centres to the raw surface, the raw vertices to the finished one), so a thin part
the finishing shaved off shows as well as a bump it added.
"""

from __future__ import annotations

import math
import os

import numpy as np
from numba import njit

import weakref

from ..mesh import Mesh
from ._geom import _centroid, _normal3

_SURFACES = weakref.WeakKeyDictionary()

#: Candidate triangles per query point (by centroid distance).  Marching-cubes and remeshed triangles
#: are within a factor of a few of one size, so the nearest triangle is nearly always among the nearest
#: centroids: measured on the 1 mm dino's marching-cubes mesh against a brute-force search over all
#: 57 442 faces, 300 points scattered 0.7 mm about it: k = 8 misses 2 by at most 0.0017 mm, k = 6 3 by
#: 0.014 mm, k = 4 9 by 0.099 mm.  The figures of a finished 1 mm sample are the same at 4, 6 and 8
#: (0.0324 / 0.7063 voxels); the candidate search is most of the time (0.10 s at 4, 0.14 s at 8, k-d tree).
_K = 6

#: Queries of at least this many points run on all cores (threads cost more below), in chunks of this many points
#: that each thread takes in turn (:func:`_run_chunks`).
_PARALLEL = 20_000
_CHUNK = 2048


#: The centroid grid's cell edge, in mean edge lengths of the mesh's faces, and at most this many cells per face
#: (its offsets, 8 bytes a cell).  Measured on the sample's raw surfaces (k = 6, points 0.3 edge about the
#: vertices; the k-d tree's same candidates, in the same order; on a lattice, centroids at equal distances may
#: come in another order): 1 mm 0.028 s against 0.055 s, 0.25 mm (0.93 M
#: faces, capped at 2 cells a face: 2.6 edges) 0.43 s against 0.93 s, cells of 1.5-3 edges within 10 %.
_CELL_EDGES, _CELLS_PER_FACE = 2.0, 2.0


@njit(cache=True, nogil=True)
def _grid_build(v, f, lo, cell, dims, gp, gface, starts):
    """Bucket the centroids of faces ``f`` into the cells (counting sort; each cell's faces ascending)."""
    nf = f.shape[0]
    ny, nz = dims[1], dims[2]
    cid = np.empty(nf, dtype=np.int64)
    cen = np.empty((nf, 3))
    starts[:] = 0
    for t in range(nf):
        a, b, c = f[t, 0], f[t, 1], f[t, 2]
        for k in range(3):
            cen[t, k] = _centroid(v, a, b, c, k)  # as numpy's v[f].mean(axis=1)
        i = min(max(int(math.floor((cen[t, 0] - lo[0]) / cell)), 0), dims[0] - 1)
        j = min(max(int(math.floor((cen[t, 1] - lo[1]) / cell)), 0), ny - 1)
        k_ = min(max(int(math.floor((cen[t, 2] - lo[2]) / cell)), 0), nz - 1)
        cid[t] = (i * ny + j) * nz + k_
        starts[cid[t] + 1] += 1
    for c in range(starts.shape[0] - 1):
        starts[c + 1] += starts[c]
    pos = starts[:-1].copy()
    for t in range(nf):
        q = pos[cid[t]]
        pos[cid[t]] += 1
        gp[q, 0], gp[q, 1], gp[q, 2] = cen[t, 0], cen[t, 1], cen[t, 2]
        gface[q] = t


@njit(cache=True, nogil=True)
def _grid_knn(px, py, pz, gp, gface, starts, lo, cell, dims, k, dk, ik):
    """The ``k`` centroids nearest to ``(px, py, pz)`` into ``ik`` (faces), nearest first, their squared distances
    into ``dk``; returns how many (fewer than ``k`` only for a mesh of fewer faces).

    Shells of cells about the point's cell (clamped into the grid), each cell skipped when it lies farther than
    the ``k``-th candidate so far; done when the next shell (at least ``s`` cells plus the point's distance to its
    cell's walls away) is farther than it too.  A slab of cells (one ``a``, or one ``a`` and ``b``) farther than
    that candidate along its own axes is skipped whole, and an empty cell before its distance is computed: the
    same cells are read, in the same order (so the same candidates, ties in the same order), with fewer tests
    (the 1 mm sample's nine queries of a finishing, 121 k points, the search alone: 78-87 -> 70-75 ms, the same
    faces and distances; the whole closest-point kernel 146-153 -> 145-150 ms, within the noise).
    """
    nx, ny, nz = dims[0], dims[1], dims[2]
    fx, fy, fz = (px - lo[0]) / cell, (py - lo[1]) / cell, (pz - lo[2]) / cell
    cx = min(max(int(math.floor(fx)), 0), nx - 1)
    cy = min(max(int(math.floor(fy)), 0), ny - 1)
    cz = min(max(int(math.floor(fz)), 0), nz - 1)
    m = np.inf  # the point's distance to its cell's walls (0 where it lies outside the grid)
    for f_, c_ in ((fx, cx), (fy, cy), (fz, cz)):
        if c_ <= f_ < c_ + 1:
            m = min(m, min(f_ - c_, c_ + 1 - f_))
        else:
            m = 0.0
    m *= cell
    smax = max(nx, max(ny, nz))
    n = 0
    s = 0
    while True:
        for a in range(max(cx - s, 0), min(cx + s, nx - 1) + 1):
            ea = a == cx - s or a == cx + s
            bx = max(0.0, max(lo[0] + a * cell - px, px - (lo[0] + (a + 1) * cell)))
            gx = bx * bx
            if n == k and gx > dk[k - 1]:
                continue
            for b in range(max(cy - s, 0), min(cy + s, ny - 1) + 1):
                step = 1 if (ea or b == cy - s or b == cy + s) else 2 * s
                by = max(0.0, max(lo[1] + b * cell - py, py - (lo[1] + (b + 1) * cell)))
                gxy = gx + by * by
                if n == k and gxy > dk[k - 1]:
                    continue
                row = (a * ny + b) * nz
                c = cz - s
                while c <= cz + s:
                    if 0 <= c < nz:
                        cid = row + c
                        q0, q1 = starts[cid], starts[cid + 1]
                        if q0 < q1:
                            go = n < k
                            if not go:
                                bz = max(0.0, max(lo[2] + c * cell - pz, pz - (lo[2] + (c + 1) * cell)))
                                go = gxy + bz * bz <= dk[k - 1]
                            if go:
                                for q in range(q0, q1):
                                    dx, dy, dz = gp[q, 0] - px, gp[q, 1] - py, gp[q, 2] - pz
                                    d = dx * dx + dy * dy + dz * dz
                                    if n < k:
                                        j = n
                                        n += 1
                                    elif d < dk[k - 1]:
                                        j = k - 1
                                    else:
                                        continue
                                    while j > 0 and dk[j - 1] > d:
                                        dk[j] = dk[j - 1]
                                        ik[j] = ik[j - 1]
                                        j -= 1
                                    dk[j] = d
                                    ik[j] = gface[q]
                    if step == 0:
                        break
                    c += step
        if n == k:
            r = s * cell + m
            if dk[k - 1] <= r * r:
                break
        if s > smax:
            break
        s += 1
    return n


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
def _closest_kernel(points, i0, i1, v, f, gp, gface, starts, lo, cell, dims, k, best, dist, face):
    """For points ``i0:i1``, the closest point over their ``k`` candidate triangles (those of the nearest centroids,
    :func:`_grid_knn`, nearest first; Ericson's regions, one triangle at a time)."""
    dk = np.empty(k)
    ik = np.empty(k, dtype=np.int64)
    for i in range(i0, i1):
        px, py, pz = points[i, 0], points[i, 1], points[i, 2]
        dbest = np.inf
        nc = _grid_knn(px, py, pz, gp, gface, starts, lo, cell, dims, k, dk, ik)
        for j in range(nc):
            t = ik[j]
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


@njit(cache=True, nogil=True)
def _within(seeds, r, gp, gface, starts, lo, cell, dims, out):
    """``out[t]`` True for the faces whose centroids lie within ``r`` of a seed."""
    nx, ny, nz = dims[0], dims[1], dims[2]
    r2 = r * r
    for i in range(seeds.shape[0]):
        px, py, pz = seeds[i, 0], seeds[i, 1], seeds[i, 2]
        a0 = max(int(math.floor((px - r - lo[0]) / cell)), 0)
        a1 = min(int(math.floor((px + r - lo[0]) / cell)), nx - 1)
        b0 = max(int(math.floor((py - r - lo[1]) / cell)), 0)
        b1 = min(int(math.floor((py + r - lo[1]) / cell)), ny - 1)
        c0 = max(int(math.floor((pz - r - lo[2]) / cell)), 0)
        c1 = min(int(math.floor((pz + r - lo[2]) / cell)), nz - 1)
        for a in range(a0, a1 + 1):
            for b in range(b0, b1 + 1):
                for c in range(c0, c1 + 1):
                    cid = (a * ny + b) * nz + c
                    for q in range(starts[cid], starts[cid + 1]):
                        dx, dy, dz = gp[q, 0] - px, gp[q, 1] - py, gp[q, 2] - pz
                        if dx * dx + dy * dy + dz * dz <= r2:
                            out[gface[q]] = True


@njit(cache=True, nogil=True)
def _normal_sums(v, f):
    """Each vertex's sum of its faces' cross products ``(V, 3)``: ``sum(np.bincount(f[:, i], fn[:, j]) for i in
    range(3))`` per component ``j`` of ``fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])``, the
    same operations in the same order (a sum per corner over the faces in order, then the corners' sums from 0):
    the same bits, in one pass without the (F, 3) temporaries."""
    nv = v.shape[0]
    acc = np.zeros((3, nv, 3))
    for t in range(f.shape[0]):
        a, b, c = f[t, 0], f[t, 1], f[t, 2]
        nx, ny, nz = _normal3(v[a, 0], v[a, 1], v[a, 2], v[b, 0], v[b, 1], v[b, 2], v[c, 0], v[c, 1], v[c, 2])
        for i in range(3):
            acc[i, f[t, i], 0] += nx
            acc[i, f[t, i], 1] += ny
            acc[i, f[t, i], 2] += nz
    out = np.empty((nv, 3))
    for q in range(nv):
        for j in range(3):
            out[q, j] = ((0.0 + acc[0, q, j]) + acc[1, q, j]) + acc[2, q, j]
    return out


class _Grid:
    """The faces' centroids bucketed into a uniform grid of cubes (:data:`_CELL_EDGES`)."""

    def __init__(self, v, f):
        nf = len(f)
        c = v[f[:, 0]]  # the centroids' box is within the vertices' box; the cells are clamped anyway
        lo, hi = (v.min(axis=0), v.max(axis=0)) if len(v) else (np.zeros(3), np.zeros(3))
        edge = float(np.linalg.norm(v[f[:, 1]] - c, axis=1).mean()) if nf else 1.0
        span = np.maximum(hi - lo, 1e-9)
        cell = max(_CELL_EDGES * edge, float(np.cbrt(np.prod(span) / max(_CELLS_PER_FACE * nf, 1.0))), 1e-9)
        dims = np.floor(span / cell).astype(np.int64) + 1
        while dims.prod() > _CELLS_PER_FACE * nf + 64:  # flat boxes: the volume bound above is not enough
            cell *= 1.25
            dims = np.floor(span / cell).astype(np.int64) + 1
        self.lo, self.cell, self.dims = lo.astype(np.float64), float(cell), dims
        self.gp, self.gface = np.empty((nf, 3)), np.empty(nf, dtype=np.int64)
        self.starts = np.empty(int(dims.prod()) + 1, dtype=np.int64)
        _grid_build(v, f, self.lo, self.cell, dims, self.gp, self.gface, self.starts)


def _run_chunks(queries):
    """Run :func:`_closest_kernel` over ``queries`` (``(points, args)`` pairs) in chunks of :data:`_CHUNK` points
    that this thread and helper threads (all cores but this one's, at most 3) take in turn until none is left.

    The same kernel on the same points, so the same values as one call; taken in turn rather than cut in equal
    shares, so a thread slowed by another's work beside it (the AAA measures beside the finishing, 2 cores) takes
    fewer chunks instead of being waited for.  The helpers are daemon threads that end with the call: a thread
    left alive would keep ``organlab``'s command from its quick exit (``cli._exit_now``: 0.5-1.3 s of teardown).
    """
    import itertools
    import threading

    chunks = [(q, i, min(i + _CHUNK, len(q[0]))) for q in queries for i in range(0, len(q[0]), _CHUNK)]
    turn = itertools.count()  # next() on it is atomic under the GIL
    failed = []

    def drain():
        try:
            while (c := next(turn)) < len(chunks):
                (points, args), i0, i1 = chunks[c]
                _closest_kernel(points, i0, i1, *args)
        except BaseException as e:  # noqa: BLE001 (raised in the calling thread below)
            failed.append(e)

    n = min(max(1, min(os.cpu_count() or 1, 4) - 1), len(chunks) - 1)
    helpers = [threading.Thread(target=drain, name="organlab-closest", daemon=True) for _ in range(n)]
    for h in helpers:
        h.start()
    drain()
    for h in helpers:
        h.join()
    if failed:
        raise failed[0]


def _surface(mesh):
    """The :class:`_Surface` of ``mesh``, built once per mesh (meshes are immutable)."""
    got = _SURFACES.get(mesh)
    if got is None:
        got = _SURFACES[mesh] = _Surface(mesh)
    return got


class _Surface:
    """A mesh prepared for closest-point queries (its centroid grid built once)."""

    def __init__(self, mesh, tree=None):
        self.v = np.ascontiguousarray(mesh.vertices, dtype=np.float64)
        self.f = np.ascontiguousarray(mesh.faces, dtype=np.int64)
        # ``tree``: the centroid grid of a mesh with these faces and vertices at most a rounding apart (it
        # only picks the candidate faces; the distances are this mesh's own)
        self.tree = _Grid(self.v, self.f) if tree is None else tree
        self.k = min(_K, len(self.f))
        self._vertex_normals = None

    def vertex_normal_sums(self):
        """Area-weighted normals ``(V, 3)`` of the vertices (not normalized; computed once, one bincount per corner
        and component: 1 mm sample, 57 724 faces, about 10 ms)."""
        if self._vertex_normals is None:
            self._vertex_normals = _normal_sums(self.v, self.f)
        return self._vertex_normals

    def closest(self, points, k=None):
        """``(closest (N, 3), distance (N,), face (N,))`` for ``points`` ``(N, 3)`` (among ``k`` candidate faces)."""
        query, out = self._query(points, k)
        if query is not None:
            if len(query[0]) < _PARALLEL:
                _closest_kernel(query[0], 0, len(query[0]), *query[1])
            else:  # all cores for the large queries (the remesher's relaxations, the deviation), as the k-d tree's did
                _run_chunks([query])
        return out

    def _query(self, points, k=None):
        """``((points, kernel arguments) or None when there is nothing to do, (closest, distance, face))``: a query
        for :func:`_closest_kernel` or :func:`_run_chunks`, and the arrays it fills."""
        points = np.ascontiguousarray(points, dtype=np.float64)
        n = len(points)
        best, dist, face = np.empty((n, 3)), np.empty(n), np.empty(n, dtype=np.int64)
        k = self.k if k is None else min(k, len(self.f))
        g = self.tree
        args = (self.v, self.f, g.gp, g.gface, g.starts, g.lo, g.cell, g.dims, k, best, dist, face)
        return ((points, args) if n and k else None), (best, dist, face)

    def faces_within(self, seeds, radius):
        """``(F,)`` bool: the faces whose centroids lie within ``radius`` (mm) of one of ``seeds`` ``(S, 3)``."""
        g, out = self.tree, np.zeros(len(self.f), dtype=bool)
        _within(np.ascontiguousarray(seeds, dtype=np.float64).reshape(-1, 3), float(radius), g.gp, g.gface, g.starts,
                g.lo, g.cell, g.dims, out)
        return out


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

    Up to :data:`_SIDE_BY_SIDE` raw vertices the second direction (``finished``'s grid built, then queried) runs
    in a second thread while this one queries ``rs``: the same calls, so the same distances; both release the GIL
    (the grid's build and the query kernels).  The 1 mm sample: 31 403 and 28 864 points, about 0.05 and 0.04 s
    CPU, the last step of the viewer's full update, when the AAA measures beside it are done.
    """
    fv, ff = np.asarray(finished.vertices), np.asarray(finished.faces)
    pts = np.concatenate([fv, fv[ff].mean(axis=1)])
    if len(raw.vertices) > _SIDE_BY_SIDE:
        _, d_out, _ = rs.closest(pts)
        _, d_in, _ = _Surface(finished).closest(raw.vertices)
        return d_out, d_in
    q_out, (_, d_out, _) = rs._query(pts)
    q_in, (_, d_in, _) = _Surface(finished)._query(raw.vertices)
    _run_chunks([q for q in (q_out, q_in) if q is not None])
    return d_out, d_in


def _deviation_figures(d_out, d_in, voxel_size):
    def figures(d):
        d = d / voxel_size
        return {"mean_voxels": round(float(d.mean()), 4), "p99_voxels": round(float(np.percentile(d, 99)), 4),
                "max_voxels": round(float(d.max()), 4)}

    a, b = figures(d_out), figures(d_in)
    return {"mean_voxels": max(a["mean_voxels"], b["mean_voxels"]), "max_voxels": max(a["max_voxels"], b["max_voxels"]),
            "finished_to_raw": a, "raw_to_finished": b}
