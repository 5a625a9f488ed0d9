"""Thin parts: which side of a sheet a vertex is on.

Where a part is thinner than the distance a vertex moves in one step (a fin thinner than a voxel: its
two sides a fraction of a voxel apart), closest-point projection puts a vertex of one side on the
other.  Two places did: Taubin smoothing moves each side of a sheet on its own, so the two pass
through each other, and the remesher, which starts from the smoothed surface, projects the vertices
onto the raw surface by closest point after every move.  A ball with three fins 0.6 voxel thick (a
coverage field, 1 mm voxels): 503 smoothed faces already faced the other way than the raw surface
under them, about 1 300 of the 18 000 remeshed ones, 2 000 faces below 20 degrees after the clean-up,
and the finished surface was 1.7 voxels off the raw one.

- :func:`keep_thin`: after smoothing, the vertices smoothing took through a thin part (their closest
  raw point faces away from their raw normal), and two rings around them, go back to their raw places
  (run only when :func:`._repair._staircase`'s sample of the smoothed vertices finds one);
- :func:`thin_vertices`: the vertices of a part thinner than about a voxel (a probe half a voxel inward along the
  normal is nearer the part's other side); :func:`keep_thin` puts them, and 4 rings around, back at their raw
  places too, crossed or not, so that the remesher starts from one sheet, not a sheet partly smoothed and partly raw;
- :func:`thickened`: before any of that, a part thinner than :data:`MIN_THICK_VOXELS` (a fin under half a voxel,
  which marching cubes gives as a lace of slabs a few hundredths of a voxel thick and rods along the grid's lines) is
  made that thick, each side moved out by about half of it; the remesher stays on that surface, whose volume
  (the raw one and what the thickening added) is the one restored;
- :func:`same_side`: a closest point whose face looks away from the moved vertex (normals more than 90
  degrees apart) is on the other side of a sheet, never on the vertex's own: the remesher's
  relaxations refuse it (the vertex keeps its place, as for their other refused moves) and
  :func:`._remesh.fit_faces` does not count a face's gap to it.

On a surface without thin parts nothing is put back and no projection is refused: the same result
(the sample at 1 mm: the same 20 934 faces).
"""

from __future__ import annotations

import numpy as np

from ..mesh import Mesh
from ._deviation import _surface


def _face_normals(surface, face):
    """Normals ``(N, 3)`` (not normalized) of faces ``face`` ``(N,)`` of a :class:`._deviation._Surface`: only the
    faces asked for, nothing kept (a cache of the whole surface's was 45 MB at 0.25 mm, at the command's peak)."""
    v, f = surface.v, surface.f[face]
    return np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])


def same_side(surface, face: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """``(N,)`` bool: the closest point on ``face`` ``(N,)`` of ``surface`` faces the same way as ``normals``
    ``(N, 3)`` (the moved vertices' or faces' normals, any length): on their own side of a thin part."""
    return np.einsum("ij,ij->i", _face_normals(surface, face), normals) > 0.0


#: Rings of vertices around one smoothing took through a thin part that go back to their raw places too.
UNSMOOTH_RINGS = 2


def crossed(surface, points: np.ndarray, index: np.ndarray) -> np.ndarray:
    """``(N,)`` bool: the closest point of ``surface`` to ``points`` ``(N, 3)`` (moved copies of its vertices
    ``index`` ``(N,)``) faces away from the vertex it came from: the point went through a thin part."""
    _, _, face = surface.closest(points)
    return ~same_side(surface, face, surface.vertex_normal_sums()[index])


def thin_vertices(surface, depth: float) -> np.ndarray:
    """``(V,)`` bool: the vertices of ``surface`` (a :class:`._deviation._Surface`) on a part thinner than about
    ``2 * depth`` (mm): the point ``depth`` inside along the vertex's normal is closer to the other side of
    the part (a closest face looking away from the vertex) than to its own."""
    n = surface.vertex_normal_sums()
    u = n / (np.linalg.norm(n, axis=1, keepdims=True) + 1e-300)
    _, _, face = surface.closest(surface.v - float(depth) * u)
    return ~same_side(surface, face, n)


#: Rings of vertices around the vertices of a part thinner than a voxel (:func:`thin_vertices`) that keep their raw
#: places too (1 mm balls with coverage fins 0.6-0.7 voxel thick: 2 rings left 0.82-0.83 voxel, 4 rings 0.59-0.76).
THIN_RINGS = 4


def _grown(mask, F, rings):
    """``mask`` (vertices, bool) with ``rings`` rings of vertices around it, through the faces ``F``: a new mask."""
    out = np.array(mask, dtype=bool)
    for _ in range(int(rings)):
        out[F[out[F].any(axis=1)].ravel()] = True
    return out


def keep_thin(smoothed, raw, *, rings: int = UNSMOOTH_RINGS, rounds: int = 6, depth: float | None = None,
              thin_rings: int = THIN_RINGS):
    """``smoothed`` with the vertices of thin parts back at their ``raw`` places: ``(Mesh, n restored)``.

    Taubin smoothing moves each side of a sheet on its own; where the sheet is thinner than the
    staircase it relaxes (a fin a fraction of a voxel thick, or a perforated one), the two sides pass
    through each other: the smoothed vertex's closest point on the raw surface is on the other side
    (a ball with fins 0.6 voxel thick at 1 mm: 56 vertices; 0.7 voxel thick in an occupancy: 134).  The
    remesher starts from the smoothed surface and projects onto the raw one, so such vertices, and the
    faces around them, end on the wrong side of the fin.  Every such vertex, and ``rings`` rings of
    vertices around it, gets its raw place back, until none is left (at most ``rounds`` times).

    With ``depth`` (mm; ``finish_surface`` passes half a voxel), every vertex of a part thinner than about
    ``2 * depth`` (:func:`thin_vertices`), and ``thin_rings`` rings around, gets its raw place back first,
    crossed or not: a sheet partly smoothed and partly raw is the remesher's worst start (1 mm balls with
    coverage fins 0.6 voxel thick: 1 573 faces below 20 degrees after remeshing, 1.87 voxels off when
    finished; from the raw places of the whole sheet: 0.76 voxel, 21.1 degrees).
    ``smoothed`` itself (and 0) when none is found.  Called only when :func:`._repair._staircase`'s
    sample of the smoothed vertices found one.
    """
    F = np.asarray(raw.faces, dtype=np.int64)
    if len(smoothed.vertices) != len(raw.vertices) or not np.array_equal(np.asarray(smoothed.faces), F):
        return smoothed, 0
    ref, R = _surface(raw), np.asarray(raw.vertices, dtype=np.float64)
    V = np.asarray(smoothed.vertices, dtype=np.float64)
    back = np.zeros(len(V), dtype=bool)
    if depth is not None:
        back = _grown(thin_vertices(ref, depth), F, thin_rings)
        V = np.where(back[:, None], R, V)
    every = np.arange(len(V))
    nr = np.cross(R[F[:, 1]] - R[F[:, 0]], R[F[:, 2]] - R[F[:, 0]])
    for _ in range(int(rounds)):
        wrong = crossed(ref, V, every)
        # and the vertices of faces turned over from their raw selves (the two sides crossed within a face)
        turned = np.einsum("ij,ij->i", np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]), nr) <= 0.0
        wrong[F[turned].ravel()] = True
        if not wrong.any():
            break
        mark = _grown(wrong, F, rings)
        if not (mark & ~back).any():
            break
        back |= mark
        V = np.where(back[:, None], R, V)
    if not back.any():
        return smoothed, 0
    return Mesh(V, F), int(back.sum())


#: The thickness (voxels) a part thinner than a voxel is given before remeshing (:func:`thickened`): each side moves
#: out by at most half of it.  Chosen on balls with coverage fins at 1 mm (max deviation from the raw surface, voxels):
#: 0.4-0.5 voxel thick, seeds 0-2, as they were 0.80-2.21 (19.5-21.6 deg); 0.2: 0.66-2.24 (one 0.13 deg); 0.3:
#: 0.57-0.99; 0.4: 0.48-0.75.  With 0.4 (and 4 rounds) 0.35-0.55 voxel thick, seeds 3-8: 16 of 18 within, seed 7's
#: fins (a plane within 0.2 degrees of the x axis: rods along the grid's lines) 1.33-3.49; 0.5: 0.45-1.54 there;
#: 0.6: 0.38-0.80 on all of them, no last step needed (one sliver cut).
MIN_THICK_VOXELS = 0.6


def thickened(raw, depth: float, min_mm: float, *, rounds: int = 4):
    """``raw`` with its parts thinner than ``min_mm`` made that thick: ``(Mesh, vertices moved)``.

    A part much thinner than a voxel comes out of marching cubes as a lace: islands of two sheets a few hundredths
    of a voxel apart (a fin 0.4 voxel thick, sampled where its middle plane passes near a row of samples), joined
    by sub-voxel tunnels.  No triangle of the remesher's edges (0.35 voxel at least) is well shaped on such a slab,
    and its projection onto the raw surface squeezed the islands flat: 500 faces below 20 degrees after remeshing
    (a ball with coverage fins 0.4 voxel thick, seed 1), which the sliver step's cuts then took out with the
    islands (1.4-2.2 voxels of raw surface lost).  Each vertex whose probe ``depth`` inward reaches the other side
    of its part (:func:`thin_vertices`) moves out along its normal by half of what the part lacks of ``min_mm``
    there (the distance along its normal to the other side's closest point; at most ``min_mm / 2`` a round), both
    sides alike, ``rounds`` times.  The remesher then stays on this surface (a plate 0.3 voxel thick: its vertices
    moved 0.37 voxel at most, its two sheets 0.02-0.38 -> 0.40-0.80 voxel apart).  ``raw`` itself (and 0) when no
    part is thinner.
    """
    F = np.asarray(raw.faces, dtype=np.int64)
    V = np.asarray(raw.vertices, dtype=np.float64)
    out, moved = raw, np.zeros(len(V), dtype=bool)
    ask = np.arange(len(V))  # the vertices probed: all, then those within 2 rings of the last round's moves
    for _ in range(int(rounds)):
        surface = _surface(out)
        n = surface.vertex_normal_sums()[ask]
        u = n / (np.linalg.norm(n, axis=1, keepdims=True) + 1e-300)
        q, _, face = surface.closest(V[ask] - float(depth) * u)
        other = ~same_side(surface, face, n)
        lack = float(min_mm) - np.einsum("ij,ij->i", V[ask] - q, u)  # what the part lacks of min_mm along the normal
        push = np.where(other, np.clip(0.5 * lack, 0.0, 0.5 * float(min_mm)), 0.0)
        step = push > 1e-6 * float(min_mm)
        if not step.any():
            break
        moved[ask[step]] = True
        V = V.copy()
        V[ask[step]] += push[step, None] * u[step]
        out = Mesh(V, F)
        # a vertex farther than 2 rings from a move keeps its normal; its probe may reach a moved face of the other
        # side, whose vertices move in the same rounds: not asked again (the dino at 1 mm: the same vertices, bit for
        # bit, 0.22 -> 0.12 s CPU; fins 0.35-0.5 voxel thick: within 6e-7 mm)
        near = np.zeros(len(V), dtype=bool)
        near[ask[step]] = True
        ask = np.flatnonzero(_grown(near, F, 2))
    return out, int(moved.sum())
