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
from typing import Literal

import numpy as np

from ..bandfield import BandField
from ..grid import VoxelGrid
from ..mesh import Mesh
from ._bandmesh import band_mesh, tie_level, untie
from ._classic_mc import classic_marching_cubes

__all__ = ["Mesh", "mesh_from_volume", "mesh_from_field", "measure", "color_vertices"]


MC_METHODS = ("lewiner", "decider", "classic")


def mesh_from_volume(volume: np.ndarray, grid: VoxelGrid, *, level: float = 0.5,
                     method: Literal["lewiner", "decider", "classic"] = "lewiner") -> Mesh:
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
    origin = np.asarray(grid.origin) - s
    for lev in (level, tie_level(level)):
        if method == "lewiner":
            verts, faces, _, _ = marching_cubes(  # samples exactly at the level would leave holes: see untie
                untie(padded, lev), level=lev, spacing=(s, s, s), method="lewiner", allow_degenerate=False
            )
        else:
            verts, faces = classic_marching_cubes(padded, level, decider=method == "decider")
            verts = verts * s
        mesh = Mesh(verts.astype(np.float64) + origin, faces.astype(np.int64))
        if mesh.volume < 0:
            mesh = Mesh(mesh.vertices, mesh.faces[:, ::-1].copy())
        if method != "lewiner" or not mesh.edge_counts()[1]:  # else a saddle exactly at the level: see TIE_LEVEL
            break
    return mesh


def mesh_from_field(field: np.ndarray | BandField, grid: VoxelGrid) -> Mesh:
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

    Examples
    --------
    >>> import numpy as np
    >>> import organlab as ol
    >>> grid = ol.VoxelGrid(origin=(-24.0, -24.0, -24.0), voxel_size=2.0, shape=(25, 25, 25))
    >>> x, y, z = np.meshgrid(*grid.axes(), indexing="ij")
    >>> ball = x**2 + y**2 + z**2 <= 20.0**2  # a sphere of radius 20 mm: 33 510 mm^3
    >>> mesh = ol.mesh_from_field(ball, grid)  # an occupancy or a hull field (dense or BandField)
    >>> mesh.is_watertight, round(mesh.volume)
    (True, 33183)
    """
    if isinstance(field, BandField):
        return band_mesh(field)
    return mesh_from_volume(field, grid, level=0.5)


@dataclass(frozen=True)
class MeshMeasures:
    """What :func:`measure` measured of a mesh (world frame, mm).

    Attributes
    ----------
    volume_mm3 : float
        Enclosed volume, mm^3.
    area_mm2 : float
        Surface area, mm^2.
    watertight : bool
        Every edge used exactly twice, in opposite directions.
    n_vertices, n_faces : int
    bounds_mm : (2, 3) list of float
        ``[[xmin, ymin, zmin], [xmax, ymax, zmax]]``.
    """

    volume_mm3: float
    area_mm2: float
    watertight: bool
    n_vertices: int
    n_faces: int
    bounds_mm: list

    def to_dict(self) -> dict:
        """The JSON-ready dict that ``report.json`` holds (the attributes by name)."""
        return {"volume_mm3": self.volume_mm3, "area_mm2": self.area_mm2, "watertight": self.watertight,
                "n_vertices": self.n_vertices, "n_faces": self.n_faces,
                "bounds_mm": [list(self.bounds_mm[0]), list(self.bounds_mm[1])]}


def measure(mesh: Mesh) -> MeshMeasures:
    """The measures of a mesh that ``report.json`` holds.

    Parameters
    ----------
    mesh : Mesh

    Returns
    -------
    MeshMeasures
        ``volume_mm3`` (enclosed volume, mm^3), ``area_mm2`` (mm^2),
        ``watertight`` (every edge used exactly twice, in opposite directions),
        ``n_vertices``, ``n_faces``, ``bounds_mm`` (``[[xmin, ymin, zmin], [xmax, ymax, zmax]]``);
        ``.to_dict()`` for JSON.

    Examples
    --------
    >>> import numpy as np
    >>> import organlab as ol
    >>> grid = ol.VoxelGrid(origin=(-24.0, -24.0, -24.0), voxel_size=2.0, shape=(25, 25, 25))
    >>> x, y, z = np.meshgrid(*grid.axes(), indexing="ij")
    >>> ball = x**2 + y**2 + z**2 <= 20.0**2  # a sphere of radius 20 mm: 33 510 mm^3
    >>> m = ol.measure(ol.finish_surface(ol.mesh_from_field(ball, grid), voxel_size=2.0).mesh)
    >>> round(m.volume_mm3), round(m.area_mm2), m.watertight  # the sphere: 33 510 mm^3, 5 027 mm^2
    (33297, 5054, True)
    """
    if not isinstance(mesh, Mesh):
        raise TypeError(f"mesh must be an organlab.surface.Mesh, got {type(mesh).__name__}")
    lo, hi = mesh.bounds
    return MeshMeasures(float(mesh.volume), float(mesh.area), bool(mesh.is_watertight), int(len(mesh.vertices)),
                        int(len(mesh.faces)), [np.asarray(lo, float).tolist(), np.asarray(hi, float).tolist()])


def color_vertices(mesh: Mesh, colors: np.ndarray, colored: np.ndarray, grid: VoxelGrid) -> Mesh:
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
