"""Masks of a model seen by a camera: one projection and raster for meshes and voxel models.

:func:`model_mask` gives the pixels whose centre sees a mesh or a voxel model
through a :class:`~organlab.camera.Camera` (the full camera model at the
vertices, straight edges between them): the agreement check compares it
with the silhouettes, the automatic colour threshold with the hull's, the
tests with the photographs' masks.  :func:`fill_triangles` and
:func:`voxel_boundary_quads` are its two steps.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numba import njit

from .camera import Camera
from .grid import VoxelGrid
from .nbcam import pack_camera, to_camera, to_pixel

__all__ = ["model_mask", "MeshRaster", "fill_triangles", "voxel_boundary_quads"]


@njit(cache=True, nogil=True)
def _fill(uv, faces, out):
    h, w = out.shape
    for f in range(faces.shape[0]):
        a, b, c = faces[f, 0], faces[f, 1], faces[f, 2]
        ax, ay = uv[a, 0], uv[a, 1]
        bx, by = uv[b, 0], uv[b, 1]
        cx, cy = uv[c, 0], uv[c, 1]
        if not (math.isfinite(ax) and math.isfinite(ay) and math.isfinite(bx)):
            continue
        if not (math.isfinite(by) and math.isfinite(cx) and math.isfinite(cy)):
            continue
        area = (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)
        if area == 0.0:
            continue
        sgn = 1.0 if area > 0 else -1.0
        c0 = max(int(math.ceil(min(ax, bx, cx))), 0)
        c1 = min(int(math.floor(max(ax, bx, cx))), w - 1)
        r0 = max(int(math.ceil(min(ay, by, cy))), 0)
        r1 = min(int(math.floor(max(ay, by, cy))), h - 1)
        for r in range(r0, r1 + 1):
            for col in range(c0, c1 + 1):
                e0 = sgn * ((bx - ax) * (r - ay) - (by - ay) * (col - ax))
                e1 = sgn * ((cx - bx) * (r - by) - (cy - by) * (col - bx))
                e2 = sgn * ((ax - cx) * (r - cy) - (ay - cy) * (col - cx))
                if e0 >= 0.0 and e1 >= 0.0 and e2 >= 0.0:
                    out[r, col] = True


@njit(cache=True, nogil=True)
def _project(verts, cp, uv, z):
    """``Camera.project`` of every vertex (the same operations, organlab.nbcam): pixels into ``uv``, depth into ``z``."""
    for i in range(verts.shape[0]):
        xc, yc, zc = to_camera(cp, verts[i, 0], verts[i, 1], verts[i, 2])
        z[i] = zc
        if zc > 0.0:
            uv[i, 0], uv[i, 1] = to_pixel(cp, xc / zc, yc / zc)
        else:
            uv[i, 0] = uv[i, 1] = np.nan


@njit(cache=True, nogil=True)
def _front_faces(faces, z):
    """The faces whose three vertices lie in front of the camera plane."""
    keep = np.empty(faces.shape[0], dtype=np.bool_)
    for f in range(faces.shape[0]):
        keep[f] = z[faces[f, 0]] > 0.0 and z[faces[f, 1]] > 0.0 and z[faces[f, 2]] > 0.0
    return keep


class MeshRaster:
    """A mesh prepared once for :func:`model_mask` in many cameras (its arrays converted once).

    :meth:`mask` may run on several threads at once (its kernels release the GIL; each call has
    its own buffers).

    Parameters
    ----------
    vertices : (V, 3) float, mm, world frame
    faces : (F, 3) int

    Examples
    --------
    >>> import numpy as np
    >>> from organlab.camera import Camera
    >>> from organlab.raster import MeshRaster
    >>> cam = Camera(np.array([[100.0, 0, 32], [0, 100.0, 24], [0, 0, 1]]), np.zeros(5),
    ...              np.eye(3), np.array([0.0, 0.0, 100.0]), image_size=(64, 48))
    >>> square = MeshRaster(np.array([[-5.0, -5, 0], [5, -5, 0], [5, 5, 0], [-5, 5, 0]]), np.array([[0, 1, 2], [0, 2, 3]]))
    >>> int(square.mask(cam, (48, 64)).sum())  # 10 mm at 100 mm: 10 px a side, edges included
    121
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray) -> None:
        self.verts = np.ascontiguousarray(vertices, dtype=np.float64).reshape(-1, 3)
        self.faces = np.ascontiguousarray(faces, dtype=np.int64).reshape(-1, 3)

    def mask(self, camera: Camera, shape: tuple[int, int]) -> np.ndarray:
        """Pixels whose centre sees the mesh (as :func:`model_mask`), ``shape`` bool."""
        out = np.zeros(tuple(int(s) for s in shape), dtype=np.bool_)
        if len(self.faces) == 0:
            return out
        uv, z = np.empty((len(self.verts), 2)), np.empty(len(self.verts))
        _project(self.verts, pack_camera(camera), uv, z)
        keep = _front_faces(self.faces, z)
        faces = self.faces if keep.all() else np.ascontiguousarray(self.faces[keep])
        _fill(uv, faces, out)
        return out


def fill_triangles(uv: np.ndarray, faces: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Pixels whose centre lies in any of the triangles (closed), ``(H, W)`` bool.

    Parameters
    ----------
    uv : (V, 2) float64, px
        Projected vertices; triangles with a NaN vertex are skipped.
    faces : (F, 3) int
    shape : (H, W)
    """
    out = np.zeros(tuple(int(s) for s in shape), dtype=np.bool_)
    if len(faces):
        _fill(np.ascontiguousarray(uv, dtype=np.float64), np.ascontiguousarray(faces, dtype=np.int64), out)
    return out


def voxel_boundary_quads(occupancy: np.ndarray, grid: VoxelGrid) -> tuple[np.ndarray, np.ndarray]:
    """The faces between occupied and empty voxels, as triangles.

    Parameters
    ----------
    occupancy : grid.shape bool
    grid : VoxelGrid

    Returns
    -------
    vertices : (V, 3) float64, mm, world frame
        Voxel corners used by the faces.
    triangles : (2 * n_faces, 3) int64
    """
    occ = np.asarray(occupancy, dtype=bool)
    nx, ny, nz = occ.shape
    P = np.pad(occ, 1)
    quads = []

    def vid(i, j, k):
        return (i * (ny + 1) + j) * (nz + 1) + k

    # x faces: plane i between voxels i - 1 and i
    i, j, k = np.nonzero(P[1:, 1:-1, 1:-1] != P[:-1, 1:-1, 1:-1])
    quads.append(np.stack([vid(i, j, k), vid(i, j + 1, k), vid(i, j + 1, k + 1), vid(i, j, k + 1)], axis=1))
    i, j, k = np.nonzero(P[1:-1, 1:, 1:-1] != P[1:-1, :-1, 1:-1])
    quads.append(np.stack([vid(i, j, k), vid(i + 1, j, k), vid(i + 1, j, k + 1), vid(i, j, k + 1)], axis=1))
    i, j, k = np.nonzero(P[1:-1, 1:-1, 1:] != P[1:-1, 1:-1, :-1])
    quads.append(np.stack([vid(i, j, k), vid(i + 1, j, k), vid(i + 1, j + 1, k), vid(i, j + 1, k)], axis=1))
    q = np.concatenate(quads).astype(np.int64)
    used, inv = np.unique(q, return_inverse=True)
    q = inv.reshape(q.shape)
    kk = used % (nz + 1)
    jj = (used // (nz + 1)) % (ny + 1)
    ii = used // ((nz + 1) * (ny + 1))
    lo = grid.bounds[0]
    verts = lo + grid.voxel_size * np.stack([ii, jj, kk], axis=1).astype(np.float64)
    tris = np.concatenate([q[:, [0, 1, 2]], q[:, [0, 2, 3]]])
    return verts, tris


def model_mask(model: Any, camera: Camera, shape: tuple[int, int] | None = None, *,
               grid: VoxelGrid | None = None) -> np.ndarray:
    """Pixels whose centre sees a mesh or a voxel model through a camera: the model's silhouette.

    Parameters
    ----------
    model : organlab.mesh.Mesh or (nx, ny, nz) bool
        A closed mesh (mm, world frame): every triangle is projected and
        filled.  Or an occupancy on ``grid``: the faces between occupied and
        empty voxels (and the grid's outer faces) are projected and filled,
        i.e. the union of the projected voxel boxes.
    camera : organlab.camera.Camera
    shape : (2,) int, optional
        ``(H, W)`` of the image; default the camera's ``image_size``
        reversed.
    grid : VoxelGrid, optional
        Needed with an occupancy.

    Returns
    -------
    (H, W) bool
        Triangles with a vertex on or behind the camera plane are left out.

    Raises
    ------
    ValueError
        If an occupancy comes without ``grid`` or does not match it.

    Examples
    --------
    >>> import numpy as np
    >>> from organlab.camera import Camera
    >>> from organlab.grid import VoxelGrid
    >>> from organlab.raster import model_mask
    >>> cam = Camera(np.array([[100.0, 0, 32], [0, 100.0, 24], [0, 0, 1]]), np.zeros(5),
    ...              np.eye(3), np.array([0.0, 0.0, 100.0]), image_size=(64, 48))
    >>> grid = VoxelGrid(origin=(-5.0, -5.0, -5.0), voxel_size=1.0, shape=(10, 10, 10))
    >>> m = model_mask(np.ones(grid.shape, bool), cam, grid=grid)   # a 10 mm cube, 95-105 mm away
    >>> m.shape, int(m.sum())                                       # about 1 px per mm there
    ((48, 64), 100)
    """
    if shape is None:
        w, h = camera.image_size
        shape = (h, w)
    if hasattr(model, "vertices") and hasattr(model, "faces"):
        return MeshRaster(model.vertices, model.faces).mask(camera, shape)
    else:
        if grid is None:
            raise ValueError("an occupancy model needs grid=")
        occ = np.asarray(model, dtype=bool)
        if occ.shape != tuple(grid.shape):
            raise ValueError(f"occupancy shape {occ.shape} does not match the grid {tuple(grid.shape)}")
        verts, faces = voxel_boundary_quads(occ, grid)
    if len(faces) == 0:
        return np.zeros(tuple(int(s) for s in shape), dtype=bool)
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):  # vertices on or behind the camera plane
        uv, z = camera.project(verts, return_depth=True)
    front = np.all(z[faces] > 0, axis=1)
    return fill_triangles(uv, faces[front], shape)
