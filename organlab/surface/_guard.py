"""The finished surface's last step (``stay_on_data``): the spots more than a voxel off the raw surface put back.

The remesher's sliver step cuts out, fills and relaxes what it cannot fix and flattens knife edges, without
projecting back onto the raw surface: on the 0.25 mm sample and the 1 mm dino that shaved thin parts by 2.2-2.5
voxels (raw vertices with no finished surface within a voxel).  :func:`insert_lost` puts such raw points back as
vertices (the closest finished face split in three at each, then :func:`._remesh.fix_slivers`);
:func:`pull_back` moves the vertices still more than :data:`LIMIT_VOXELS` off onto the raw surface, spread over
their rings; a move that would leave a face below the smallest angle (and worse than before) or turn a face over
is halved, then refused.  :func:`keep_on_data` runs the rounds and keeps the closest surface that keeps the angle,
closed and manifold.

The step is local: the points more than :data:`LIMIT_VOXELS` apart are found once (from the distances
``finish_surface`` measured the deviation with), and the rounds query and move only the finished faces within six
median edges of them and the raw vertices near them; the kept surface is measured whole once.  The same surfaces
as whole-surface rounds, bit for bit, on the 0.25 mm sample, the 1 mm dino and the finned balls of
tests/test_finish_deviation.py; at 0.25 mm the step takes 3.4 s CPU instead of 19.4 (2026-12-03, load 17-19).

:func:`near_deviation` measures a patch the same two ways: the sliver step (``_repair._adaptive_step``) keeps the
smallest cut whose result stays within a voxel there, so that the cut itself no longer fills over a thin part (the
0.25 mm sample: a cut of 2.8 voxels over a tunnel under a sub-voxel wall, 2.1 voxels off; now 0.35 voxel, 0.6-0.7
voxel off, and this step does not run).
"""

from __future__ import annotations

import numpy as np

from ._deviation import _distances, _Surface, _surface, surface_deviation
from ._mesh import Mesh
from ._quality import mesh_quality
from ._remesh import _face_min_angles, fix_slivers

#: Vertices farther than this many voxels from the other surface are moved (a margin under the promised 1).
LIMIT_VOXELS = 0.9


def _normals(V, F):
    n = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    return n / (np.linalg.norm(n, axis=1, keepdims=True) + 1e-300)


def pull_back(mesh: Mesh, reference: _Surface, *, voxel_size: float, min_angle: float, rounds: int = 6,
              spread: int = 2, points: np.ndarray | None = None, seeds: np.ndarray | None = None, reach: float = 0.0):
    """``(Mesh, record)``: ``mesh``'s vertices more than :data:`LIMIT_VOXELS` off ``reference`` moved onto it.

    ``mesh``: closed and manifold, world frame, mm; ``reference``: the repaired raw surface, prepared for
    closest-point queries.  The record counts the vertices moved each way and the faces whose move was refused.
    ``points``, ``seeds``, ``reach``: as :func:`insert_lost`'s (the raw vertices tested, the finished faces
    within ``reach`` of ``seeds`` the only ones tested and moved).
    """
    V = np.array(mesh.vertices, dtype=np.float64)
    F = np.asarray(mesh.faces, dtype=np.int64)
    lim = LIMIT_VOXELS * float(voxel_size)
    start_angles = _face_min_angles(V, F)
    start_normals = _normals(V, F)
    moved_out = moved_in = refused = 0
    loc = np.arange(len(F)) if seeds is None else np.flatnonzero(_local(V, F, seeds, reach))
    vloc = np.unique(F[loc])
    pts = reference.v if points is None else reference.v[np.asarray(points, dtype=np.int64)]
    from scipy.sparse import coo_matrix

    e = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    adj = coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(len(V), len(V))).tocsr()
    adj = ((adj + adj.T) > 0).astype(np.float64)
    for _ in range(int(rounds)):
        target = V.copy()
        # the finished surface's vertices too far from the raw one: onto their closest raw point
        q, dl, _ = reference.closest(V[vloc])
        far = np.zeros(len(V), dtype=bool)
        far[vloc[dl > lim]] = True
        target[vloc[dl > lim]] = q[dl > lim]
        # the raw vertices too far from the finished surface: the nearest vertex of their closest face onto them
        _, din, face = _Surface(Mesh(V, F[loc])).closest(pts)
        lost = np.nonzero(din > lim)[0]
        if len(lost):
            p = pts[lost]
            tri = F[loc[face[lost]]]
            k = np.argmin(np.linalg.norm(V[tri] - p[:, None, :], axis=2), axis=1)
            vid = tri[np.arange(len(lost)), k]
            # one raw point per vertex: the farthest one it lost
            order = np.argsort(din[lost])
            target[vid[order]] = p[order]
        move = np.union1d(np.nonzero(far)[0], vid if len(lost) else np.empty(0, dtype=np.int64))
        if not len(move):
            break
        # the move spread over the rings around (halved per ring) so that the neighbours follow and the
        # triangles keep their shape: a lone vertex pulled two voxels out is a spike with slivers around it
        D = np.zeros_like(V)
        D[move] = target[move] - V[move]
        fixed = np.zeros(len(V), dtype=bool)
        fixed[move] = True
        for _ in range(int(spread)):
            S = adj @ D
            cnt = adj @ (np.abs(D).sum(axis=1) > 0).astype(np.float64)
            grow = ~fixed & (cnt > 0)
            D[grow] = 0.5 * S[grow] / cnt[grow, None]
            fixed |= grow
        W = V + D
        step = fixed
        near = np.nonzero(step[F].any(axis=1))[0]  # only the faces of moved vertices change
        Fn = F[near]
        for attempt in range(30):
            a = _face_min_angles(W, Fn)
            flipped = np.einsum("ij,ij->i", _normals(W, Fn), start_normals[near]) < 0.0
            bad = ((a < min_angle) & (a < start_angles[near] - 1e-9)) | flipped
            if not bad.any():
                break
            vb = np.unique(Fn[bad])
            vb = vb[step[vb]]
            if not len(vb):  # cannot happen (only moved vertices change faces): give the round up
                W, step = V.copy(), np.zeros(len(V), dtype=bool)
                break
            if attempt < 3:
                W[vb] = 0.5 * (W[vb] + V[vb])
            else:
                W[vb] = V[vb]
                step[vb] = False
                refused += len(vb)
        moved_out += int((far & step).sum())
        moved_in += int((step & ~far & (np.abs(target - V).sum(axis=1) > 0)).sum())
        if np.array_equal(W, V):
            break
        V = W
    out = Mesh(V, F)
    return out, {"step": "pull_back", "limit_voxels": LIMIT_VOXELS, "vertices_moved_onto_raw": moved_out,
                 "vertices_moved_to_lost_raw": moved_in, "moves_refused": refused}


def _local(V, F, seeds, reach):
    """Faces of ``(V, F)`` with a corner within ``reach`` of a ``seeds`` point: ``(F,)`` bool."""
    from scipy.spatial import cKDTree

    d, _ = cKDTree(seeds).query(V, distance_upper_bound=reach)
    return np.isfinite(d)[F].any(axis=1)


def insert_lost(mesh: Mesh, reference: Mesh, *, voxel_size: float, min_angle: float, target_mm: float,
                rounds: int = 3, points: np.ndarray | None = None, seeds: np.ndarray | None = None,
                reach: float = 0.0):
    """``(Mesh, inserted)``: the raw surface's points the finished one lost (farther than :data:`LIMIT_VOXELS`)
    put back as vertices (the finished face closest to each split in three at it), then the local clean-up
    (:func:`._remesh.fix_slivers`: flips, collapses, relaxation onto ``reference``).

    ``points``: the indices of the raw vertices to test (default: all); ``seeds`` ``(S, 3)``, mm: the work is
    done on the finished faces within ``reach`` of them (the closest faces of ``points`` are among these, the
    clean-up starts from their faces below the angle and the new ones; default: every face)."""
    ref = _surface(reference)  # the raw surface's tree, built once per finishing (see ._deviation)
    lim = LIMIT_VOXELS * float(voxel_size)
    out, inserted = mesh, 0
    pts_idx = np.arange(len(ref.v)) if points is None else np.asarray(points, dtype=np.int64)
    for _ in range(int(rounds)):
        V = np.asarray(out.vertices, dtype=np.float64)
        F = np.asarray(out.faces, dtype=np.int64)
        region = None if seeds is None else _local(V, F, seeds, reach)
        loc = np.arange(len(F)) if region is None else np.flatnonzero(region)
        _, din, lface = _Surface(Mesh(V, F[loc])).closest(ref.v[pts_idx])
        face = loc[lface]
        lost = np.nonzero(din > lim)[0]
        if not len(lost):
            break
        # per face, its farthest lost raw point
        order = lost[np.argsort(din[lost])]
        pick = {}
        for i in order:
            pick[int(face[i])] = int(pts_idx[i])
        faces = np.fromiter(pick.keys(), dtype=np.int64)
        pts = ref.v[np.fromiter(pick.values(), dtype=np.int64)]
        new = len(V) + np.arange(len(faces))
        a, b, c = F[faces, 0], F[faces, 1], F[faces, 2]
        keep = np.ones(len(F), dtype=bool)
        keep[faces] = False
        F2 = np.concatenate([F[keep], np.stack([a, b, new], 1), np.stack([b, c, new], 1), np.stack([c, a, new], 1)])
        V2 = np.concatenate([V, pts])
        inserted += len(faces)
        only = None
        if region is not None:  # the region's faces, the new ones, and any face left below the angle elsewhere
            only = np.concatenate([region[keep], np.ones(3 * len(faces), dtype=bool)])
            only |= _face_min_angles(V2, F2) < min_angle
        out = fix_slivers(Mesh(V2, F2), reference, target_mm=target_mm, min_angle=min_angle,
                          tol_mm=0.1 * float(voxel_size), rounds=12, only=only)
    return out, inserted


def near_deviation(mesh: Mesh, reference: Mesh, seeds: np.ndarray, reach: float, *, voxel_size: float) -> float:
    """The largest distance, voxels, between ``mesh`` and ``reference`` about the ``seeds`` ``(S, 3)`` (mm), where
    ``mesh`` changed within ``reach`` (mm) of them: ``mesh``'s vertices and face centres within ``reach`` to
    ``reference``, and ``reference``'s vertices within ``reach`` + 2 voxels to ``mesh`` (its faces within ``reach`` +
    3 voxels) -- the two ways :func:`._deviation.surface_deviation` measures, on a patch.

    A raw point that a change within ``reach`` took more than a voxel from ``mesh`` was within a voxel of the changed
    faces before, so within ``reach`` + 1 voxel of the seeds; its closest face now is within another 2 voxels.  What
    :func:`._repair.cut_and_fill` changed, measured without a query of the whole surfaces (1 mm dino: 13 seeds, the
    same maximum as the whole surfaces' 3.14 voxels; a patch of ``reach`` alone for both found 0.80).
    """
    from scipy.spatial import cKDTree

    ref = _surface(reference)  # the raw surface's tree, built once per finishing (see ._deviation)
    seeds = np.asarray(seeds, dtype=np.float64).reshape(-1, 3)
    vs = float(voxel_size)
    mv, mf = np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64)
    loc = _local(mv, mf, seeds, reach)
    if not loc.any():
        return 0.0
    p = np.concatenate([mv[np.unique(mf[loc])], mv[mf[loc]].mean(axis=1)])
    _, a, _ = ref.closest(p)
    pts = np.unique(ref.f[ref.faces_within(seeds, reach + 3.0 * vs)])
    pts = pts[np.isfinite(cKDTree(seeds).query(ref.v[pts], distance_upper_bound=reach + 2.0 * vs)[0])]
    b = _Surface(Mesh(mv, mf[_local(mv, mf, seeds, reach + 3.0 * vs)])).closest(ref.v[pts])[1] if len(pts) else a[:1]
    return float(max(a.max(), b.max()) / vs)


def keep_on_data(mesh: Mesh, reference: Mesh, *, voxel_size: float, min_angle: float, target_mm: float,
                 rounds: int = 4, deviation: dict | None = None, distances: tuple | None = None):
    """``(Mesh, record, deviation)``: :func:`insert_lost` then :func:`pull_back`, ``rounds`` times at most, until the
    surface lies within 1 voxel of ``reference`` both ways; the closest of the rounds' surfaces (by the larger
    maximum, :func:`._deviation.surface_deviation`), or ``mesh`` itself when none is closer or none keeps
    ``min_angle`` (or ``mesh``'s own smallest angle, if lower).  ``deviation``: ``mesh``'s, if known; the one
    returned is the result's; ``distances``: ``mesh``'s vertices' distances to ``reference`` and ``reference``'s
    vertices' to ``mesh``, mm, if known (:func:`._deviation._distances`).

    Local: the points more than :data:`LIMIT_VOXELS` apart are found once over both whole surfaces; the rounds
    then test and move only the finished faces within a few edges of them and the raw vertices near them
    (the rest of the surface does not move), and the kept surface is measured whole once.
    """
    ref = _surface(reference)  # the raw surface's tree, built once per finishing (see ._deviation)
    lim = LIMIT_VOXELS * float(voxel_size)
    V, F = np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64)
    floor = min(float(min_angle), float(_face_min_angles(V, F).min()))
    best_dev = surface_deviation(mesh, reference, voxel_size=voxel_size, raw_surface=ref) if deviation is None \
        else deviation
    before = best_max = best_dev["max_voxels"]
    record = {"step": "stay_on_data", "max_voxels": [before, before], "rounds": 0, "vertices_inserted": 0,
              "vertices_moved": 0, "moves_refused": 0}
    if best_max < 1.0:
        return mesh, record, best_dev
    # where the two surfaces part: the raw vertices the finished surface lost, the finished vertices off the raw
    if distances is None:
        d_out, d_in = _distances(mesh, reference, ref)
        d_out = d_out[:len(V)]  # the vertices' (the face centres' follow)
    else:
        d_out, d_in = distances
    seeds = np.concatenate([ref.v[d_in > lim], V[d_out > lim]])
    if not len(seeds):  # only face centres are off: the whole-surface rounds' way has nothing to move either
        return mesh, record, best_dev
    # a few edges around them: the moves (a vertex and 2 rings) and the clean-up's flips and collapses stay there
    edge = float(np.median(np.linalg.norm(V[F[:, 1]] - V[F[:, 0]], axis=1)))
    reach = 6.0 * edge + 2.0 * lim
    from scipy.spatial import cKDTree

    d, _ = cKDTree(seeds).query(ref.v, distance_upper_bound=reach)
    points = np.flatnonzero(np.isfinite(d))
    near = dict(points=points, seeds=seeds, reach=reach)

    def local_max(m):  # the deviation where the rounds work (elsewhere the surface is the same)
        mv, mf = np.asarray(m.vertices), np.asarray(m.faces)
        loc = _local(mv, mf, seeds, reach)
        p = np.concatenate([mv[np.unique(mf[loc])], mv[mf[loc]].mean(axis=1)])
        _, a, _ = ref.closest(p)
        _, b, _ = _Surface(Mesh(mv, mf[loc])).closest(ref.v[points])
        return max(a.max(), b.max()) / float(voxel_size)

    best, best_local = mesh, local_max(mesh)
    m, inserted, pulled, refused, used = mesh, 0, 0, 0, 0
    for r in range(int(rounds)):
        if best_local < 1.0:
            break
        m, n = insert_lost(m, reference, voxel_size=voxel_size, min_angle=min_angle, target_mm=target_mm, rounds=1,
                           **near)
        m, rec = pull_back(m, ref, voxel_size=voxel_size, min_angle=min_angle, rounds=2, **near)
        inserted += n
        pulled += rec["vertices_moved_onto_raw"] + rec["vertices_moved_to_lost_raw"]
        refused += rec["moves_refused"]
        if _face_min_angles(np.asarray(m.vertices), np.asarray(m.faces)).min() < floor - 1e-9:
            continue
        lm = local_max(m)
        if lm < best_local:
            best, best_local, used = m, lm, r + 1
    if best is not mesh:
        q = mesh_quality(best)  # splits, flips, collapses and moves keep it closed and manifold: checked once
        if q["boundary_edges"] or q["nonmanifold_edges"] or q["nonmanifold_vertices"]:
            best, used = mesh, 0
        else:
            dev = surface_deviation(best, reference, voxel_size=voxel_size, raw_surface=ref)
            if dev["max_voxels"] < best_max:
                best_max, best_dev = dev["max_voxels"], dev
            else:
                best, used = mesh, 0
    record.update({"max_voxels": [before, best_max], "rounds": used, "vertices_inserted": inserted,
                   "vertices_moved": pulled, "moves_refused": refused})
    return best, record, best_dev
