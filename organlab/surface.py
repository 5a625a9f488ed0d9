"""Surface: marching cubes, mesh measurements and exports.

The voxel model (or a sub-voxel field, see :func:`organlab.carving.hull_field`)
becomes a triangle mesh by scikit-image's Lewiner marching cubes, which
resolves the ambiguous cube configurations so that the surface is closed.
The volume is padded by one empty voxel so the surface also closes where the
specimen touches the roi's faces (the trimesh recipe), faces are oriented
outward, and degenerate faces are not produced.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = ["Mesh", "mesh_from_volume", "mesh_from_field", "measure", "color_vertices", "write_ply", "write_stl", "read_ply"]


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
        v = self.vertices
        a, b, c = v[self.faces[:, 0]], v[self.faces[:, 1]], v[self.faces[:, 2]]
        # centre the coordinates for numerical accuracy
        o = v.mean(axis=0) if len(v) else np.zeros(3)
        return float(np.einsum("ij,ij->i", a - o, np.cross(b - o, c - o)).sum() / 6.0)

    @property
    def area(self):
        """Surface area, mm^2."""
        v = self.vertices
        a, b, c = v[self.faces[:, 0]], v[self.faces[:, 1]], v[self.faces[:, 2]]
        return float(np.linalg.norm(np.cross(b - a, c - a), axis=1).sum() / 2.0)

    def edge_counts(self):
        """Directed-edge bookkeeping: ``(n_boundary, n_nonmanifold, n_misoriented)`` edges."""
        f = self.faces
        if len(f) == 0:
            return 0, 0, 0
        e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
        und = np.sort(e, axis=1)
        key = und[:, 0].astype(np.int64) * (int(f.max()) + 1) + und[:, 1]
        _, inv, counts = np.unique(key, return_inverse=True, return_counts=True)
        boundary = int((counts == 1).sum())
        nonmanifold = int((counts > 2).sum())
        # in an oriented closed surface each undirected edge is used once in each direction
        forward = (e[:, 0] < e[:, 1]).astype(np.int64)
        fwd_per_edge = np.bincount(inv, weights=forward, minlength=len(counts))
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


def mesh_from_volume(volume, grid, *, level=0.5):
    """Closed surface of a voxel model or field by Lewiner marching cubes.

    Parameters
    ----------
    volume : (nx, ny, nz) bool or float
        Occupancy (``True`` inside) or a field whose ``level`` set is the
        surface and which is larger inside; axes x, y, z of ``grid``.
    grid : VoxelGrid
        Where the samples (voxel centres) lie.
    level : float
        Iso-level (0.5 for occupancy and :func:`organlab.carving.hull_field`).

    Returns
    -------
    Mesh
        World frame, mm, faces oriented outward, no degenerate faces.
    """
    from skimage.measure import marching_cubes

    vol = np.asarray(volume)
    if vol.shape != tuple(grid.shape):
        raise ValueError(f"volume shape {vol.shape} does not match the grid {grid.shape}")
    vol = vol.astype(np.float32)
    if not (vol.max() > level):
        raise ValueError("the volume has nothing above the iso-level: the model is empty")
    padded = np.pad(vol, 1, mode="constant", constant_values=min(0.0, float(vol.min())))
    s = grid.voxel_size
    verts, faces, _, _ = marching_cubes(
        padded, level=level, spacing=(s, s, s), method="lewiner", allow_degenerate=False
    )
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
    field : (nx, ny, nz) float32 or bool
        From :func:`organlab.carving.hull_field` (or an occupancy).
    grid : VoxelGrid

    Returns
    -------
    Mesh
        World frame, mm, faces oriented outward.
    """
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


def write_ply(path, mesh):
    """Write a binary little-endian PLY (vertex colours when the mesh has them).

    Parameters
    ----------
    path : str or Path
    mesh : Mesh
    """
    v = np.asarray(mesh.vertices, dtype="<f4")
    f = np.asarray(mesh.faces)
    colors = mesh.vertex_colors
    header = ["ply", "format binary_little_endian 1.0", "comment organlab mesh, world frame, mm", f"element vertex {len(v)}"]
    header += ["property float x", "property float y", "property float z"]
    vdtype = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if colors is not None:
        header += ["property uchar red", "property uchar green", "property uchar blue"]
        vdtype += [("r", "u1"), ("g", "u1"), ("b", "u1")]
    header += [f"element face {len(f)}", "property list uchar int vertex_indices", "end_header"]
    vert = np.empty(len(v), dtype=vdtype)
    vert["x"], vert["y"], vert["z"] = v[:, 0], v[:, 1], v[:, 2]
    if colors is not None:
        c = np.asarray(colors, dtype=np.uint8)
        vert["r"], vert["g"], vert["b"] = c[:, 0], c[:, 1], c[:, 2]
    face = np.empty(len(f), dtype=[("n", "u1"), ("i", "<i4", (3,))])
    face["n"] = 3
    face["i"] = f
    with open(Path(path), "wb") as fh:
        fh.write(("\n".join(header) + "\n").encode("ascii"))
        fh.write(vert.tobytes())
        fh.write(face.tobytes())


def write_stl(path, mesh):
    """Write a binary STL (world frame, mm).

    Parameters
    ----------
    path : str or Path
    mesh : Mesh
    """
    v = np.asarray(mesh.vertices, dtype=np.float64)
    f = np.asarray(mesh.faces)
    tri = v[f]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    n = np.divide(n, norm, out=np.zeros_like(n), where=norm > 0)
    rec = np.zeros(len(f), dtype=[("n", "<f4", (3,)), ("v", "<f4", (3, 3)), ("attr", "<u2")])
    rec["n"] = n
    rec["v"] = tri
    with open(Path(path), "wb") as fh:
        head = b"organlab mesh, world frame, mm"
        fh.write(head.ljust(80, b" "))
        fh.write(np.uint32(len(f)).tobytes())
        fh.write(rec.tobytes())


def read_ply(path):
    """Read a PLY written by :func:`write_ply` (binary little-endian, triangles).

    Returns
    -------
    Mesh
    """
    data = Path(path).read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    header = data[:end].decode("ascii").splitlines()
    nv = nf = 0
    has_color = False
    for line in header:
        parts = line.split()
        if parts[:2] == ["element", "vertex"]:
            nv = int(parts[2])
        elif parts[:2] == ["element", "face"]:
            nf = int(parts[2])
        elif parts[:2] == ["property", "uchar"] and parts[2] == "red":
            has_color = True
    vdtype = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")] + ([("r", "u1"), ("g", "u1"), ("b", "u1")] if has_color else [])
    vert = np.frombuffer(data, dtype=vdtype, count=nv, offset=end)
    off = end + vert.nbytes
    face = np.frombuffer(data, dtype=[("n", "u1"), ("i", "<i4", (3,))], count=nf, offset=off)
    v = np.stack([vert["x"], vert["y"], vert["z"]], axis=1).astype(np.float64)
    c = np.stack([vert["r"], vert["g"], vert["b"]], axis=1) if has_color else None
    return Mesh(v, face["i"].astype(np.int64), c)
