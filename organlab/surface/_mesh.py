"""The triangle mesh type and marching cubes.

The voxel model (or a sub-voxel field, see :func:`organlab.carving.hull_field`)
becomes a triangle mesh by scikit-image's Lewiner marching cubes, which
resolves the ambiguous cube configurations so that the surface is closed.
The volume is padded by one empty voxel so the surface also closes where the
specimen touches the roi's faces (the trimesh recipe), faces are oriented
outward, and degenerate faces are not produced.  ``method='classic'`` and
``'decider'`` run the teaching implementation of :mod:`._classic_mc`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Mesh", "mesh_from_volume", "mesh_from_field", "measure", "color_vertices"]


@dataclass(frozen=True, eq=False)
class Mesh:
    """A triangle mesh in the world frame.

    Attributes
    ----------
    vertices : (V, 3) float64, mm, world frame
    faces : (F, 3) int64
        Vertex indices, counter-clockwise seen from outside (normals out).
    vertex_colors : (V, 3) uint8 RGB, optional
    """

    vertices: np.ndarray
    faces: np.ndarray
    vertex_colors: np.ndarray | None = None

    @property
    def volume(self):
        """Enclosed volume, mm^3 (signed sum of tetrahedra; > 0 when oriented outward)."""
        cached = self.__dict__.get("_volume")
        if cached is not None:
            return cached
        v = self.vertices
        a, b, c = v[self.faces[:, 0]], v[self.faces[:, 1]], v[self.faces[:, 2]]
        # centre the coordinates for numerical accuracy
        o = v.mean(axis=0) if len(v) else np.zeros(3)
        vol = float(np.einsum("ij,ij->i", a - o, np.cross(b - o, c - o)).sum() / 6.0)
        object.__setattr__(self, "_volume", vol)  # cached: the mesh is immutable
        return vol

    @property
    def area(self):
        """Surface area, mm^2."""
        v = self.vertices
        a, b, c = v[self.faces[:, 0]], v[self.faces[:, 1]], v[self.faces[:, 2]]
        return float(np.linalg.norm(np.cross(b - a, c - a), axis=1).sum() / 2.0)

    def _edges(self):
        """The undirected edges, sorted once (cached: the mesh is immutable).

        Returns ``(order, starts, counts)``: ``order`` sorts the directed edges
        ``f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]`` (stacked: edge ``i`` is slot
        ``i // F`` of face ``i % F``) by their undirected edge; for each distinct
        undirected edge, the position in ``order`` of its first directed edge
        and how many faces use it.  ``order[p]`` and ``order[p + 1]`` are the same
        edge where :meth:`_same_as_next` is True.
        """
        cached = self.__dict__.get("_edge_table")
        if cached is not None:
            return cached
        f = np.asarray(self.faces, dtype=np.int64)
        nv = int(f.max()) + 1 if len(f) else 1
        a = f.T.ravel()  # corners 0 of all faces, then 1, then 2: directed edge i goes a[i] -> b[i]
        b = f[:, [1, 2, 0]].T.ravel()
        key = np.minimum(a, b) * nv + np.maximum(a, b)
        del a, b
        order = np.argsort(key)
        ks = key[order]
        del key
        first = np.ones(len(ks), dtype=bool)
        first[1:] = ks[1:] != ks[:-1]
        del ks
        small = np.int32 if len(first) < 2**31 else np.int64  # half the memory of what stays cached
        starts = np.flatnonzero(first).astype(small)
        counts = np.diff(np.append(starts, len(first))).astype(np.int32)
        table = (order.astype(small), starts, counts)
        object.__setattr__(self, "_edge_table", table)
        return table

    def _same_as_next(self):
        """(3F - 1,) bool: sorted directed edges ``p`` and ``p + 1`` (see :meth:`_edges`) are the same edge."""
        order, starts, _ = self._edges()
        same = np.ones(max(len(order) - 1, 0), dtype=bool)
        same[starts[1:].astype(np.int64) - 1] = False
        return same

    def edge_counts(self):
        """Directed-edge bookkeeping: ``(n_boundary, n_nonmanifold, n_misoriented)`` edges."""
        f = self.faces
        if len(f) == 0:
            return 0, 0, 0
        order, starts, counts = self._edges()
        boundary = int((counts == 1).sum())
        nonmanifold = int((counts > 2).sum())
        # in an oriented closed surface each undirected edge is used once in each direction
        f = np.asarray(f)
        forward = (f.T.ravel() < f[:, [1, 2, 0]].T.ravel()).astype(np.int64)
        fwd_per_edge = np.add.reduceat(forward[order], starts)
        misoriented = int(((counts == 2) & (fwd_per_edge != 1)).sum())
        return boundary, nonmanifold, misoriented

    @property
    def is_watertight(self):
        """Closed, edge-manifold and consistently oriented: every edge is shared by
        exactly two faces that traverse it in opposite directions."""
        return len(self.faces) > 0 and self.edge_counts() == (0, 0, 0)

    @property
    def bounds(self):
        """``(min, max)`` of the vertices, mm, each ``(3,)``."""
        return self.vertices.min(axis=0), self.vertices.max(axis=0)


MC_METHODS = ("lewiner", "decider", "classic")


def mesh_from_volume(volume, grid, *, level=0.5, method="lewiner"):
    """Closed surface of a voxel model or field by marching cubes.

    Parameters
    ----------
    volume : (nx, ny, nz) bool or float
        Occupancy (``True`` inside) or a field whose ``level`` set is the
        surface and which is larger inside; axes x, y, z of ``grid``.
    grid : VoxelGrid
        Where the samples (voxel centres) lie.
    level : float
        Iso-level (0.5 for occupancy and :func:`organlab.carving.hull_field`).
    method : {'lewiner', 'decider', 'classic'}
        ``'lewiner'``: scikit-image's (closed, the default); ``'decider'``:
        the teaching classic marching cubes with the asymptotic decider on
        ambiguous faces (closed); ``'classic'``: the same with the original
        table's rule, which leaves holes at disagreeing ambiguous faces.

    Returns
    -------
    Mesh
        World frame, mm, faces oriented outward (no degenerate faces for
        ``'lewiner'``).
    """
    from skimage.measure import marching_cubes

    if method not in MC_METHODS:
        raise ValueError(f"method must be one of {MC_METHODS}, got {method!r}")
    vol = np.asarray(volume)
    if vol.shape != tuple(grid.shape):
        raise ValueError(f"volume shape {vol.shape} does not match the grid {grid.shape}")
    vol = vol.astype(np.float32)
    if not (vol.max() > level):
        raise ValueError("the volume has nothing above the iso-level: the model is empty")
    padded = np.pad(vol, 1, mode="constant", constant_values=min(0.0, float(vol.min())))
    s = grid.voxel_size
    if method == "lewiner":
        verts, faces, _, _ = marching_cubes(
            padded, level=level, spacing=(s, s, s), method="lewiner", allow_degenerate=False
        )
    else:
        from ._classic_mc import classic_marching_cubes

        verts, faces = classic_marching_cubes(padded, level, decider=method == "decider")
        verts = verts * s
    verts = verts.astype(np.float64) + (np.asarray(grid.origin) - s)
    faces = faces.astype(np.int64)
    mesh = Mesh(verts, faces)
    if mesh.volume < 0:
        mesh = Mesh(verts, faces[:, ::-1].copy())
    return mesh


def mesh_from_field(field, grid):
    """The surface of a hull field or a voxel model: its 0.5 level.

    ``mesh_from_volume(field, grid, level=0.5)``; the level that
    :func:`organlab.carving.hull_field` and occupancy arrays share.

    Parameters
    ----------
    field : (nx, ny, nz) float32 or bool, or BandField
        From :func:`organlab.carving.hull_field` (or an occupancy).  A
        ``BandField`` (``hull_field(..., sparse=True)``) is meshed on its band
        only: the same surface as its dense field's, its vertices in another order.
    grid : VoxelGrid

    Returns
    -------
    Mesh
        World frame, mm, faces oriented outward.
    """
    from ..carving import BandField

    if isinstance(field, BandField):
        return field.mesh()
    return mesh_from_volume(field, grid, level=0.5)


def measure(mesh):
    """The measures of a mesh that ``report.json`` holds.

    Parameters
    ----------
    mesh : Mesh

    Returns
    -------
    dict
        ``volume_mm3`` (enclosed volume, mm^3), ``area_mm2`` (mm^2),
        ``watertight`` (every edge used exactly twice, in opposite directions),
        ``n_vertices``, ``n_faces``, ``bounds_mm`` (``[[xmin, ymin, zmin], [xmax, ymax, zmax]]``).
    """
    if not isinstance(mesh, Mesh):
        raise TypeError(f"mesh must be an organlab.surface.Mesh, got {type(mesh).__name__}")
    lo, hi = mesh.bounds
    return {
        "volume_mm3": float(mesh.volume),
        "area_mm2": float(mesh.area),
        "watertight": bool(mesh.is_watertight),
        "n_vertices": int(len(mesh.vertices)),
        "n_faces": int(len(mesh.faces)),
        "bounds_mm": [np.asarray(lo, float).tolist(), np.asarray(hi, float).tolist()],
    }


def color_vertices(mesh, colors, colored, grid):
    """The mesh with each vertex coloured as its nearest coloured voxel.

    Parameters
    ----------
    mesh : Mesh
    colors : (nx, ny, nz, 3) uint8
        Voxel colours (:func:`organlab.coloring.color_voxels`).
    colored : (nx, ny, nz) bool
        Voxels that got a colour.
    grid : VoxelGrid

    Returns
    -------
    Mesh
        Same vertices and faces, ``vertex_colors`` (V, 3) uint8 (grey 128 when no voxel has a colour).
    """
    from scipy import ndimage

    has = np.asarray(colored, dtype=bool)
    if has.shape != tuple(grid.shape) or np.shape(colors)[:3] != tuple(grid.shape):
        raise ValueError(f"colors {np.shape(colors)} and colored {has.shape} must match the grid {grid.shape}")
    if not has.any():
        return Mesh(mesh.vertices, mesh.faces, np.full((len(mesh.vertices), 3), 128, np.uint8))
    _, idx = ndimage.distance_transform_edt(~has, return_indices=True)
    ijk = np.rint((mesh.vertices - np.asarray(grid.origin)) / grid.voxel_size).astype(int)
    ijk = np.clip(ijk, 0, np.asarray(grid.shape) - 1)
    src = idx[:, ijk[:, 0], ijk[:, 1], ijk[:, 2]]
    return Mesh(mesh.vertices, mesh.faces, np.asarray(colors)[src[0], src[1], src[2]])
