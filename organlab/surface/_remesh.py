"""Adaptive isotropic remeshing that stays on the data (numba).

Botsch and Kobbelt's remeshing loop (split edges longer than 4/3 of their
target, collapse those shorter than 4/5, flip edges toward better triangles,
relax the vertices in their tangent planes), with two changes that keep the
result on the marching-cubes surface:

- the **target edge is per vertex** (a sizing field on the reference
  surface): the uniform edge ``max_mm`` where the surface is flat, shorter
  where it curves (an edge of length ``h`` across a radius ``R`` strays
  ``h^2 / (8 R)`` from it: ``h = sqrt(8 R tol)``), never below ``min_mm``,
  and graded (it grows by at most ``grade`` per mm away from a small one),
  so a fin thinner than ``max_mm`` keeps its rim;
- every relaxation step **projects each vertex back onto the reference
  surface** (its closest point, :mod:`._deviation`'s kernel), so no vertex
  drifts more than the chord error off it; a vertex whose closest point
  jumps further than half its edge (another sheet of a thin part) stays.

The local operations keep the mesh closed, manifold and consistently
oriented: a collapse obeys the link condition and refuses to flip or fold a
neighbouring face, a flip refuses a fold (faces more than ``flip_deg``
apart) or an existing edge.  The operations of one sweep run in one pass
over the faces; a face an operation changed is locked for the rest of that
sweep (so the vertex stars read at the sweep's start stay exact where they
are used), and the next sweep rebuilds the stars: every sweep is linear in
the faces.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from ..mesh import Mesh
from ._deviation import _Surface, _surface
from ._geom import _centroid, _normal, _normal3
from ._thin import same_side

#: The projections refuse a closest point on a face looking away from the vertex's (the other side of a thin part,
#: :func:`._thin.same_side`); False only to measure what that rule does (tests switch it off).
SAME_SIDE = True

# ------------------------------------------------------------------ small geometry helpers (a face's normal and
# centroid: ._geom, shared with ._deviation)


@njit(cache=True, inline="always")
def _sub(V, a, b):
    return V[a, 0] - V[b, 0], V[a, 1] - V[b, 1], V[a, 2] - V[b, 2]


@njit(cache=True, nogil=True)
def _cos3(ax, ay, az, bx, by, bz, cx, cy, cz):
    """Cosine of the angle at ``a`` of triangle ``abc`` (1.0 when an edge is degenerate)."""
    ux, uy, uz = bx - ax, by - ay, bz - az
    vx, vy, vz = cx - ax, cy - ay, cz - az
    d = (ux * ux + uy * uy + uz * uz) * (vx * vx + vy * vy + vz * vz)
    if d == 0.0:
        return 1.0
    return (ux * vx + uy * vy + uz * vz) / math.sqrt(d)


@njit(cache=True, nogil=True)
def _max_cos(V, a, b, c):
    """The largest cosine of triangle ``abc``'s angles (that of its smallest angle)."""
    ax, ay, az = V[a, 0], V[a, 1], V[a, 2]
    bx, by, bz = V[b, 0], V[b, 1], V[b, 2]
    cx, cy, cz = V[c, 0], V[c, 1], V[c, 2]
    return max(_cos3(ax, ay, az, bx, by, bz, cx, cy, cz), _cos3(bx, by, bz, cx, cy, cz, ax, ay, az),
               _cos3(cx, cy, cz, ax, ay, az, bx, by, bz))


@njit(cache=True, nogil=True)
def _stars(F, alive, nf, nv):
    """Vertex -> faces (CSR) of the alive faces."""
    cnt = np.zeros(nv + 1, dtype=np.int64)
    for f in range(nf):
        if alive[f]:
            for i in range(3):
                cnt[F[f, i] + 1] += 1
    for i in range(nv):
        cnt[i + 1] += cnt[i]
    lst = np.empty(cnt[nv], dtype=np.int64)
    pos = cnt[:nv].copy()
    for f in range(nf):
        if alive[f]:
            for i in range(3):
                v = F[f, i]
                lst[pos[v]] = f
                pos[v] += 1
    return cnt, lst


@njit(cache=True, nogil=True)
def _stars_of(F, alive, nf, nv, todo):
    """:func:`_stars` of the corners of faces ``todo`` only (every other vertex's star empty): the same lists
    for those, in two passes that write little (the splits of a sweep read no other star)."""
    need = np.zeros(nv, dtype=np.bool_)
    for f in todo:
        for i in range(3):
            need[F[f, i]] = True
    cnt = np.zeros(nv + 1, dtype=np.int64)
    for f in range(nf):
        if alive[f]:
            for i in range(3):
                v = F[f, i]
                if need[v]:
                    cnt[v + 1] += 1
    for i in range(nv):
        cnt[i + 1] += cnt[i]
    lst = np.empty(cnt[nv], dtype=np.int64)
    pos = cnt[:nv].copy()
    for f in range(nf):
        if alive[f]:
            for i in range(3):
                v = F[f, i]
                if need[v]:
                    lst[pos[v]] = f
                    pos[v] += 1
    return cnt, lst


@njit(cache=True, nogil=True)
def _other_face(F, alive, lock, start, lst, f, a, b):
    """The unlocked face holding the directed edge ``b -> a`` (the twin of ``f``'s ``a -> b``), or -1."""
    for k in range(start[a], start[a + 1]):
        q = lst[k]
        if q == f or not alive[q] or lock[q]:
            continue
        for j in range(3):
            if F[q, j] == b and F[q, (j + 1) % 3] == a:
                return q
    return -1


@njit(cache=True, nogil=True)
def _third(F, q, a, b):
    for j in range(3):
        v = F[q, j]
        if v != a and v != b:
            return v
    return -1


@njit(cache=True, nogil=True)
def _star_free(lock, start, lst, v):
    for k in range(start[v], start[v + 1]):
        if lock[lst[k]]:
            return False
    return True


@njit(cache=True, nogil=True)
def _segments_apart(V, a, b, c, d):
    """Distance between segments ``ab`` and ``cd`` (sampled: 9 points of ``cd`` against ``ab``)."""
    ux, uy, uz = _sub(V, b, a)
    uu = ux * ux + uy * uy + uz * uz
    best = np.inf
    for k in range(1, 10):
        t = k / 10.0
        px = V[c, 0] + t * (V[d, 0] - V[c, 0]) - V[a, 0]
        py = V[c, 1] + t * (V[d, 1] - V[c, 1]) - V[a, 1]
        pz = V[c, 2] + t * (V[d, 2] - V[c, 2]) - V[a, 2]
        s = min(max((px * ux + py * uy + pz * uz) / uu, 0.0), 1.0) if uu > 0 else 0.0
        qx, qy, qz = px - s * ux, py - s * uy, pz - s * uz
        best = min(best, qx * qx + qy * qy + qz * qz)
    return math.sqrt(best)


# ------------------------------------------------------------------ the three local operations


@njit(cache=True, nogil=True)
def _split_long(V, F, H, alive, lock, nv, nf, hi, todo, keep):
    """Split every edge longer than ``hi`` times its target (the longest of a face first).

    Visits the faces ``todo`` (ascending; those below ``nf`` at the start); marks in ``keep`` those
    with an edge to split (see :func:`_next_todo`).  Returns ``(nv, nf, full)``: ``full`` when the
    arrays ran out of room (the caller grows them).
    """
    # the stars of the faces' corners only (a split reads the star of its edge's first end): every sweep after the
    # first visits a few faces (0.25 mm sample: 100-9 000 of 940 000), whose stars cost a tenth of all of them
    start, lst = _stars_of(F, alive, nf, nv, todo) if 8 * len(todo) < nf else _stars(F, alive, nf, nv)
    for f in todo:
        if not alive[f] or lock[f]:
            continue
        best, bi = 0.0, -1
        for i in range(3):
            a, b = F[f, i], F[f, (i + 1) % 3]
            dx, dy, dz = _sub(V, a, b)
            h = hi * min(H[a], H[b])
            r = (dx * dx + dy * dy + dz * dz) / (h * h)
            if r > 1.0 and r > best:
                best, bi = r, i
        if bi < 0:
            continue
        keep[f] = True
        if nv + 1 > V.shape[0] or nf + 2 > F.shape[0]:
            return nv, nf, True
        a, b, c = F[f, bi], F[f, (bi + 1) % 3], F[f, (bi + 2) % 3]
        g = _other_face(F, alive, lock, start, lst, f, a, b)
        if g < 0:
            continue
        d = _third(F, g, a, b)
        m = nv
        nv += 1
        for k in range(3):
            V[m, k] = 0.5 * (V[a, k] + V[b, k])
        H[m] = min(H[a], H[b])
        F[f, 0], F[f, 1], F[f, 2] = a, m, c
        F[nf, 0], F[nf, 1], F[nf, 2] = m, b, c
        F[g, 0], F[g, 1], F[g, 2] = b, m, d
        F[nf + 1, 0], F[nf + 1, 1], F[nf + 1, 2] = m, a, d
        alive[nf] = alive[nf + 1] = True
        lock[f] = lock[g] = lock[nf] = lock[nf + 1] = True
        nf += 2
    return nv, nf, False


@njit(cache=True, nogil=True)
def _collapse_short(V, F, H, alive, valive, lock, nv, nf, lo, hi, cos_turn, force, todo, keep, geo=None):
    """Collapse every edge shorter than ``lo`` times its target into its midpoint, where that is safe.

    Safe: the link condition (the two ends share only the two opposite vertices), those two keep
    more than 3 neighbours, no edge of the new star longer than ``hi`` times its target, and no
    face of the star turns by more than ``acos(cos_turn)`` (a flip or a fold).  With ``force`` (one
    flag per face, or empty), only the flagged faces' shortest edges are collapsed, whatever their
    length, where the star's smallest angle grows.  Visits the faces ``todo`` (ascending); marks in
    ``keep`` those with an edge to collapse, and in ``geo`` (if given) those whose collapse was refused by
    the shape of the stars of its ends and of the two opposite vertices, not by a lock (see :func:`_retest`).
    Returns collapses done.
    """
    start, lst = _stars(F, alive, nf, nv)
    done = 0
    mark = np.full(V.shape[0], -1, dtype=np.int64)  # mark[v] == f: v is a neighbour of a (f's candidate edge ab)
    forced = len(force) > 0
    for f in todo:
        if not alive[f] or lock[f] or (forced and not force[f]):
            continue
        best, bi = (np.inf if forced else 1.0), -1
        for i in range(3):
            a, b = F[f, i], F[f, (i + 1) % 3]
            dx, dy, dz = _sub(V, a, b)
            h = lo * min(H[a], H[b])
            r = (dx * dx + dy * dy + dz * dz) / (h * h)
            if r < best:
                best, bi = r, i
        if bi < 0:
            continue
        keep[f] = True
        a, b, c = F[f, bi], F[f, (bi + 1) % 3], F[f, (bi + 2) % 3]
        if not (_star_free(lock, start, lst, a) and _star_free(lock, start, lst, b)
                and _star_free(lock, start, lst, c)):
            continue
        g = _other_face(F, alive, lock, start, lst, f, a, b)
        if g < 0:
            continue
        d = _third(F, g, a, b)
        if not _star_free(lock, start, lst, d):
            continue
        if geo is not None:
            geo[f] = True  # from here on, a refusal reads the stars of a, b, c and d only (cleared if done)
        if start[c + 1] - start[c] <= 3 or start[d + 1] - start[d] <= 3:
            continue
        # link condition: the neighbours of a and of b share c and d only (a star of 32 faces or more: refused,
        # as when the neighbours were listed in an array of 64)
        if 2 * (start[a + 1] - start[a]) >= 64:
            continue
        for k in range(start[a], start[a + 1]):
            q = lst[k]
            for j in range(3):
                mark[F[q, j]] = f
        ok = True
        for k in range(start[b], start[b + 1]):
            q = lst[k]
            for j in range(3):
                v = F[q, j]
                if v != b and v != a and mark[v] == f and v != c and v != d:
                    ok = False
        if not ok:
            continue
        worst_old = 0.0
        if forced:
            for s in (a, b):
                for k in range(start[s], start[s + 1]):
                    q = lst[k]
                    worst_old = max(worst_old, _max_cos(V, F[q, 0], F[q, 1], F[q, 2]))
        px = 0.5 * (V[a, 0] + V[b, 0])
        py = 0.5 * (V[a, 1] + V[b, 1])
        pz = 0.5 * (V[a, 2] + V[b, 2])
        hnew = min(H[a], H[b])
        # the new star: every face of a or b except f and g, with a or b moved to p
        for s in (a, b):
            if not ok:
                break
            for k in range(start[s], start[s + 1]):
                q = lst[k]
                if q == f or q == g:
                    continue
                i0 = 0
                for j in range(3):
                    if F[q, j] == s:
                        i0 = j
                u, w = F[q, (i0 + 1) % 3], F[q, (i0 + 2) % 3]
                for o in (u, w):
                    ex, ey, ez = V[o, 0] - px, V[o, 1] - py, V[o, 2] - pz
                    h = hi * min(hnew, H[o])
                    if ex * ex + ey * ey + ez * ez > h * h:
                        ok = False
                n0 = _normal3(V[s, 0], V[s, 1], V[s, 2], V[u, 0], V[u, 1], V[u, 2], V[w, 0], V[w, 1], V[w, 2])
                n1 = _normal3(px, py, pz, V[u, 0], V[u, 1], V[u, 2], V[w, 0], V[w, 1], V[w, 2])
                l0 = math.sqrt(n0[0] ** 2 + n0[1] ** 2 + n0[2] ** 2)
                l1 = math.sqrt(n1[0] ** 2 + n1[1] ** 2 + n1[2] ** 2)
                if l0 == 0.0 or l1 == 0.0 or (n0[0] * n1[0] + n0[1] * n1[1] + n0[2] * n1[2]) < cos_turn * l0 * l1:
                    ok = False
                    break
                if forced:
                    c0 = _cos3(px, py, pz, V[u, 0], V[u, 1], V[u, 2], V[w, 0], V[w, 1], V[w, 2])
                    c1 = _cos3(V[u, 0], V[u, 1], V[u, 2], V[w, 0], V[w, 1], V[w, 2], px, py, pz)
                    c2 = _cos3(V[w, 0], V[w, 1], V[w, 2], px, py, pz, V[u, 0], V[u, 1], V[u, 2])
                    if max(c0, c1, c2) >= worst_old:
                        ok = False
                        break
        if not ok:
            continue
        if geo is not None:
            geo[f] = False
        for k in range(start[b], start[b + 1]):
            q = lst[k]
            for j in range(3):
                if F[q, j] == b:
                    F[q, j] = a
            lock[q] = True
        for k in range(start[a], start[a + 1]):
            lock[lst[k]] = True
        alive[f] = alive[g] = False
        V[a, 0], V[a, 1], V[a, 2] = px, py, pz
        H[a] = hnew
        valive[b] = False
        done += 1
    return done


@njit(cache=True, nogil=True)
def _flip_edges(V, F, alive, lock, nv, nf, cos_fold, gain, cos_good, tol, todo, keep, geo=None):
    """Flip an edge to the other diagonal of its two faces where the smallest angle grows by ``gain``.

    Only across edges whose faces are less than ``acos(cos_fold)`` apart (a ridge or a thin part's rim is
    kept), never onto an existing edge, never turning a new face against the old ones.  Visits the faces
    ``todo`` (ascending); marks in ``keep`` those with an angle below ``acos(cos_good)``, and in ``geo`` (if
    given) those of them where no edge was flipped and no refusal came from a lock (see :func:`_retest`).
    Returns flips done.
    """
    start, lst = _stars(F, alive, nf, nv)
    done = 0
    for f in todo:
        if not alive[f] or lock[f]:
            continue
        if _max_cos(V, F[f, 0], F[f, 1], F[f, 2]) < cos_good:
            continue  # a face whose angles are all above good_deg: its neighbours' own visits flip its edges
        keep[f] = True
        by_lock, flipped = False, False
        for i in range(3):
            a, b, c = F[f, i], F[f, (i + 1) % 3], F[f, (i + 2) % 3]
            g = _other_face(F, alive, lock, start, lst, f, a, b)
            if g < 0:
                by_lock = True
                continue
            d = _third(F, g, a, b)
            if c == d:
                continue
            old = max(_max_cos(V, a, b, c), _max_cos(V, b, a, d))
            new = max(_max_cos(V, c, a, d), _max_cos(V, d, b, c))
            # no smaller cosine, no larger angle (acos decreases): the test below would fail, without its acos
            if (new >= old and gain >= 0.0) or not (math.acos(min(new, 1.0)) > math.acos(min(old, 1.0)) + gain):
                continue
            if not (_star_free(lock, start, lst, c) and _star_free(lock, start, lst, d)):
                by_lock = True
                continue
            exists = False
            for k in range(start[c], start[c + 1]):
                q = lst[k]
                if F[q, 0] == d or F[q, 1] == d or F[q, 2] == d:
                    exists = True
            if exists:
                continue
            nf_ = _normal(V[a], V[b], V[c])
            ng = _normal(V[b], V[a], V[d])
            lf = math.sqrt(nf_[0] ** 2 + nf_[1] ** 2 + nf_[2] ** 2)
            lg = math.sqrt(ng[0] ** 2 + ng[1] ** 2 + ng[2] ** 2)
            if lf == 0.0 or lg == 0.0:
                continue
            if nf_[0] * ng[0] + nf_[1] * ng[1] + nf_[2] * ng[2] < cos_fold * lf * lg:
                continue
            if tol > 0.0 and _segments_apart(V, a, b, c, d) > tol:
                continue  # the new edge would leave the surface (across a ridge or a thin part's rim)
            n1 = _normal(V[c], V[a], V[d])
            n2 = _normal(V[d], V[b], V[c])
            m = (nf_[0] / lf + ng[0] / lg, nf_[1] / lf + ng[1] / lg, nf_[2] / lf + ng[2] / lg)
            if (n1[0] * m[0] + n1[1] * m[1] + n1[2] * m[2]) <= 0.0 or (n2[0] * m[0] + n2[1] * m[1] + n2[2] * m[2]) <= 0.0:
                continue
            F[f, 0], F[f, 1], F[f, 2] = c, a, d
            F[g, 0], F[g, 1], F[g, 2] = d, b, c
            lock[f] = lock[g] = True
            done += 1
            flipped = True
            break
        if geo is not None and not flipped and not by_lock:
            geo[f] = True
    return done


# ------------------------------------------------------------------ the driver

#: faces whose angles are all above 40 degrees are left to their neighbours' flips
_COS_GOOD = math.cos(math.radians(40.0))
_NONE = np.zeros(0, dtype=np.bool_)


def _next_todo(keep, lock, alive, nf):
    """The faces the next sweep visits: those the last one found an operation for and did not change
    (``keep``) and those it changed (``lock``, less the faces locked from the start, dead ones).

    Every other face was visited with nothing to do, and its vertices and targets are as they were
    (an operation locks every face whose corner it moves or whose target it changes): the next sweep
    would skip it too, so it runs the same operations in the same order as one over all faces.
    """
    return np.flatnonzero((keep[:nf] | lock[:nf]) & alive[:nf])


@njit(cache=True, nogil=True)
def _retest(F, alive, lock, lock0, keep, geo, pending, todo, nf, nv):
    """The faces the next collapse or flip sweep visits: :func:`_next_todo`'s, less those whose operation was
    refused by their neighbourhood's shape (``geo``) at their last visit, this sweep or an earlier one
    (``pending``, updated here), where no corner of theirs is a corner of a face changed in this sweep.

    Such a refusal reads the face's corners, the vertices across its edges and the stars around them.  A
    collapse locks every face of both ends' stars (the faces of the moved vertex's neighbours with it), a flip
    its two faces: whatever could turn a refusal into an operation (a star's faces, a vertex moved or given
    another target, a new twin across an edge, a new edge from a corner, a valence that grows) locks a face
    with a corner of the refused face.  What changes without that (the valence of the vertex across an edge
    dropping) refuses again.  So every face left out would be refused again in the same way, and the sweeps
    do the same operations (0.25 mm sample: of the 20 000-30 000 faces the later sweeps visited, 10-20 were
    collapsed).
    """
    for f in todo:
        pending[f] = geo[f]
    touched = np.zeros(nv, dtype=np.bool_)
    for f in range(nf):
        if lock[f] and not lock0[f]:
            touched[F[f, 0]] = touched[F[f, 1]] = touched[F[f, 2]] = True
    n = 0
    out = np.empty(nf, dtype=np.int64)
    for f in range(nf):
        if not alive[f]:
            continue
        if (lock[f] and not lock0[f]) or (keep[f] and not geo[f]) or (
                pending[f] and (touched[F[f, 0]] or touched[F[f, 1]] or touched[F[f, 2]])):
            out[n] = f
            n += 1
    return out[:n]


@njit(cache=True, nogil=True)
def _compact(V, F, H, alive, valive, nv, nf):
    """The live faces (in order) and the vertices they use (in order, renumbered): ``(V, F, H)`` new arrays (one
    pass each, for numpy's masks, cumsum and fancy indexing: 1 mm sample, six calls, 10 -> 2 ms)."""
    new = np.full(nv, -1, dtype=np.int64)
    m = 0
    for t in range(nf):
        if alive[t]:
            m += 1
            for i in range(3):
                new[F[t, i]] = 0
    n = 0
    for v in range(nv):
        if new[v] == 0:
            new[v] = n
            n += 1
    V2, H2, F2 = np.empty((n, 3)), np.empty(n), np.empty((m, 3), dtype=np.int64)
    for v in range(nv):
        j = new[v]
        if j >= 0:
            V2[j, 0], V2[j, 1], V2[j, 2] = V[v, 0], V[v, 1], V[v, 2]
            H2[j] = H[v]
    m = 0
    for t in range(nf):
        if alive[t]:
            for i in range(3):
                F2[m, i] = new[F[t, i]]
            m += 1
    return V2, F2, H2


def _vertex_normals(V, F):
    nrm = np.empty((len(V), 3))
    _star_sums(np.ascontiguousarray(V, dtype=np.float64), np.ascontiguousarray(F, dtype=np.int64), nrm, None)
    return nrm


def _neighbour_mean(V, F):
    """Each vertex's mean over its faces' centroids weighted by their areas."""
    mean = np.empty((len(V), 3))
    _star_sums(np.ascontiguousarray(V, dtype=np.float64), np.ascontiguousarray(F, dtype=np.int64), None, mean)
    return mean


@njit(cache=True, nogil=True)
def _star_sums(V, F, nrm, mean):
    nv = V.shape[0]
    acc_n = np.zeros((3, nv, 3))
    acc_c = np.zeros((3, nv, 3))
    acc_w = np.zeros((3, nv))
    for t in range(F.shape[0]):
        a, b, c = F[t, 0], F[t, 1], F[t, 2]
        nx, ny, nz = _normal3(V[a, 0], V[a, 1], V[a, 2], V[b, 0], V[b, 1], V[b, 2], V[c, 0], V[c, 1], V[c, 2])
        area = np.sqrt(nx * nx + ny * ny + nz * nz)
        for i in range(3):
            v = F[t, i]
            acc_n[i, v, 0] += nx
            acc_n[i, v, 1] += ny
            acc_n[i, v, 2] += nz
            acc_w[i, v] += area
        for k in range(3):
            m = (V[a, k] + V[b, k] + V[c, k]) / 3.0 * area
            for i in range(3):
                acc_c[i, F[t, i], k] += m
    for v in range(nv):
        if nrm is not None:
            for k in range(3):
                nrm[v, k] = ((0.0 + acc_n[0, v, k]) + acc_n[1, v, k]) + acc_n[2, v, k]
            ln = np.sqrt(nrm[v, 0] ** 2 + nrm[v, 1] ** 2 + nrm[v, 2] ** 2) + 1e-300
            for k in range(3):
                nrm[v, k] /= ln
        if mean is not None:
            w = max(((0.0 + acc_w[0, v]) + acc_w[1, v]) + acc_w[2, v], 1e-300)
            for k in range(3):
                mean[v, k] = (((0.0 + acc_c[0, v, k]) + acc_c[1, v, k]) + acc_c[2, v, k]) / w


def sizing_field(mesh: Mesh, *, max_mm: float, min_mm: float, tol_mm: float, grade: float = 0.5) -> np.ndarray:
    """Target edge length at each vertex of ``mesh``, mm, ``(V,)`` float64.

    ``sqrt(8 R tol_mm)`` where the surface's radius of curvature is ``R`` (from how fast the vertex
    normals turn along the edges), clipped to ``[min_mm, max_mm]``, then graded: no vertex's target
    exceeds a neighbour's by more than ``grade`` times their distance.
    """
    V, F = np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64)
    n = _vertex_normals(V, F)
    e = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    # curvature along the edge from the turn of the normals: |n_b - n_a| / |b - a|; short marching-cubes
    # edges (< 0.2 of the minimum) are left out, their normals are noise over such a distance
    kv, ln = np.zeros(len(V)), np.empty(len(e))
    _edge_curvature(V, n, e, float((0.2 * min_mm) ** 2), kv, ln)
    with np.errstate(divide="ignore"):
        h = np.sqrt(8.0 * tol_mm / np.maximum(kv, 1e-12))
    h = np.clip(h, min_mm, max_mm)
    _grade(h, e, ln, float(grade))
    return h


@njit(cache=True, nogil=True)
def _edge_curvature(V, n, e, short2, kv, ln):
    """Each edge's length into ``ln`` and, at both its ends, the largest ``|n_b - n_a| / |b - a|`` into ``kv``
    (edges whose squared length is not above ``short2`` count 0).

    The numpy expressions it replaced, in the same order (the same values, without the six ``(3F, 3)``
    temporaries: 0.25 mm sample, 2.8 M edges, 320 MB less at the finishing's peak).
    """
    for i in range(e.shape[0]):
        a, b = e[i, 0], e[i, 1]
        dx, dy, dz = V[b, 0] - V[a, 0], V[b, 1] - V[a, 1], V[b, 2] - V[a, 2]
        l2 = (dx * dx + dz * dz) + dy * dy  # as numpy's einsum sums three terms
        ln[i] = math.sqrt(l2)
        k = 0.0
        if l2 > short2:
            nx, ny, nz = n[b, 0] - n[a, 0], n[b, 1] - n[a, 1], n[b, 2] - n[a, 2]
            k = math.sqrt(nx * nx + ny * ny + nz * nz) / math.sqrt(max(l2, 1e-300))
        if k > kv[a]:
            kv[a] = k
        if k > kv[b]:
            kv[b] = k


@njit(cache=True, nogil=True)
def _grade(h, e, ln, grade):
    """``h[a] <= h[b] + grade * |ab|`` over every edge, by sweeps until nothing changes (in place)."""
    for _ in range(200):
        changed = False
        for i in range(e.shape[0]):
            a, b = e[i, 0], e[i, 1]
            c = h[b] + grade * ln[i]
            if c < h[a]:
                h[a] = c
                changed = True
            c = h[a] + grade * ln[i]
            if c < h[b]:
                h[b] = c
                changed = True
        if not changed:
            break


def adaptive_remesh(mesh: Mesh, reference: Mesh, sizing: np.ndarray, *, iterations: int = 6, min_angle: float = 20.0,
                    tol_mm: float = 0.1, relax: float = 0.8, flip_deg: float = 35.0, turn_deg: float = 60.0) -> Mesh:
    """Remesh ``mesh`` (closed, manifold, oriented) toward the per-vertex ``sizing`` of ``reference``,
    its vertices on ``reference``'s surface (see the module's docstring).

    Parameters
    ----------
    mesh : Mesh
        The start (usually ``reference`` itself).
    reference : Mesh
        The surface to stay on; world frame, mm.
    sizing : (len(reference.vertices),) float64, mm
        Target edge length at the reference's vertices (:func:`sizing_field`).
    iterations : int
        Split / collapse / flip / relax rounds.

    Returns
    -------
    Mesh
    """
    ref = _surface(reference)
    rsize = np.asarray(sizing, dtype=np.float64)
    V = np.array(mesh.vertices, dtype=np.float64)
    F = np.array(mesh.faces, dtype=np.int64)
    _, _, face = ref.closest(V)
    H = rsize[ref.f[face]].min(axis=1)
    cos_fold, cos_turn = math.cos(math.radians(flip_deg)), math.cos(math.radians(turn_deg))
    for it in range(int(iterations)):
        nv, nf = len(V), len(F)
        cap_v, cap_f = 2 * nv + 16, 2 * nf + 32
        Vb = np.zeros((cap_v, 3))
        Vb[:nv] = V
        Fb = np.zeros((cap_f, 3), dtype=np.int64)
        Fb[:nf] = F
        Hb = np.zeros(cap_v)
        Hb[:nv] = H
        alive = np.zeros(cap_f, dtype=bool)
        alive[:nf] = True
        valive = np.ones(cap_v, dtype=bool)
        # splits until none is left (each sweep locks the faces it changed); every sweep after the first
        # visits only the faces the last one changed or found something to do for (_next_todo)
        todo = np.arange(nf)
        for _ in range(8):
            lock = np.zeros(len(alive), dtype=bool)
            keep = np.zeros(len(alive), dtype=bool)
            nv0 = nv
            nv, nf, full = _split_long(Vb, Fb, Hb, alive, lock, nv, nf, 4.0 / 3.0, todo, keep)
            if full:
                Vb = np.concatenate([Vb, np.zeros_like(Vb)])
                Hb = np.concatenate([Hb, np.zeros_like(Hb)])
                valive = np.concatenate([valive, np.ones(len(valive), dtype=bool)])
                Fb = np.concatenate([Fb, np.zeros_like(Fb)])
                alive = np.concatenate([alive, np.zeros(len(alive), dtype=bool)])
                todo = np.arange(nf)  # the next sweep starts over, as it did
                continue
            if nv == nv0:
                break
            todo = _next_todo(keep, lock, alive, nf)
        # each sweep locks what it changed; sweeps stop when one does less than 0.1 % of the faces' worth
        # (a face refused for its neighbourhood's shape is visited again only when that changed: _retest)
        few = 1
        todo = np.arange(nf)
        pending = np.zeros(len(alive), dtype=bool)
        for _ in range(8):
            lock = ~alive[: len(alive)].copy()
            lock0, keep, geo = lock.copy(), np.zeros(len(alive), dtype=bool), np.zeros(len(alive), dtype=bool)
            if _collapse_short(Vb, Fb, Hb, alive, valive, lock, nv, nf, 0.8, 4.0 / 3.0, cos_turn, _NONE, todo, keep,
                               geo) < few:
                break
            todo = _retest(Fb, alive, lock, lock0, keep, geo, pending, todo, nf, nv)
        todo = np.arange(nf)
        pending[:] = False
        for _ in range(4):
            lock = ~alive.copy()
            lock0, keep, geo = lock.copy(), np.zeros(len(alive), dtype=bool), np.zeros(len(alive), dtype=bool)
            if _flip_edges(Vb, Fb, alive, lock, nv, nf, cos_fold, math.radians(0.5), _COS_GOOD, 0.0, todo, keep,
                           geo) < few:
                break
            todo = _retest(Fb, alive, lock, lock0, keep, geo, pending, todo, nf, nv)
        V, F, H = _compact(Vb, Fb, Hb, alive, valive, nv, nf)
        V, H = _relax(V, F, H, ref, rsize, relax)
    return _fix_slivers(V, F, H, ref, rsize, min_angle=min_angle, tol_mm=tol_mm, cos_fold=cos_fold, cos_turn=cos_turn)


#: Rings of faces around the faces being fixed that :func:`_fix_slivers` works on (the outermost one
#: locked).  A round's flips, collapses and relaxation change faces up to 3 rings from a face below the
#: angle at its start and read the stars of their vertices (a knife-edge round, whose flattening makes
#: new bad faces 2 rings out first: 6 rings), so the region is taken again when a bad face comes within
#: 4 rings (a knife-edge round: 7) of the locked one.
_REGION_RINGS = 8


def _rings(F, seed, rings, alive=None):
    """Faces of ``F`` (the ``alive`` ones) within ``rings`` vertex-rings of the ``seed`` faces (a mask):
    ``(F,)`` int8, the ring of each face (0 for the seeds), -1 beyond."""
    ring = np.full(len(F), -1, dtype=np.int8)
    cur = seed if alive is None else seed & alive
    ring[cur] = 0
    mark = np.zeros(int(F.max()) + 1 if len(F) else 0, dtype=bool)
    for k in range(1, rings + 1):
        mark[F[cur].ravel()] = True
        cur = (ring < 0) & mark[F].any(axis=1)
        if alive is not None:
            cur &= alive
        ring[cur] = k
    return ring


def _fix_slivers(V, F, H, ref, rsize, *, min_angle, tol_mm, cos_fold, cos_turn, rounds=8, only=None):
    """Local clean-up of the faces still below ``min_angle``: flips that stay within ``tol_mm`` of the
    surface, collapses of their shortest edges that improve their stars, and a relaxation of their
    vertices kept only where it improves their stars' smallest angle.

    Each round works on the faces within :data:`_REGION_RINGS` rings of the bad ones (its outermost ring
    locked; faces in their order in ``F``), as the rounds over the whole mesh did: the same operations in
    the same order (0.25 mm sample: a few dozen faces of 143 000 to fix, up to 22 rounds a call).
    """
    cos_bad = math.cos(math.radians(min_angle + 1.0))
    bad = _face_min_angles(V, F) < min_angle + 1.0
    if only is not None:
        bad &= only
    if not bad.any():
        return Mesh(V, F)
    V, F, H = np.array(V, dtype=np.float64), np.array(F, dtype=np.int64), np.array(H, dtype=np.float64)
    nv = len(V)
    alive_all = np.ones(len(F), dtype=bool)
    valive = np.ones(nv, dtype=bool)
    idx = None
    r = 0
    while r < int(rounds) + 10:
        if idx is not None:
            bad = _face_min_angles(V, Fs) < min_angle + 1.0
            if not bad.any():
                break
            if (_rings(Fs, bad, 7 if r >= rounds else 4)[edge] >= 0).any():  # near the locked ring: a new region
                F[idx] = Fs
                bad_all = np.zeros(len(F), dtype=bool)
                bad_all[idx[bad]] = True
                idx = None
        else:
            bad_all = bad
        if idx is None:
            ring = _rings(F, bad_all, _REGION_RINGS, alive_all)
            idx = np.flatnonzero(ring >= 0)
            Fs, edge = F[idx], ring[idx] == _REGION_RINGS
            bad = bad_all[idx]
        if r >= rounds:
            # still there: a knife edge of the raw surface (faces folded back by more than 150 degrees), where no
            # triangle of the surface is well shaped; its tip is flattened (a Laplacian step of the vertices of the
            # faces below min_angle and their neighbours, not projected back), then cleaned up again
            near = np.isin(Fs, np.unique(Fs[bad])).any(axis=1)
            verts = np.unique(Fs[near])
            V = V.copy()
            Fr = Fs[np.isin(Fs, verts).any(axis=1)]
            for _ in range(2):
                V[verts] += 0.5 * (_neighbour_mean(V, Fr)[verts] - V[verts])
        nf = len(Fs)
        alive = np.ones(nf, dtype=bool)
        every, keep = np.arange(nf), np.zeros(nf, dtype=bool)
        # (a ``geo`` array given, unread: the kernels' one specialisation, that of adaptive_remesh's sweeps)
        flips = _flip_edges(V, Fs, alive, edge.copy(), nv, nf, -1.0, math.radians(0.1), cos_bad, tol_mm, every, keep,
                            np.zeros(nf, dtype=bool))
        bad = _face_min_angles(V, Fs) < min_angle + 1.0
        collapses = _collapse_short(V, Fs, H, alive, valive, edge.copy(), nv, nf, 1.0, 2.0, cos_turn, bad, every, keep,
                                    np.zeros(nf, dtype=bool))
        if collapses:
            alive_all[idx[~alive]] = False
            F[idx] = Fs
            idx, Fs, edge = idx[alive], Fs[alive], edge[alive]
        W = _smart_relax(V, Fs, ref if r < rounds else None, _face_min_angles(V, Fs) < min_angle + 1.0)
        if r < rounds - 1 and not flips and not collapses and W is V:
            # nothing changed: the rounds up to the knife-edge flattening would repeat this one exactly
            r = int(rounds) - 1
        V = W
        r += 1
    F[idx] = Fs
    if not alive_all.all():
        V, F, _ = _compact(V, F, H, alive_all, valive, nv, len(F))
    return Mesh(V, F)


def _face_min_angles(V, F):
    """Smallest angle of each face, degrees."""
    out = np.empty(len(F))
    _min_angles(np.ascontiguousarray(V), np.ascontiguousarray(F), out)
    return out


@njit(cache=True, nogil=True)
def _min_angles(V, F, out):
    for f in range(F.shape[0]):
        out[f] = math.degrees(math.acos(max(-1.0, min(1.0, _max_cos(V, F[f, 0], F[f, 1], F[f, 2])))))


def _smart_relax(V, F, ref, bad, steps=3):
    """Move the vertices of the ``bad`` faces toward their stars' centroids (projected onto ``ref``)
    where that raises the smallest angle of their stars.  Returns ``V`` itself when none moved."""
    verts = np.unique(F[bad])
    if len(verts) == 0:
        return V
    # the stars of verts (their normals and centroids need no other face), on their own vertices
    used, Fl = np.unique(F[np.isin(F, verts).any(axis=1)], return_inverse=True)
    Fl = Fl.reshape(-1, 3)
    lv = np.searchsorted(used, verts)
    Vl, moved = V[used], False
    for _ in range(steps):
        n = _vertex_normals(Vl, Fl)
        c = _neighbour_mean(Vl, Fl)[lv] - Vl[lv]
        c -= np.einsum("ij,ij->i", c, n[lv])[:, None] * n[lv]
        if ref is None:
            q = Vl[lv] + c
        else:  # a closest point on the other side of a thin part is refused (._thin)
            q, _, face = ref.closest(Vl[lv] + c)
            if SAME_SIDE:
                q = np.where(same_side(ref, face, n[lv])[:, None], q, Vl[lv])
        before = _star_min(Vl, Fl, lv)
        W = Vl.copy()
        W[lv] = q
        after = _star_min(W, Fl, lv)
        # the normals of the star must not turn over either
        good = after > before
        if not good.any():
            break
        W[lv[~good]] = Vl[lv[~good]]
        nb = np.cross(Vl[Fl[:, 1]] - Vl[Fl[:, 0]], Vl[Fl[:, 2]] - Vl[Fl[:, 0]])
        na = np.cross(W[Fl[:, 1]] - W[Fl[:, 0]], W[Fl[:, 2]] - W[Fl[:, 0]])
        if (np.einsum("ij,ij->i", nb, na) <= 0).any():
            break
        Vl, moved = W, True
    if not moved:
        return V
    out = V.copy()
    out[used] = Vl
    return out


def _star_min(V, F, verts):
    """Smallest angle over the star of each of ``verts`` (among faces ``F``)."""
    ang = _face_min_angles(V, F)
    out = np.full(len(V), 180.0)
    for i in range(3):
        np.minimum.at(out, F[:, i], ang)
    return out[verts]


def _relax(V, F, H, ref, rsize, relax):
    """Tangential relaxation toward the area-weighted centroid of the star, projected onto ``ref``."""
    n, c = np.empty((len(V), 3)), np.empty((len(V), 3))
    _star_sums(np.ascontiguousarray(V, dtype=np.float64), np.ascontiguousarray(F, dtype=np.int64), n, c)  # one pass
    c -= V
    c -= np.einsum("ij,ij->i", c, n)[:, None] * n
    moved = V + relax * c
    # 4 candidate faces: a relaxation step moves a vertex a fraction of an edge, the next one corrects a miss
    q, dist, face = ref.closest(moved, k=4)
    # a vertex whose closest point is far from where it moved (another sheet of a thin part) stays, nor one on the
    # other side of a thin part (._thin.same_side); compiled: the numpy version's same bits, 16 -> 3 ms a mesh of
    # 10 k vertices (1 mm sample: six rounds, 25 ms of numpy temporaries)
    # (in place: V and H are adaptive_remesh's own, fresh from _compact)
    _accept(V, H, q, dist, face, n, ref.v, ref.f, rsize, SAME_SIDE)
    return V, H


@njit(cache=True, nogil=True)
def _accept(V, H, q, dist, face, n, rv, rf, rsize, sides):
    """:func:`_relax`'s choice per vertex: ``q`` (its closest point on the reference's face ``face``) where it lies
    within half the vertex's size of where it moved and that face looks the same way as ``n`` (the vertex's
    normal; when ``sides``), with the face's smallest size, into ``V`` and ``H``; else they stay.  The same
    operations as ``(dist <= 0.5 * H) & (np.einsum("ij,ij->i", np.cross(e1, e2), n) > 0)`` and ``np.where``
    (numpy 2.4's einsum sums a row of three products as ``(p0 + p2) + p1``): the same bits."""
    for i in range(V.shape[0]):
        t = face[i]
        a, b, c = rf[t, 0], rf[t, 1], rf[t, 2]
        nx, ny, nz = _normal(rv[a], rv[b], rv[c])
        if dist[i] <= 0.5 * H[i] and (not sides or (nx * n[i, 0] + nz * n[i, 2]) + ny * n[i, 1] > 0.0):
            V[i, 0], V[i, 1], V[i, 2] = q[i, 0], q[i, 1], q[i, 2]
            H[i] = min(min(rsize[a], rsize[b]), rsize[c])


def fit_faces(mesh: Mesh, reference: Mesh, *, min_angle: float = 20.0, factor: float = 1.0) -> Mesh:
    """Move each vertex along its normal by the mean signed gap between its faces' centroids and ``reference``.

    A remeshed surface's vertices lie on the reference and its faces are chords: inside where the
    surface is convex (a thin part's rim, a silhouette's contour), outside where it is concave.  This
    offset puts the faces, not the vertices, on the reference on average, locally.  A vertex whose
    offset would leave a face of its star below ``min_angle`` (and worse than before) keeps its place.
    """
    ref = reference if isinstance(reference, _Surface) else _surface(reference)
    V, F = np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64)
    c = np.empty((len(F), 3))
    _centroids(V, F, c)
    q, d, face = ref.closest(c)
    g = np.empty(len(V))
    _fit_gaps(V, F, c, q, face, ref.v, ref.f, SAME_SIDE, g)
    n = _vertex_normals(V, F)
    before = _face_min_angles(V, F)
    for _ in range(5):
        W = V + factor * g[:, None] * n
        after = _face_min_angles(W, F)
        worse = (after < min_angle + 1.0) & (after < before)
        if not worse.any():
            break
        g[np.unique(F[worse])] = 0.0
    return Mesh(W, F)


@njit(cache=True, nogil=True)
def _centroids(V, F, out):
    """The faces' centroids, as ``V[F].mean(axis=1)`` (the same bits)."""
    for t in range(F.shape[0]):
        for k in range(3):
            out[t, k] = _centroid(V, F[t, 0], F[t, 1], F[t, 2], k)


@njit(cache=True, nogil=True)
def _fit_gaps(V, F, c, q, face, rv, rf, sides, out):
    """:func:`fit_faces`'s offset per vertex: the mean over its faces of the signed gap from the face's centroid
    ``c`` to its closest point ``q`` on the reference's face ``face``, along that face's normal (> 0: the face is
    inside); 0 for a face whose closest face looks the other way (._thin.same_side; when ``sides``).  The same
    operations in the same order as the numpy version (np.cross; einsum's ``(p0 + p2) + p1`` on numpy 2.4;
    np.linalg.norm's ``(s0 + s1) + s2``; a bincount per corner summed from corner 0, divided by the vertex's face
    count): the same bits, one pass (1 mm sample: 12 -> 1 ms)."""
    nv = V.shape[0]
    acc = np.zeros((3, nv))
    cnt = np.zeros((3, nv), dtype=np.int64)
    for t in range(F.shape[0]):
        r = face[t]
        nx, ny, nz = _normal(rv[rf[r, 0]], rv[rf[r, 1]], rv[rf[r, 2]])
        gap = (((q[t, 0] - c[t, 0]) * nx + (q[t, 2] - c[t, 2]) * nz) + (q[t, 1] - c[t, 1]) * ny) / (
            math.sqrt((nx * nx + ny * ny) + nz * nz) + 1e-300)
        mx, my, mz = _normal(V[F[t, 0]], V[F[t, 1]], V[F[t, 2]])
        if sides and not ((nx * mx + nz * mz) + ny * my > 0.0):
            gap = 0.0
        for i in range(3):
            acc[i, F[t, i]] += gap
            cnt[i, F[t, i]] += 1
    for v in range(nv):
        out[v] = (((0.0 + acc[0, v]) + acc[1, v]) + acc[2, v]) / max(cnt[0, v] + cnt[1, v] + cnt[2, v], 1)


def fix_slivers(mesh: Mesh, reference: Mesh, *, target_mm: float, min_angle: float = 20.0, tol_mm: float = 0.1,
                rounds: int = 8, flip_deg: float = 35.0, turn_deg: float = 60.0, only: np.ndarray | None = None) -> Mesh:
    """The local clean-up of :func:`adaptive_remesh`'s last step, on its own: faces below ``min_angle`` fixed
    by flips within ``tol_mm`` of ``reference``, collapses and relaxation onto it (knife edges flattened).
    ``only``: ``(F,)`` bool, the faces below the angle to start from (default: every one)."""
    V = np.array(mesh.vertices, dtype=np.float64)
    F = np.array(mesh.faces, dtype=np.int64)
    H = np.full(len(V), float(target_mm))
    return _fix_slivers(V, F, H, _surface(reference), None, min_angle=min_angle, tol_mm=tol_mm,
                        cos_fold=math.cos(math.radians(flip_deg)), cos_turn=math.cos(math.radians(turn_deg)),
                        rounds=rounds, only=only)
