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
closed and its patch relaxed by Laplacian smoothing (``cut_and_fill`` in
:mod:`._repair`, beside the repair it runs).

Since issue 21 this runs only on the pymeshlab path (an open surface,
``repair=False``) and as the last resort for faces the adaptive remesher's
clean-up leaves below the smallest angle: cutting folds out was the main
loss of the dino's thin parts (11 voxels).  The adaptive remesher
(:mod:`._remesh`) tiles folds with edges down to 0.35 voxel instead.
"""

from __future__ import annotations

import numpy as np


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
