"""The closest-point queries' candidate search (organlab.surface._deviation's centroid grid) finds what the k-d tree of
the centroids it replaced found: the k nearest centroids, nearest first, so the same closest points, distances and faces.

Checked against scipy's cKDTree on meshes the finishing never sees (a sphere's marching-cubes surface, a flat sheet,
a mesh of fewer faces than k) and on points on, near, inside, far outside and beyond the grid's box.
"""

import numpy as np
import pytest
from scipy.spatial import cKDTree

from organlab.mesh import Mesh
from organlab.surface._deviation import _K, _grid_knn, _Surface, _tri_closest


def _expected(mesh, points, k):
    """The k nearest centroids (cKDTree, nearest first) and the distance to the nearest of their faces."""
    v, f = np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64)
    k = min(k, len(f))
    _, cand = cKDTree(v[f].mean(axis=1)).query(points, k=k)
    cand = cand.reshape(len(points), k)
    q = np.stack([_tri_closest(points, v[f[cand[:, j], 0]], v[f[cand[:, j], 1]], v[f[cand[:, j], 2]])
                  for j in range(k)], axis=1)
    return cand, np.linalg.norm(q - points[:, None], axis=2).min(axis=1)


def _sphere():
    from organlab.grid import VoxelGrid
    from organlab.surface import mesh_from_field

    grid = VoxelGrid(origin=(-12.0, -12.0, -12.0), voxel_size=1.0, shape=(25, 25, 25))
    x, y, z = np.meshgrid(*grid.axes(), indexing="ij")
    return mesh_from_field(np.clip(10.5 - np.sqrt(x**2 + y**2 + z**2), 0.0, 1.0), grid)  # its 0.5 level: r = 10 mm


def _sheet():
    n = 20
    x, y = np.meshgrid(np.arange(n, dtype=float), np.arange(n, dtype=float), indexing="ij")
    v = np.stack([x.ravel(), y.ravel(), np.zeros(n * n)], axis=1)
    i = (np.arange(n - 1)[:, None] * n + np.arange(n - 1)[None, :]).ravel()
    f = np.concatenate([np.stack([i, i + n, i + 1], 1), np.stack([i + 1, i + n, i + n + 1], 1)])
    return Mesh(v, f)


def _pair():
    return Mesh(np.array([[0.0, 0, 0], [2, 0, 0], [0, 2, 0], [2, 2, 1]]), np.array([[0, 1, 2], [1, 3, 2]]))


@pytest.mark.parametrize("make", [_sphere, _sheet, _pair])
@pytest.mark.parametrize("k", [_K, 4])
def test_grid_candidates_are_the_kd_trees(make, k):
    mesh = make()
    rng = np.random.default_rng(7)
    v = np.asarray(mesh.vertices)
    lo, hi = v.min(axis=0), v.max(axis=0)
    points = np.concatenate([
        v[rng.integers(0, len(v), 300)] + rng.normal(scale=0.3, size=(300, 3)),  # near the surface
        rng.uniform(lo, hi, size=(200, 3)),  # anywhere in the box (inside the sphere too)
        rng.uniform(lo - 40.0, hi + 40.0, size=(100, 3)),  # far outside the grid
        v[:20],  # the vertices themselves
    ])
    surf = _Surface(mesh)
    q, d, face = surf.closest(points, k=k)
    cand, ed = _expected(mesh, points, k)
    g, kk = surf.tree, cand.shape[1]
    dk, ik = np.empty(kk), np.empty(kk, dtype=np.int64)
    c = np.asarray(mesh.vertices)[np.asarray(mesh.faces)].mean(axis=1)
    same = 0
    for p, want in zip(points, cand):  # the grid's candidates: the tree's, nearest first
        assert _grid_knn(p[0], p[1], p[2], g.gp, g.gface, g.starts, g.lo, g.cell, g.dims, kk, dk, ik) == kk
        # centroids at equal distances (the sheet's lattice) may come in another order, or the k-th be another
        assert np.abs(np.linalg.norm(c[ik] - p, axis=1) - np.linalg.norm(c[want] - p, axis=1)).max() < 1e-12
        same += np.array_equal(ik, want)
    assert same >= 0.9 * len(points)  # measured: all on the sphere and the pair, all but 1-2 of 620 on the sheet
    # the nearest of them (equal distances, on a shared edge or corner, may differ in the last bits: either face)
    assert np.abs(d - ed).max() < 1e-12
    assert np.abs(np.linalg.norm(q - points, axis=1) - d).max() < 1e-12
    assert (face[:, None] == cand).any(axis=1).all()


def test_faces_within_is_a_ball_query_of_the_centroids():
    mesh = _sphere()
    c = np.asarray(mesh.vertices)[np.asarray(mesh.faces)].mean(axis=1)
    seeds = np.array([[10.0, 0.0, 0.0], [0.0, -10.5, 1.0], [30.0, 30.0, 30.0]])
    for r in (0.5, 2.0, 7.0):
        want = np.isfinite(cKDTree(seeds).query(c, distance_upper_bound=r * (1 + 1e-12))[0])
        assert np.array_equal(_Surface(mesh).faces_within(seeds, r), want) and want.any()


def test_chunked_queries_are_one_calls():
    """Queries run in chunks on all cores (``_run_chunks``: a large query, and the deviation's two directions in one
    go) give the single-threaded kernel's values bit for bit: empty, shorter than a chunk, several chunks and a partial
    last one; two meshes in one call."""
    from organlab.surface._deviation import _CHUNK, _closest_kernel, _distances, _run_chunks

    sphere, sheet = _sphere(), _sheet()
    rng = np.random.default_rng(3)
    sets = [(s, rng.normal(scale=8.0, size=(n, 3))) for s, n in
            ((sphere, 0), (sphere, 17), (sheet, 2 * _CHUNK + 5), (sphere, 5 * _CHUNK + 1))]
    queries, outs, refs = [], [], []
    for mesh, pts in sets:
        surf = _Surface(mesh)
        q, out = surf._query(pts)
        if q is not None:
            queries.append(q)
        outs.append(out)
        _, ref = surf._query(pts)
        if len(pts):
            _closest_kernel(np.ascontiguousarray(pts), 0, len(pts), *(q[1][:9] + ref))
        refs.append(ref)
    assert len(queries) == 3
    _run_chunks(queries)
    # no helper thread left alive: one would keep the command from its quick exit (cli._exit_now)
    import threading

    assert not [t for t in threading.enumerate() if t.name.startswith("organlab-closest") and t.is_alive()]
    for out, ref in zip(outs, refs):
        for a, b in zip(out, ref):
            assert np.array_equal(a, b)
    # the deviation's two directions in one call: each the same as its own query
    d_out, d_in = _distances(sheet, sphere, _Surface(sphere))
    fv, ff = np.asarray(sheet.vertices), np.asarray(sheet.faces)
    assert np.array_equal(d_out, _Surface(sphere).closest(np.concatenate([fv, fv[ff].mean(axis=1)]))[1])
    assert np.array_equal(d_in, _Surface(sheet).closest(sphere.vertices)[1])


def test_compiled_sums_are_numpys_to_the_bit():
    """The compiled normal sums (``_Surface.vertex_normal_sums``) and Taubin steps (``smooth_mesh``) give the numpy
    and scipy expressions they replaced bit for bit (bytes compared: -0.0 and 0.0 differ), on a random field's
    surface (ambiguous faces, vertices of every valence) and a sheet with open edges."""
    from scipy import ndimage
    from scipy.sparse import coo_matrix, diags

    from organlab.grid import VoxelGrid
    from organlab.surface import mesh_from_field
    from organlab.surface._repair import _taubin

    f = ndimage.gaussian_filter(np.random.default_rng(5).standard_normal((18, 18, 18)), 1.5)
    blob = mesh_from_field(f / f.std(), VoxelGrid(origin=(0.0, 0.0, 0.0), voxel_size=0.7, shape=(18, 18, 18)))
    for mesh in (blob, _sheet()):
        v, fa = np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64)
        fn = np.cross(v[fa[:, 1]] - v[fa[:, 0]], v[fa[:, 2]] - v[fa[:, 0]])
        want = np.stack([sum(np.bincount(fa[:, i], fn[:, j], len(v)) for i in range(3)) for j in range(3)], axis=1)
        assert want.tobytes() == _Surface(mesh).vertex_normal_sums().tobytes()
        e = np.concatenate([fa[:, [0, 1]], fa[:, [1, 2]], fa[:, [2, 0]]])
        adj = (coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(len(v),) * 2) > 0).astype(np.float64).tocsr()
        adj = ((adj + adj.T) > 0).astype(np.float64)
        w = diags(1.0 / np.maximum(np.asarray(adj.sum(axis=1)).ravel(), 1.0)) @ adj
        a, b = v.copy(), v.copy()
        for _ in range(4):
            a += 0.5 * (w @ a - a)
            a += -0.53 * (w @ a - a)
        _taubin(b, w.indptr, w.indices, w.data, 4, 0.5, -0.53)
        assert a.tobytes() == b.tobytes()
