"""Repair, smoothing and remeshing: the finished surface.

A closed, manifold surface (the usual marching-cubes one, or one repair
closed) is remeshed by :mod:`._remesh`: edges adapted to the curvature, every
vertex on the raw surface, no fold cut out (issue 21: the former fold cutting
shaved thin parts off real specimens).  An open or non-manifold one
(``repair=False``) goes through pymeshlab's isotropic remeshing as before.

Facts this relies on (pymeshlab 2025.7): ``meshing_close_holes``'s
``maxholesize`` counts boundary edges, so it is set from the measured hole
sizes; ``meshing_repair_non_manifold_edges`` ('Remove Faces') opens new holes,
so holes are closed and specks dropped after it; isotropic remeshing takes its
target edge length as ``PureValue(mm)``; it keeps edges sharper than
``featuredeg`` as features, so the marching-cubes staircase is first relaxed by
Taubin smoothing (volume-preserving to about 0.1 %); folds (faces more than
90 degrees apart: voxel-scale crevices, lips and handles below 1 mm voxels)
are cut out and filled before remeshing, see :mod:`._folds`.
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from numba import njit

from ..errors import OrganlabError
from ..grid import VoxelGrid
from ._deviation import _SURFACES, _deviation_figures, _distances, _Surface, _surface
from ._folds import fold_edges
from ._guard import keep_on_data, near_deviation
from ._mesh import Mesh, mesh_from_field
from ._quality import (_face_figures, _find, _moved, boundary_loops, has_duplicate_vertices, has_null_faces,
                       mesh_quality, triangle_angles)
from ._remesh import adaptive_remesh, fit_faces, fix_slivers, sizing_field
from ._thin import MIN_THICK_VOXELS, keep_thin, same_side, thickened
from ._voronoi import vertex_normals


def _to_ms(mesh):
    import pymeshlab

    ms = pymeshlab.MeshSet()
    v = np.ascontiguousarray(mesh.vertices, dtype=np.float64)
    f = np.ascontiguousarray(mesh.faces, dtype=np.int32)
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=v, face_matrix=f))
    return ms


def _from_ms(ms):
    m = ms.current_mesh()
    return Mesh(np.asarray(m.vertex_matrix(), dtype=np.float64), np.asarray(m.face_matrix(), dtype=np.int64))


def _oriented(mesh):
    return mesh if mesh.volume >= 0 else Mesh(mesh.vertices, mesh.faces[:, ::-1].copy())


def _step(name, before, after, **extra):
    qb, qa = mesh_quality(before), mesh_quality(after)
    vb = qb["volume_mm3"]
    rec = {
        "step": name,
        "faces_before": qb["faces"],
        "faces_after": qa["faces"],
        "holes_before": qb["holes"],
        "holes_after": qa["holes"],
        "boundary_edges_after": qa["boundary_edges"],
        "nonmanifold_edges_after": qa["nonmanifold_edges"],
        "nonmanifold_vertices_after": qa["nonmanifold_vertices"],
        "volume_change_pct": 100.0 * (qa["volume_mm3"] - vb) / vb if vb else float("nan"),
        "min_angle_deg": [qb["min_angle_deg"], qa["min_angle_deg"]],
        "max_aspect_ratio": [qb["max_aspect_ratio"], qa["max_aspect_ratio"]],
    }
    rec.update(extra)
    return rec


def _repair_once(ms, speck_mm):
    import pymeshlab

    ms.meshing_remove_duplicate_vertices()
    ms.meshing_remove_duplicate_faces()
    ms.meshing_remove_null_faces()
    ms.meshing_repair_non_manifold_edges(method="Remove Faces")
    ms.meshing_repair_non_manifold_vertices(vertdispratio=0)
    ms.meshing_remove_unreferenced_vertices()
    ms.meshing_remove_connected_component_by_diameter(mincomponentdiag=pymeshlab.PureValue(speck_mm))
    loops = boundary_loops(_from_ms(ms))
    if loops:
        # maxholesize counts boundary edges: just above the largest hole
        ms.meshing_close_holes(maxholesize=int(max(loops)) + 1, newfaceselected=False)
    try:
        ms.meshing_re_orient_faces_coherently()
    except pymeshlab.PyMeshLabException:
        pass  # still non-manifold: the next round removes more faces first
    return loops


def repair_mesh(mesh: Mesh, *, speck_mm: float = 3.0, max_rounds: int = 4) -> tuple[Mesh, dict]:
    """Close holes, remove non-manifold edges and vertices, drop specks.

    Parameters
    ----------
    mesh : Mesh
        World frame, mm.
    speck_mm : float, mm
        Connected components whose bounding-box diagonal is below this are removed.
    max_rounds : int
        Repair rounds (non-manifold removal opens holes, which the next closes).

    Returns
    -------
    Mesh
        Oriented outward.
    dict
        ``holes`` closed (their edge counts), ``faces_removed``, ``rounds``,
        ``volume_change_pct`` and the quality before and after.
    """
    _check_mesh(mesh)
    defects = _defects(mesh, speck_mm)
    if not defects:  # already closed, manifold, oriented, without specks (the usual marching-cubes surface)
        return mesh, _step("repair", mesh, mesh, holes_closed=0, hole_edges=[], rounds=0)
    if defects <= {"specks", "holes", "unreferenced"}:
        # manifold, with holes (a cut, see _folds) and small separate pieces (finer voxels): the pieces
        # dropped and the holes closed as _repair_once does, without its other filters
        out = _drop_specks(mesh, speck_mm) if defects & {"specks", "unreferenced"} else mesh
        left = None if out is None else _defects(out, speck_mm)
        if left is not None and left <= {"holes"}:
            holes = boundary_loops(out) if left else []
            if holes:
                ms = _to_ms(out)
                ms.meshing_close_holes(maxholesize=int(max(holes)) + 1, newfaceselected=False)
                out = _oriented(_from_ms(ms))
                if _defects(out, speck_mm) == {"holes"}:  # holes the filter refused (it tests self-intersection)
                    out = _fan_loops(out)
            if out is not None and not _defects(out, speck_mm):
                return out, _step("repair", mesh, out, holes_closed=len(holes), hole_edges=holes, rounds=1)
    ms = _to_ms(mesh)
    holes = []
    rounds = 0
    out = mesh
    for rounds in range(1, max_rounds + 1):
        holes += _repair_once(ms, speck_mm)
        out = _oriented(_from_ms(ms))
        q = mesh_quality(out)
        if q["boundary_edges"] == q["nonmanifold_edges"] == q["nonmanifold_vertices"] == 0:
            break
    rec = _step("repair", mesh, out, holes_closed=len(holes), hole_edges=holes, rounds=rounds)
    return out, rec


def _defects(mesh, speck_mm):
    """What :func:`repair_mesh` would change: a set of ``'holes'``, ``'nonmanifold'``, ``'misoriented'``,
    ``'unreferenced'``, ``'duplicates'``, ``'null'``, ``'specks'`` (empty: nothing).  Computed once per mesh
    and ``speck_mm`` (the mesh is immutable; repair asks again about the mesh it just checked)."""
    known = _DEFECTS.get(mesh)
    if known is not None and speck_mm in known:
        return set(known[speck_mm])
    out = _find_defects(mesh, speck_mm)
    _DEFECTS.setdefault(mesh, {})[speck_mm] = frozenset(out)
    return out


_DEFECTS = weakref.WeakKeyDictionary()


def _find_defects(mesh, speck_mm):
    q = mesh_quality(mesh)
    out = set()
    if q["boundary_edges"]:
        out.add("holes")
    if q["nonmanifold_edges"] or q["nonmanifold_vertices"]:
        out.add("nonmanifold")
    if q["misoriented_edges"]:
        out.add("misoriented")
    v, f = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    if q["vertices"] != len(v):
        out.add("unreferenced")
    if has_duplicate_vertices(mesh):
        out.add("duplicates")
    # a zero cross product of the edge vectors; the face figures' area is half its norm, from the same
    # quality pass (the cross product of (p1 - p0, p0 - p2) is that of (p1 - p0, p2 - p0) negated, exactly)
    if has_null_faces(mesh):
        out.add("null")
    if q["components"] > 1 or np.linalg.norm(np.ptp(v, axis=0)) < speck_mm:
        out.add("specks")  # the pymeshlab filter decides which of several pieces go
    return out


def _fan_loops(mesh):
    """The mesh with each boundary loop closed by a fan from its first vertex; None if a loop is not simple.

    What ``meshing_close_holes`` leaves (0.25 mm sample: one 3-edge hole of a fold cut that it would
    not close) before the full repair rounds (21 s there, and still open).  The new faces run each
    boundary edge the other way.
    """
    f = np.asarray(mesh.faces, dtype=np.int64)
    order, starts, counts = mesh._edges()
    e = order[starts[counts == 1]].astype(np.int64)
    F = len(f)
    a, b = f[e % F, e // F], f[e % F, (e // F + 1) % 3]
    if len(np.unique(a)) != len(a):
        return None  # a vertex on two loops (or twice on one)
    nxt = dict(zip(a.tolist(), b.tolist()))
    new, seen = [], set()
    for start in a.tolist():
        if start in seen:
            continue
        loop = [start]
        while nxt[loop[-1]] != start:
            loop.append(nxt[loop[-1]])
            if len(loop) > len(a):
                return None
        seen.update(loop)
        new += [(loop[0], loop[i + 1], loop[i]) for i in range(1, len(loop) - 1)]
    return Mesh(mesh.vertices, np.concatenate([f, np.asarray(new, dtype=np.int64).reshape(-1, 3)]))


def _pieces(f, nv):
    """``(n, label (nv,))``: the connected pieces of faces ``f`` ``(F, 3)`` int64 over ``nv`` vertices (by edges);
    each piece labelled by its smallest vertex (union-find: the partition scipy's graph components gave, in one
    compiled pass instead of a sparse graph of 2F edges)."""
    lab = _piece_roots(np.ascontiguousarray(f, dtype=np.int64), int(nv))
    return int((lab == np.arange(nv)).sum()), lab


@njit(cache=True, nogil=True)
def _piece_roots(f, nv):
    parent = np.arange(nv)
    for t in range(f.shape[0]):
        for i in range(2):
            x, y = _find(parent, f[t, i]), _find(parent, f[t, i + 1])
            if x != y:
                parent[max(x, y)] = min(x, y)
    for v in range(nv):
        parent[v] = _find(parent, v)
    return parent


@njit(cache=True, nogil=True)
def _piece_boxes(v, lab, lo, hi):
    """Each piece's bounding box, in the rows of its label (the vertices' exact minima and maxima)."""
    for i in range(v.shape[0]):
        r = lab[i]
        for k in range(3):
            lo[r, k] = min(lo[r, k], v[i, k])
            hi[r, k] = max(hi[r, k], v[i, k])


def _drop_specks(mesh, speck_mm):
    """The mesh without the connected pieces whose bounding-box diagonal is below ``speck_mm``; None if none is left.

    As pymeshlab's ``meshing_remove_connected_component_by_diameter`` on an edge-manifold mesh
    (pieces connected by edges; the vertices of the pieces left are renumbered in order).
    """
    v, f = np.asarray(mesh.vertices), np.asarray(mesh.faces, dtype=np.int64)
    nv = len(v)
    _, lab = _pieces(f, nv)
    lo = np.full((nv, 3), np.inf)
    hi = np.full((nv, 3), -np.inf)
    _piece_boxes(np.ascontiguousarray(v, dtype=np.float64), lab, lo, hi)
    roots = np.flatnonzero(lab == np.arange(nv))
    big = np.zeros(nv, dtype=bool)
    big[roots] = np.linalg.norm(hi[roots] - lo[roots], axis=1) >= speck_mm
    keep = big[lab[f[:, 0]]]
    if not keep.any():
        return None
    used = np.zeros(nv, dtype=bool)
    used[f[keep].ravel()] = True
    new = np.cumsum(used) - 1
    return Mesh(v[used], new[f[keep]])


@njit(cache=True, nogil=True)
def _taubin(v, indptr, indices, data, iterations, lambda_, mu):
    """``v += step * (w @ v - v)`` for ``step`` in ``(lambda_, mu)``, ``iterations`` times, in place; ``w`` in CSR
    (``indptr``, ``indices``, ``data``).  Each row's product summed from 0 in the stored order, as scipy's
    ``csr_matvecs``; then numpy's operations of the expression, one element at a time: the same bits."""
    n = v.shape[0]
    y = np.empty_like(v)
    for _ in range(iterations):
        for step in (lambda_, mu):
            for i in range(n):
                a0 = a1 = a2 = 0.0
                for jj in range(indptr[i], indptr[i + 1]):
                    x, j = data[jj], indices[jj]
                    a0 += x * v[j, 0]
                    a1 += x * v[j, 1]
                    a2 += x * v[j, 2]
                y[i, 0], y[i, 1], y[i, 2] = a0, a1, a2
            for i in range(n):
                for c in range(3):
                    v[i, c] += step * (y[i, c] - v[i, c])


def smooth_mesh(mesh: Mesh, *, iterations: int = 10, lambda_: float = 0.5, mu: float = -0.53) -> tuple[Mesh, dict]:
    """Taubin smoothing (shrink-free): relaxes the marching-cubes staircase.

    Parameters
    ----------
    mesh : Mesh
    iterations : int
    lambda_, mu : float
        Taubin's positive and negative steps.

    Returns
    -------
    Mesh, dict
    """
    from scipy.sparse import coo_matrix, diags

    _check_mesh(mesh)
    if mesh.edge_counts()[0]:  # open: pymeshlab's smoothing moves the border vertices along the border only
        ms = _to_ms(mesh)
        ms.apply_coord_taubin_smoothing(lambda_=lambda_, mu=mu, stepsmoothnum=int(iterations))
        out = _oriented(_from_ms(ms))
        return out, _step("smooth", mesh, out, iterations=int(iterations))
    # closed: the uniform Laplacian (the mean of the edge neighbours) that pymeshlab's
    # apply_coord_taubin_smoothing applies, as a sparse matrix (1 mm sample: the same vertices
    # within 5e-8 mm, 20 ms instead of 130 ms)
    f = np.asarray(mesh.faces, dtype=np.int64)
    order, starts, _ = mesh._edges()
    u = order[starts].astype(np.int64)
    a, b = f[u % len(f), u // len(f)], f[u % len(f), (u // len(f) + 1) % 3]
    nv = len(mesh.vertices)
    adj = coo_matrix((np.ones(2 * len(a)), (np.r_[a, b], np.r_[b, a])), shape=(nv, nv)).tocsr()
    w = diags(1.0 / np.maximum(np.asarray(adj.sum(axis=1)).ravel(), 1.0)) @ adj
    v = np.array(mesh.vertices, dtype=np.float64)
    # v += lambda_ * (w @ v - v), then mu, compiled: scipy's products (each row's terms in w's order, from 0)
    # and numpy's steps, so the same bits (1 mm sample 23 -> 15 ms, 0.25 mm 0.37 -> 0.26 s CPU)
    _taubin(v, w.indptr, w.indices, w.data, int(iterations), float(lambda_), float(mu))  # scipy's int32 indices
    out = _moved(_oriented(Mesh(v, mesh.faces)), mesh)
    return out, _step("smooth", mesh, out, iterations=int(iterations))


def remesh_mesh(mesh: Mesh, target_mm: float, *, iterations: int = 6, feature_deg: float = 60.0, min_angle: float = 20.0,
                max_passes: int = 3) -> tuple[Mesh, dict]:
    """Isotropic explicit remeshing to edges of about ``target_mm``.

    Parameters
    ----------
    mesh : Mesh
        Closed, manifold (run :func:`repair_mesh` first).
    target_mm : float, mm
        Target edge length (``PureValue``, not a percentage of the bounding box).
    iterations : int
        Remeshing iterations per pass.
    feature_deg : float, degrees
        Dihedral angles sharper than this are kept as feature edges.
    min_angle : float, degrees
        Further passes run while the smallest angle is below this.
    max_passes : int

    Returns
    -------
    Mesh, dict
    """
    import pymeshlab

    _check_mesh(mesh)
    if not target_mm > 0:
        raise ValueError(f"remesh target edge length must be > 0 mm, got {target_mm}")
    # every flag given at each call (pymeshlab keeps no state between calls, but the two kinds of pass
    # must not depend on it); checksurfdist=False: its test of every collapse and flip against the input
    # surface took 60 % of the time (1 mm sample: 3.4 s -> 0.7 s) for the same volume and angles
    flags = dict(targetlen=pymeshlab.PureValue(float(target_mm)), featuredeg=float(feature_deg), adaptive=False,
                 checksurfdist=False, splitflag=True, collapseflag=True, swapflag=True, smoothflag=True,
                 reprojectflag=True)
    ms = _to_ms(mesh)
    out, passes, best, kept = mesh, 0, -1.0, None
    for passes in range(1, max_passes + 1):
        if passes == 1:
            ms.meshing_isotropic_explicit_remeshing(iterations=int(iterations), selectedonly=False, **flags)
        else:
            # later passes remesh only the faces within 3 rings of those still below min_angle
            # (0.5 mm sample: one face of 76 000, 0.7 s instead of 4 s for a whole pass, 23.3 degrees)
            ms = pymeshlab.MeshSet()
            bad = (_face_figures(out)[0] < min_angle).astype(np.float64)
            ms.add_mesh(pymeshlab.Mesh(vertex_matrix=np.ascontiguousarray(out.vertices, dtype=np.float64),
                                       face_matrix=np.ascontiguousarray(out.faces, dtype=np.int32),
                                       f_scalar_array=bad))
            ms.compute_selection_by_condition_per_face(condselect="fq > 0.5")
            for _ in range(3):
                ms.apply_selection_dilatation()
            ms.meshing_isotropic_explicit_remeshing(iterations=3, selectedonly=True, **flags)
        out = _oriented(_from_ms(ms))
        angle = mesh_quality(out)["min_angle_deg"]
        if angle < best:  # a local pass can make it worse (0.25 mm sample: 0.3 degrees): the best pass is kept
            out, angle = kept, best
        # done, or a pass that gained less than a degree
        if angle >= min_angle or angle < best + 1.0:
            break
        best, kept = angle, out
    return out, _step("remesh", mesh, out, target_mm=float(target_mm), passes=passes)


def _restore_volume(mesh, volume):
    """Offset the vertices along their normals so that the enclosed volume is ``volume``.

    Remeshing with longer edges cuts chords inside convex parts (-0.15 % at
    1.5 mm on the sample, -0.5 % at 3 mm); a uniform normal offset of
    ``(volume - V) / area`` (hundredths of a mm) gives the volume back
    without changing the triangles' shapes.
    """
    out = mesh
    for _ in range(3):
        gap = volume - out.volume
        if abs(gap) <= 1e-6 * abs(volume):
            break
        out = _moved(Mesh(out.vertices + (gap / out.area) * vertex_normals(out), out.faces), out)
    return out


def _clear_folds(mesh, radius_mm, *, speck_mm, fold_deg=90.0, max_rounds=3):
    """Cut out and fill the spots where neighbouring faces are more than ``fold_deg`` apart (see :mod:`._folds`)."""
    out, found, removed = mesh, [], 0
    for _ in range(max_rounds):
        fe = fold_edges(out, fold_deg)
        found.append(len(fe))
        if len(fe) == 0:
            break
        out, n = cut_and_fill(out, out.vertices[np.unique(fe)], radius_mm, speck_mm=speck_mm)
        if n == 0:
            break
        removed += n
    return out, _step("folds", mesh, out, fold_edges=found, faces_removed=removed, radius_mm=float(radius_mm))


def _clear_slivers(mesh, target_mm, *, speck_mm, feature_deg, min_angle, max_rounds=3):
    """Cut out and fill the faces below ``min_angle`` left by remeshing, then remesh once more."""
    best, best_angle = mesh, mesh_quality(mesh)["min_angle_deg"]
    out, rounds = mesh, 0
    while best_angle < min_angle and rounds < max_rounds:
        rounds += 1
        bad = triangle_angles(out).min(axis=1) < min_angle
        cut, n = cut_and_fill(out, out.vertices[np.unique(out.faces[bad])], 2.0 * target_mm, speck_mm=speck_mm)
        if n == 0:
            break
        out, _ = remesh_mesh(cut, target_mm, feature_deg=feature_deg, min_angle=min_angle, max_passes=1)
        angle = mesh_quality(out)["min_angle_deg"]
        if angle > best_angle:
            best, best_angle = out, angle
    return best, _step("slivers", mesh, best, rounds=rounds)


def _remesh_step(mesh, target_mm, voxel_size, feature_deg, min_angle, keep_volume):
    """Folds cleared, isotropic remeshing, slivers cleared, volume restored: ``(Mesh, [records])``."""
    speck = 3.0 * voxel_size
    out, folds = _clear_folds(mesh, 2.0 * target_mm, speck_mm=speck)
    out, rec = remesh_mesh(out, target_mm, feature_deg=feature_deg, min_angle=min_angle)
    recs = [folds, rec]
    if rec["min_angle_deg"][1] < min_angle:
        out, slivers = _clear_slivers(out, target_mm, speck_mm=speck, feature_deg=feature_deg, min_angle=min_angle)
        recs.append(slivers)
    if keep_volume:
        remeshed = out
        out = _restore_volume(remeshed, mesh.volume)
        rec["normal_offset_mm"] = (mesh.volume - remeshed.volume) / remeshed.area
        rec["volume_change_pct"] = 100.0 * (out.volume - mesh.volume) / mesh.volume
    return out, recs


#: The adaptive remeshing's figures, in voxels: the chord error the sizing field allows where the surface
#: curves, the smallest edge it may ask for, and how far a flip of the final clean-up may move the surface.
#: Measured at 1 mm (dino photos): chord 0.1 and smallest edge 0.35 gave 28 600 faces, max deviation
#: 0.72 voxel, 23.4 degrees; chord 0.05: 47 580 faces, 0.70 voxel, 3x the time.
CHORD_VOXELS, MIN_EDGE_VOXELS, FLIP_VOXELS = 0.1, 0.35, 0.25


#: Mean distance (voxels) of the smoothed surface's vertices from the raw one above which the raw surface is
#: taken for an occupancy's staircase.  Measured: marching cubes of a boolean ball 0.092; of sub-voxel hull
#: fields 0.011-0.030 (sample at 1 and 0.25 mm, dino at 1 mm), of a clipped distance field 0.025.
STAIRCASE_VOXELS = 0.06


def _staircase(smoothed, raw, voxel_size):
    """``(staircase, thin)``: True when Taubin smoothing moved ``raw`` off itself as it does an occupancy's
    staircase; True when it took a vertex through a thin part of it (:func:`._thin.crossed`), from the same
    sample of the smoothed vertices."""
    step = max(1, len(smoothed.vertices) // 5000)
    sub = np.arange(0, len(smoothed.vertices), step)
    ref = _surface(raw)
    _, d, face = ref.closest(smoothed.vertices[sub])
    return bool(d.mean() > STAIRCASE_VOXELS * voxel_size), bool((~same_side(ref, face, ref.vertex_normal_sums()[sub])).any())


def _adaptive_step(mesh, target_mm, voxel_size, min_angle, keep_volume, reference, guide=None):
    """Adaptive remeshing (:mod:`._remesh`) of ``mesh`` (smoothed) onto ``reference`` (the repaired raw
    surface), its volume restored to the reference's: ``(Mesh, [records])``.

    The sizing field comes from the smoothed surface (the raw one's normals turn by whole voxel steps),
    carried to the reference's vertices; the vertices are projected onto the reference itself.  ``guide``:
    the surface the sizing field comes from instead of ``mesh`` (the same faces; ``mesh`` with thin parts put
    back at their raw places, ._thin, whose normals turn by voxel steps there: the dino at 1 mm, 48 142 faces
    and twice the time from ``mesh``, 34 298 from the smoothed surface).
    """
    # the remesher's decisions (split, collapse, flip) are discrete: its input is rounded to float32, as
    # pymeshlab stored it, so that two runs whose calibrations differ in the last bits (OpenCV's threads:
    # raw vertices 4e-6 mm apart) give the same mesh (tests/test_api.py's snippet against the CLI)
    same = reference is mesh
    mesh = _moved(Mesh(mesh.vertices.astype(np.float32).astype(np.float64), mesh.faces), mesh)
    if not same:
        exact = reference
        reference = _moved(Mesh(reference.vertices.astype(np.float32).astype(np.float64), reference.faces), exact)
        if exact in _SURFACES:  # its centroid tree (built for _staircase) serves the rounded copy: one build fewer
            _SURFACES[reference] = _Surface(reference, tree=_SURFACES[exact].tree)
    else:
        reference = mesh
    lo = min(target_mm, MIN_EDGE_VOXELS * voxel_size)
    if guide is not None:  # rounded as the start is
        guide = Mesh(guide.vertices.astype(np.float32).astype(np.float64), guide.faces)
    h = sizing_field(mesh if guide is None else guide, max_mm=target_mm, min_mm=lo, tol_mm=CHORD_VOXELS * voxel_size)
    if reference is not mesh and len(reference.vertices) != len(mesh.vertices):
        smoothed = _Surface(mesh)
        _, _, face = smoothed.closest(reference.vertices)
        h = h[smoothed.f[face]].min(axis=1)
    # else: the smoothed surface has the reference's vertices, moved: the sizing carries over by index
    out = _oriented(adaptive_remesh(mesh, reference, h, min_angle=min_angle, tol_mm=FLIP_VOXELS * voxel_size))
    out = fit_faces(out, reference, min_angle=min_angle)
    recs = []
    if mesh_quality(out)["min_angle_deg"] < min_angle:
        # what the local clean-up could not fix (0.25 mm sample: a few faces, now and then): more rounds of it;
        # then the faces within a radius of those left are cut out, the holes filled, and cleaned up again: first
        # with radii lo, 2 lo, ... below one target edge, the first whose result reaches the angle and stays within
        # a voxel of the reference there (._guard.near_deviation) kept; else with one target edge, as before.
        # (0.25 mm sample: one target edge is 2.8 voxels; its fill closed a 0.5 mm tunnel under a wall 0.08-0.2 mm
        # thin, by a 0.1 mm pocket, 2.1 voxels off the raw surface; a cut of lo: 0.6-0.7 voxel, 21.3 degrees.)
        # (local: the former whole-mesh pymeshlab pass took the 0.25 mm sample to 89 984 faces, 3.3 voxels off)
        before = out
        tol = FLIP_VOXELS * voxel_size
        out = _oriented(fix_slivers(out, reference, target_mm=lo, min_angle=min_angle, tol_mm=tol, rounds=12))
        cut, radius = 0, 0.0
        if mesh_quality(out)["min_angle_deg"] < min_angle:
            bad = triangle_angles(out).min(axis=1) < min_angle
            seeds, base, r = out.vertices[np.unique(out.faces[bad])], out, lo
            first = None  # the smallest cut that reaches the angle, kept when none stays within a voxel too
            while True:
                r = min(r, target_mm)
                filled, n = cut_and_fill(base, seeds, r, speck_mm=3.0 * voxel_size)
                if n:
                    fixed = _oriented(fix_slivers(filled, reference, target_mm=lo, min_angle=min_angle, tol_mm=tol,
                                                  rounds=12))
                    angle_ok = mesh_quality(fixed)["min_angle_deg"] >= min_angle
                    if angle_ok and first is None:
                        first = fixed, n, r
                    if r >= target_mm or (angle_ok and near_deviation(
                            fixed, reference, seeds, 2.0 * r + target_mm, voxel_size=voxel_size) < 1.0):
                        out, cut, radius = (fixed, n, r) if angle_ok or first is None else first
                        break
                if r >= target_mm:
                    if first is not None:
                        # no cut both reaches the angle and stays within a voxel: the smallest that reaches the angle
                        # (the last step, ._guard.keep_on_data, then puts the raw points it lost back)
                        out, cut, radius = first
                    break
                r *= 2.0
        recs.append(_step("slivers", before, out, faces_cut=int(cut), cut_radius_mm=float(radius)))
    rec = _step("remesh", mesh, out, method="adaptive", onto="raw" if reference is not mesh else "smoothed",
                target_mm=float(target_mm), min_edge_mm=float(lo),
                edge_mm_p10_p50=[round(float(np.percentile(h, 10)), 4), round(float(np.percentile(h, 50)), 4)])
    if keep_volume:
        remeshed = out
        out = _restore_volume(remeshed, reference.volume)
        rec["normal_offset_mm"] = (reference.volume - remeshed.volume) / remeshed.area
        rec["volume_change_pct"] = 100.0 * (out.volume - mesh.volume) / mesh.volume
    return out, [rec] + recs


#: Finishing surfaces of at least this many raw faces hands the heap's free pages back (:func:`release_heap`):
#: the sample at 0.5 mm and finer (the faces grow at least 4x per halving from 57 724 at 1 mm).  Below, it frees
#: tens of MB, and the trim cost the viewer's 1 mm update 3-11 ms CPU, 10-38 ms wall (a loaded machine).
_TRIM_FACES = 200_000


def release_heap() -> None:
    """Hand the C heap's free pages back to the system (glibc's ``malloc_trim``; nothing elsewhere).

    Finishing a fine surface frees hundreds of MB of arrays that glibc keeps in the heap (arrays freed
    in another order than they came): the process's resident set stayed ~250 MB above what it held at
    0.25 mm, and the next large allocation (the occupancy, 251 MB) made the whole command's peak.
    """
    import ctypes
    import sys

    if sys.platform.startswith("linux"):
        try:
            ctypes.CDLL("libc.so.6").malloc_trim(0)
        except (OSError, AttributeError):
            pass


def _check_mesh(mesh):
    if not isinstance(mesh, Mesh):
        raise TypeError(f"expected an organlab.surface.Mesh, got {type(mesh).__name__}")
    if len(mesh.faces) == 0:
        raise OrganlabError("the mesh has no faces: nothing to repair (is the model empty?)")


def finish_surface(
    mesh: Mesh,
    *,
    voxel_size: float,
    repair: bool = True,
    smooth: bool = True,
    remesh: Literal["auto"] | float | None = "auto",
    feature_deg: float = 60.0,
    min_angle: float = 20.0,
    keep_volume: bool = True,
    min_edge_mm: float = 0.75,
) -> FinishedSurface:
    """A repaired, watertight, manifold surface fit for finite-element meshing.

    Runs :func:`repair_mesh`, :func:`smooth_mesh` (Taubin) and the
    remeshing in that order.  A closed, manifold surface is remeshed
    adaptively onto the repaired raw surface (:mod:`._remesh`): the edge is
    ``remesh`` where the surface is flat and shorter where it curves (a
    chord strays at most 0.1 voxel, edges down to 0.35 voxel), every vertex
    is projected onto the raw surface, each vertex is then moved along its
    normal by its faces' mean gap to it (the faces, not only the vertices,
    on the data), and the few faces still below ``min_angle`` are fixed
    locally (flips, collapses, relaxation).  The smoothed surface only
    guides the edge lengths and the start, except for an occupancy's
    staircase (smoothing moves it more than 0.06 voxel on average), which
    is remeshed onto the smoothed surface.  An open surface (``repair=False``)
    goes through pymeshlab's isotropic remeshing, folds cut out, as before.
    With ``keep_volume``, the raw volume is restored by a uniform offset.

    Parameters
    ----------
    mesh : Mesh
        E.g. the marching-cubes mesh of :func:`mesh_from_volume`; world frame, mm.
    voxel_size : float, mm
        Voxel edge of the model the mesh came from: scales the defaults.
    repair, smooth : bool
    remesh : 'auto' or float or None
        Target edge length, mm (``'auto'``: 1.5 voxels but at least
        ``min_edge_mm``; ``None``: no remeshing).
    feature_deg, min_angle : float, degrees
        ``min_angle``: the smallest triangle angle to reach; ``feature_deg``:
        see :func:`remesh_mesh` (the pymeshlab path only).
    min_edge_mm : float, mm
        Smallest automatic target edge: about what one pixel of the views
        resolves at the specimen (``organlab reconstruct`` and the viewer pass
        their cameras' :func:`organlab.pipeline.pixel_footprint`; the default
        0.75 mm is about the bundled sample's 0.69 mm); shorter edges add
        faces, not shape (at 0.25 mm voxels: 4x the faces and twice the time
        for 0.004 mm closer to the raw surface).
    keep_volume : bool
        After remeshing, offset the surface along its normals (by thousandths
        to hundredths of a mm) so that it encloses the repaired raw (or, for
        a staircase, the smoothed) surface's volume again, its parts thinner
        than 0.6 voxel made that thick (:func:`._thin.thickened`).

    Returns
    -------
    FinishedSurface
        ``mesh`` (the finished surface, oriented outward), ``steps`` (what each
        step changed), ``raw`` and ``final`` quality (:func:`mesh_quality`),
        ``watertight``, ``volume_change_pct`` and ``deviation`` (how far the
        finished surface lies from the raw one, in voxels:
        :func:`surface_deviation`); ``to_dict()`` is the report's ``surface``.

    Examples
    --------
    >>> import numpy as np
    >>> import organlab as ol
    >>> grid = ol.VoxelGrid(origin=(-24.0, -24.0, -24.0), voxel_size=2.0, shape=(25, 25, 25))
    >>> x, y, z = np.meshgrid(*grid.axes(), indexing="ij")
    >>> ball = x**2 + y**2 + z**2 <= 20.0**2  # a sphere of radius 20 mm: 33 510 mm^3
    >>> fin = ol.finish_surface(ol.mesh_from_field(ball, grid), voxel_size=2.0)
    >>> fin.mesh.is_watertight, fin.watertight, round(fin.mesh.volume)  # the raw mesh's volume is kept
    (True, True, 33297)
    >>> fin.deviation["mean_voxels"] < 0.25 and fin.deviation["max_voxels"] < 1.0  # on the raw surface
    True
    """
    if not (isinstance(voxel_size, (int, float)) and voxel_size > 0):
        raise ValueError(f"voxel_size must be a positive number of mm, got {voxel_size!r}")
    if remesh == "auto":
        remesh = max(1.5 * float(voxel_size), float(min_edge_mm))
    out, steps = mesh, []
    if repair:
        out, rec = repair_mesh(out, speck_mm=3.0 * voxel_size)
        steps.append(rec)
    repaired = out  # the deviation is measured against the raw surface less the specks repair drops
    if smooth:
        out, rec = smooth_mesh(out)
        steps.append(rec)
    if remesh is not None:
        q = mesh_quality(out)
        if not (q["boundary_edges"] or q["nonmanifold_edges"] or q["nonmanifold_vertices"] or q["misoriented_edges"]):
            ref, guide = repaired, None
            if smooth and repaired is not out and len(repaired.faces):
                stair, thin = _staircase(out, repaired, float(voxel_size))
                if thin:  # smoothing took vertices through a thin part: they go back to their raw places (._thin)
                    smoothed = out
                    # parts thinner than MIN_THICK_VOXELS made that thick first, the surface remeshed onto (._thin)
                    # (its volume is the one restored: a raw lace holds less than the part; 1 mm balls with coverage
                    # fins 0.4-0.5 voxel thick: the raw 4.1-4.4 % under the true volume, the finished up to 1 % more)
                    ref, thick = thickened(repaired, 0.5 * float(voxel_size), MIN_THICK_VOXELS * float(voxel_size))
                    out, n = keep_thin(smoothed, ref, depth=0.5 * float(voxel_size))
                    steps.append(_step("thin", smoothed, out, vertices_kept=n, vertices_thickened=thick))
                    guide = smoothed if n else None  # the edge lengths from the smoothed surface
                if stair:
                    ref = out  # an occupancy's staircase is not data: the smoothed surface is the one to stay on
            out, recs = _adaptive_step(out, float(remesh), float(voxel_size), min_angle, keep_volume, ref, guide)
        else:  # an open or non-manifold surface (repair=False): pymeshlab's remeshing, folds cut out
            out, recs = _remesh_step(out, float(remesh), voxel_size, feature_deg, min_angle, keep_volume)
        steps += recs
        q = mesh_quality(out)
        if repair and (q["boundary_edges"] or q["nonmanifold_edges"] or q["nonmanifold_vertices"]):
            out, rec = repair_mesh(out, speck_mm=3.0 * voxel_size)
            steps.append(rec)
    raw, final = mesh_quality(mesh), mesh_quality(out)
    d_out, d_in = _distances(out, repaired, _surface(repaired))  # surface_deviation's, kept for the last step
    deviation = _deviation_figures(d_out, d_in, float(voxel_size))
    if repair and remesh is not None and deviation["max_voxels"] >= 1.0 and not final["boundary_edges"]:
        # issue 21's promise (1 voxel at most): the raw points the finishing lost put back, see ._guard
        out, rec, deviation = keep_on_data(out, repaired, voxel_size=float(voxel_size), min_angle=min_angle,
                                           target_mm=min(float(remesh), MIN_EDGE_VOXELS * float(voxel_size)),
                                           deviation=deviation, distances=(d_out[:len(out.vertices)], d_in))
        steps.append(rec)
        final = mesh_quality(out)
    _SURFACES.clear()  # the closest-point trees (0.25 mm: ~100 MB for the raw surface) are not kept past the call
    if len(mesh.faces) >= _TRIM_FACES:
        release_heap()
    if mesh.vertex_colors is not None:
        from scipy.spatial import cKDTree

        _, idx = cKDTree(mesh.vertices).query(out.vertices)
        out = Mesh(out.vertices, out.faces, np.asarray(mesh.vertex_colors)[idx])
    return FinishedSurface(
        mesh=out, steps=steps, raw=raw, final=final,
        watertight=bool(out.is_watertight and final["nonmanifold_vertices"] == 0),
        volume_change_pct=100.0 * (final["volume_mm3"] - raw["volume_mm3"]) / raw["volume_mm3"],
        deviation=deviation)


@dataclass(frozen=True)
class FinishedSurface:
    """What :func:`finish_surface` made, and its figures.

    Attributes
    ----------
    mesh : Mesh
        The finished surface, world frame, mm, oriented outward.
    steps : list of dict
        What each step changed (repair, smooth, folds, remesh, slivers).
    raw, final : dict
        :func:`mesh_quality` of the input and of ``mesh``.
    watertight : bool
        Closed, edge- and vertex-manifold.
    volume_change_pct : float, %
        ``mesh``'s volume against the input's.
    deviation : dict
        :func:`surface_deviation` of ``mesh`` from the input (less the specks repair drops), voxels.

    Unpacking gives ``(mesh, to_dict())``, the ``(Mesh, dict)`` pair this function returned before.
    """

    mesh: Mesh
    steps: list = field(default_factory=list)
    raw: dict = field(default_factory=dict)
    final: dict = field(default_factory=dict)
    watertight: bool = False
    volume_change_pct: float = 0.0
    deviation: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        """The report's ``surface`` entry (``report.json``)."""
        return {"steps": list(self.steps), "raw": dict(self.raw), "final": dict(self.final), "watertight": self.watertight,
                "volume_change_pct": self.volume_change_pct, "deviation": dict(self.deviation)}

    def __iter__(self):
        return iter((self.mesh, self.to_dict()))


# ------------------------------------------------------- folds: cut and fill (see ._folds)
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

    tree = cKDTree(seeds)
    d, _ = tree.query(mesh.vertices)
    keep = ~(d < radius_mm)[mesh.faces].any(axis=1)
    # only the pieces the cut touches are repaired: the others are not its specks (1 mm dino: a separate piece 57 mm
    # from the cut, under speck_mm after remeshing, was dropped, 3.1 voxels of raw surface lost)
    f, nv = np.asarray(mesh.faces, dtype=np.int64), len(mesh.vertices)
    piece = _pieces(f, nv)[1][f[:, 0]]
    touched = np.isin(piece, piece[~keep])
    if not (keep & touched).any():  # the cut takes whole pieces (a fin's shreds): nothing of them to fill
        return mesh, 0
    rep, _ = repair_mesh(Mesh(mesh.vertices, f[keep & touched]), speck_mm=speck_mm)
    if not touched.all():
        used, rest = np.unique(f[~touched], return_inverse=True)
        rep = Mesh(np.concatenate([rep.vertices, mesh.vertices[used]]),
                   np.concatenate([rep.faces, rest.reshape(-1, 3) + len(rep.vertices)]))
    q = mesh_quality(rep)
    if q["boundary_edges"] or q["nonmanifold_edges"] or q["nonmanifold_vertices"]:
        return mesh, 0
    d, _ = tree.query(rep.vertices)
    out = _moved(Mesh(_laplace(rep.vertices, rep.faces, d < 1.5 * radius_mm, iterations), rep.faces), rep)
    return out, int((~keep).sum())


def warm_kernels() -> None:
    """Load :func:`finish_surface`'s numba kernels from their cache, ahead of its first call.

    Finishes a ball of 4.5 voxels' radius in a 13^3 grid: the dtypes and layouts the stage passes, so
    the same compiled specialisations (21 kernels: the remesher's, the closest-point grid's, the
    smoothing's).  The first ``finish_surface`` of a process spends about 0.12 s CPU loading them
    (sample, 1 mm: first call 0.57-0.61 s, later ones 0.38-0.44 s); the ``reconstruct`` command calls
    this on its loading thread while the silhouettes and the hull run (issue 24).

    Examples
    --------
    >>> from organlab.surface import warm_kernels
    >>> warm_kernels()
    """
    grid = VoxelGrid((-6.0, -6.0, -6.0), 1.0, (13, 13, 13))
    x, y, z = np.meshgrid(*grid.axes(), indexing="ij")
    ball = (4.5 - np.sqrt(x**2 + y**2 + z**2)).astype(np.float32)
    finish_surface(mesh_from_field(ball, grid), voxel_size=1.0)
