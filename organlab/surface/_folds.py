"""Folds: spots where the surface turns back on itself, cut out and filled.

Below 1 mm voxels the marching-cubes surface of a visual hull keeps
features of one or two voxels: crevices and lips where a silhouette has a
notch of a pixel or two, and tiny handles (tunnels under a one-voxel
bridge; genus 1 at 0.5 mm and 13 at 0.25 mm on the bundled sample, 0 at
1 and 2 mm).  Taubin smoothing keeps them, and there the surface folds
(neighbouring faces more than 90 degrees apart).  A feature narrower than
the remeshing edge cannot be tiled by well-shaped triangles of that edge,
and isotropic remeshing neither removes a handle nor flattens an edge
sharper than its feature angle, so slivers stayed there (1.7 degrees at
0.5 mm).  The faces within a radius of each fold are removed, the hole is
closed and its patch relaxed by Laplacian smoothing.
"""

from __future__ import annotations

import numpy as np

from ._mesh import Mesh


def fold_edges(mesh, fold_deg):
    """Edges whose two faces' normals differ by more than ``fold_deg``.

    Returns
    -------
    (E, 2) int64
        Vertex indices of the fold edges.
    """
    v, f = mesh.vertices, np.asarray(mesh.faces, dtype=np.int64)
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    n /= np.linalg.norm(n, axis=1, keepdims=True) + 1e-300
    order = mesh._edges()[0].astype(np.int64)  # directed edge i: slot i // F, face i % F
    same = mesh._same_as_next()
    ea, eb = order[:-1][same], order[1:][same]
    F = len(f)
    cos = np.einsum("ij,ij->i", n[ea % F], n[eb % F])
    bad = ea[cos < np.cos(np.radians(fold_deg))]
    return np.sort(np.stack([f[bad % F, bad // F], f[bad % F, (bad // F + 1) % 3]], axis=1), axis=1)


def _laplace(vertices, faces, movable, iterations):
    """Uniform Laplacian smoothing of the ``movable`` vertices; the others stay."""
    from scipy.sparse import coo_matrix, diags

    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    nv = len(vertices)
    a = coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(nv, nv)).tocsr()
    a = ((a + a.T) > 0).astype(np.float64)
    w = diags(1.0 / np.maximum(np.asarray(a.sum(axis=1)).ravel(), 1.0)) @ a
    v = vertices.copy()
    for _ in range(int(iterations)):
        v[movable] = (w @ v)[movable]
    return v


def cut_and_fill(mesh, seeds, radius_mm, *, speck_mm, iterations=20):
    """Remove the faces near ``seeds``, close the holes, relax the patches.

    Parameters
    ----------
    mesh : Mesh
        Closed, manifold; world frame, mm.
    seeds : (S, 3) float64, mm, world frame
    radius_mm : float, mm
        Faces with a vertex closer than this to a seed are removed.
    speck_mm : float, mm
        See :func:`repair_mesh` (pieces the cut isolates are dropped).
    iterations : int
        Laplacian steps of the vertices within 1.5 ``radius_mm`` of a seed.

    Returns
    -------
    Mesh
        The clean-up, or ``mesh`` itself when the result would not be closed
        and manifold.
    int
        Faces removed (0 when ``mesh`` is returned).
    """
    from scipy.spatial import cKDTree

    from ._quality import _moved, mesh_quality
    from ._repair import repair_mesh

    tree = cKDTree(seeds)
    d, _ = tree.query(mesh.vertices)
    keep = ~(d < radius_mm)[mesh.faces].any(axis=1)
    rep, _ = repair_mesh(Mesh(mesh.vertices, mesh.faces[keep]), speck_mm=speck_mm)
    q = mesh_quality(rep)
    if q["boundary_edges"] or q["nonmanifold_edges"] or q["nonmanifold_vertices"]:
        return mesh, 0
    d, _ = tree.query(rep.vertices)
    out = _moved(Mesh(_laplace(rep.vertices, rep.faces, d < 1.5 * radius_mm, iterations), rep.faces), rep)
    return out, int((~keep).sum())
