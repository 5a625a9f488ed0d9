"""The triangle mesh: plain data on the ground floor.

Every stage that makes or reads a surface passes a :class:`Mesh`
(:func:`organlab.surface.mesh_from_field` makes it; the agreement check,
the viewer and the writers read it).  Its algorithms live in
:mod:`organlab.surface`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Mesh"]


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
    def volume(self) -> float:
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
    def area(self) -> float:
        """Surface area, mm^2."""
        v = self.vertices
        a, b, c = v[self.faces[:, 0]], v[self.faces[:, 1]], v[self.faces[:, 2]]
        return float(np.linalg.norm(np.cross(b - a, c - a), axis=1).sum() / 2.0)

    def _edges(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The undirected edges, sorted once (cached: the mesh is immutable).

        Returns ``(key, order, starts, counts)``: ``key`` (3F,) int64 of each
        directed edge ``f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]`` (stacked),
        ``order`` the argsort of ``key``, and for each distinct undirected
        edge the position of its first directed edge in ``order`` and how
        many faces use it.
        """
        cached = self.__dict__.get("_edge_table")
        if cached is not None:
            return cached
        f = np.asarray(self.faces, dtype=np.int64)
        nv = int(f.max()) + 1 if len(f) else 1
        a = f.T.ravel()  # corners 0 of all faces, then 1, then 2: directed edge i goes a[i] -> b[i]
        b = f[:, [1, 2, 0]].T.ravel()
        key = np.minimum(a, b) * nv + np.maximum(a, b)
        order = np.argsort(key)
        ks = key[order]
        first = np.ones(len(ks), dtype=bool)
        first[1:] = ks[1:] != ks[:-1]
        starts = np.flatnonzero(first)
        counts = np.diff(np.append(starts, len(ks)))
        table = (key, order, starts, counts)
        object.__setattr__(self, "_edge_table", table)
        return table

    def edge_counts(self) -> tuple[int, int, int]:
        """Directed-edge bookkeeping: ``(n_boundary, n_nonmanifold, n_misoriented)`` edges."""
        f = self.faces
        if len(f) == 0:
            return 0, 0, 0
        key, order, starts, counts = self._edges()
        boundary = int((counts == 1).sum())
        nonmanifold = int((counts > 2).sum())
        # in an oriented closed surface each undirected edge is used once in each direction
        f = np.asarray(f)
        forward = (f.T.ravel() < f[:, [1, 2, 0]].T.ravel()).astype(np.int64)
        fwd_per_edge = np.add.reduceat(forward[order], starts)
        misoriented = int(((counts == 2) & (fwd_per_edge != 1)).sum())
        return boundary, nonmanifold, misoriented

    @property
    def is_watertight(self) -> bool:
        """Closed, edge-manifold and consistently oriented: every edge is shared by
        exactly two faces that traverse it in opposite directions."""
        return len(self.faces) > 0 and self.edge_counts() == (0, 0, 0)

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """``(min, max)`` of the vertices, mm, each ``(3,)``."""
        return self.vertices.min(axis=0), self.vertices.max(axis=0)
