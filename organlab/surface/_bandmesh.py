"""Marching cubes on the band of a :class:`~organlab.bandfield.BandField` only.

The surface of ``mesh_from_volume(field, grid)`` (the field padded by one
sample of ``min(0, field.min())`` on every side, Lewiner marching cubes at
level 0.5) is computed chunk by chunk: the padded sample lattice is cut into
cubes of ``chunk`` cells; a chunk is meshed only when its samples are not all
on one side of the level (it holds a band block, or inside and outside blocks
meet in it).  Each chunk is meshed with scikit-image's ``marching_cubes`` on
its ``(chunk + 1)**3`` samples, which it shares, one sample layer thick, with
its neighbours.

Why the pieces weld into the same closed surface: Lewiner's triangulation of
a cell depends only on that cell's 8 values (the face ambiguity on the 4
values of the shared face), and every cell belongs to exactly one chunk; a
vertex on a chunk's face is computed by both chunks from the same two values,
at local coordinates that differ only by whole numbers along the axes the
vertex does not move along (chunks are aligned on one lattice), so both copies
have the same float32 fraction and the same position after the integer
offset is added.  Copies are merged by exact coordinates.  Vertex positions
differ from the one-piece marching cubes only by float32 rounding (the
tests bound the difference).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from ..bandfield import INSIDE
from ..mesh import Mesh

__all__ = ["band_mesh"]


@njit(cache=True)
def _chunks_to_mesh(states, B, shape, S):
    """Chunks (of S cells of the padded lattice) whose samples are not all one class.

    Padded sample ``p`` is voxel ``p - 1``; samples outside the grid are the
    pad (outside).  Returns ``(n, 3)`` chunk indices.
    """
    nx, ny, nz = shape[0], shape[1], shape[2]
    ncx = (nx + 1 + S - 1) // S
    ncy = (ny + 1 + S - 1) // S
    ncz = (nz + 1 + S - 1) // S
    out = np.empty((ncx * ncy * ncz, 3), dtype=np.int64)
    n = 0
    for a in range(ncx):
        for b in range(ncy):
            for c in range(ncz):
                # voxel range of the chunk's samples [a S, (a + 1) S], minus the pad shift
                lo = (a * S - 1, b * S - 1, c * S - 1)
                hi = ((a + 1) * S - 1, (b + 1) * S - 1, (c + 1) * S - 1)
                has_out = lo[0] < 0 or lo[1] < 0 or lo[2] < 0 or hi[0] >= nx or hi[1] >= ny or hi[2] >= nz
                has_in = False
                has_band = False
                for i in range(max(lo[0], 0) // B, min(hi[0], nx - 1) // B + 1):
                    for j in range(max(lo[1], 0) // B, min(hi[1], ny - 1) // B + 1):
                        for k in range(max(lo[2], 0) // B, min(hi[2], nz - 1) // B + 1):
                            s = states[i, j, k]
                            if s == 2:
                                has_band = True
                            elif s == 1:
                                has_in = True
                            else:
                                has_out = True
                if has_band or (has_in and has_out):
                    out[n, 0] = a
                    out[n, 1] = b
                    out[n, 2] = c
                    n += 1
    return out[:n]


@njit(cache=True)
def _chunk_samples(states, index, values, B, shape, p0, n, pad):
    """Samples ``p0 + [0, n)`` of the padded lattice, float32."""
    nx, ny, nz = shape[0], shape[1], shape[2]
    out = np.empty((n[0], n[1], n[2]), dtype=np.float32)
    for a in range(n[0]):
        i = p0[0] + a - 1
        for b in range(n[1]):
            j = p0[1] + b - 1
            for c in range(n[2]):
                k = p0[2] + c - 1
                if i < 0 or j < 0 or k < 0 or i >= nx or j >= ny or k >= nz:
                    out[a, b, c] = pad
                    continue
                s = states[i // B, j // B, k // B]
                if s == 2:
                    out[a, b, c] = values[index[i // B, j // B, k // B], i % B, j % B, k % B]
                elif s == 1:
                    out[a, b, c] = 1.5
                else:
                    out[a, b, c] = -0.5
    return out


#: How far below the level (relative) marching cubes runs again when its surface has non-manifold edges:
#: where two diagonal voxels of an occupancy meet (a fin thinner than a voxel, slanted to the grid), a cube
#: face's saddle value is 0.5, exactly the level, and Lewiner's test resolves the tie one way in one cube
#: and the other way in the next, giving edges of four faces (a 30 mm ball with fins 0.5-1 voxel thick at
#: 1 mm: 39-1 062 of them), which repair then cut open (the finished surface 2-8 voxels off the raw one,
#: volume -9 to -90 %).  Just below the level every such tie joins the two voxels, in every cube; the
#: vertices move by this fraction of a voxel, and only on surfaces that were not manifold.
TIE_LEVEL = 1e-5


def tie_level(level: float) -> float:
    """The level marching cubes runs at again when its surface at ``level`` has non-manifold edges."""
    return float(level) - TIE_LEVEL * max(abs(float(level)), 1.0)


def untie(vol: np.ndarray, level: float) -> np.ndarray:
    """``vol`` (float32) with its samples exactly at ``level`` moved to :func:`tie_level` (below it): a copy if any.

    Lewiner's marching cubes counts a sample at the level as outside, and every cube edge from it to an inside
    sample puts its vertex exactly on it; with ``allow_degenerate=False`` the triangles of those coincident
    vertices are dropped and the surface has holes there (a ball with coverage fins 0.9 voxel thick at 1 mm,
    seed 0: the field exactly 0.5 at 145 voxels, 5 holes, 18 boundary edges; finishing then took the
    open-surface path, 3.5 voxels off).  Moved just below the level, the sample is outside as before (the same
    cube cases, the same topology) and each vertex lies a hundred-thousandth of a voxel off it, on its own: the
    surface closes.  Every copy of a sample (chunks of :func:`band_mesh`, the dense :func:`mesh_from_volume`)
    is moved the same way.
    """
    lev = np.float32(level)
    tie = vol == lev
    if not tie.any() or float(lev) != float(level):
        return vol
    return np.where(tie, np.float32(tie_level(level)), vol).astype(np.float32, copy=False)


def band_mesh(field, *, chunk=32, level=0.5, _tie=False):
    """Closed surface of a band field at ``level`` by Lewiner marching cubes on the band only.

    Parameters
    ----------
    field : BandField
    chunk : int
        Cells per chunk edge.
    level : float

    Returns
    -------
    organlab.surface.Mesh
        World frame, mm, faces oriented outward, no degenerate faces; the mesh
        of ``organlab.surface.mesh_from_volume(field.dense(), field.grid)``
        up to float32 rounding of the vertices and their order.

    Raises
    ------
    ValueError
        If nothing is above ``level`` (an empty model).
    """
    from skimage.measure import marching_cubes

    grid = field.grid
    shape = np.asarray(grid.shape, dtype=np.int64)
    S = int(chunk)
    if S < 1:
        raise ValueError(f"chunk must be an integer >= 1, got {chunk!r}")
    has_inside = (field.states == INSIDE).any() or (len(field.values) and float(field.values.max()) > level)
    if not has_inside:
        raise ValueError("the volume has nothing above the iso-level: the model is empty")
    pad = np.float32(min(0.0, field.min()))
    chunks = _chunks_to_mesh(field.states, field.block, shape, S)
    verts, faces, edge = [], [], []
    nverts = 0
    total = shape + 2  # padded samples
    for a, b, c in chunks:
        p0 = np.array([a, b, c], dtype=np.int64) * S
        n = np.minimum(p0 + S + 1, total) - p0
        if (n < 2).any():
            continue
        vol = untie(_chunk_samples(field.states, field.index, field.values, field.block, shape, p0, n, pad), level)
        if not (vol.min() < level < vol.max()):
            continue
        try:
            v, f, _, _ = marching_cubes(vol, level=level, method="lewiner", allow_degenerate=False)
        except RuntimeError:  # no surface in this chunk
            continue
        v = np.asarray(v, dtype=np.float32)
        # vertices on the chunk's faces are shared with a neighbour
        edge.append(((v == 0) | (v == (n - 1).astype(np.float32))).any(axis=1))
        verts.append(v.astype(np.float64) + p0)
        faces.append(np.asarray(f, dtype=np.int64) + nverts)
        nverts += len(v)
    if not verts:
        raise ValueError("the volume has nothing above the iso-level: the model is empty")
    verts = np.concatenate(verts)
    faces = np.concatenate(faces)
    edge = np.concatenate(edge)
    # weld the copies of shared vertices (bit-identical coordinates)
    inner = np.flatnonzero(~edge)
    shared = np.flatnonzero(edge)
    uniq, inv = np.unique(verts[shared], axis=0, return_inverse=True)
    remap = np.empty(len(verts), dtype=np.int64)
    remap[inner] = np.arange(len(inner))
    remap[shared] = len(inner) + inv.ravel()
    verts = np.concatenate([verts[inner], uniq])
    faces = remap[faces]
    s = grid.voxel_size
    verts = verts * s + (np.asarray(grid.origin) - s)
    mesh = Mesh(verts, faces)
    if mesh.volume < 0:
        mesh = Mesh(verts, faces[:, ::-1].copy())
    if mesh.edge_counts()[1] and not _tie:  # a saddle exactly at the level: see TIE_LEVEL
        return band_mesh(field, chunk=chunk, level=tie_level(level), _tie=True)
    return mesh

