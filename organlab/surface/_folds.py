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
    v, f = mesh.vertices, np.asarray(mesh.faces)
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    n /= np.linalg.norm(n, axis=1, keepdims=True) + 1e-300
    und = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1).astype(np.int64)
    key = und[:, 0] * (len(v) + 1) + und[:, 1]
    order = np.argsort(key, kind="stable")
    fid = np.tile(np.arange(len(f)), 3)[order]
    same = key[order][1:] == key[order][:-1]
    cos = np.einsum("ij,ij->i", n[fid[:-1][same]], n[fid[1:][same]])
    return und[order][:-1][same][cos < np.cos(np.radians(fold_deg))]
