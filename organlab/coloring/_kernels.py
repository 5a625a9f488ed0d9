"""numba kernels of :mod:`organlab.coloring`: footprints, item buffers, pixel statistics.

A camera is packed by organlab.nbcam.pack_camera: R (9, row major), t (3),
fx, K[0, 1], cx, fy, cy, k1, k2, p1, p2, k3, |t|_1.
"""

from __future__ import annotations

import numba as nb
import numpy as np

from ..nbcam import to_camera, to_pixel


@nb.njit(cache=True, nogil=True)
def _nb_project(cam, x, y, z):
    """Camera.project for one point: (u, v, z_cam); z_cam <= 0 means behind."""
    xc, yc, zc = to_camera(cam, x, y, z)
    if not zc > 0.0:
        return 0.0, 0.0, -1.0
    u, v = to_pixel(cam, xc / zc, yc / zc)
    return u, v, zc


def _silhouette_table():
    """Silhouette loops of a box seen from each of the 26 regions around it.

    Corner ``k`` of a box has local offsets ``(i, j, s) = ((k >> 1) & 1,
    k & 1, (k >> 2) & 1)`` along its local axes ``(a, b, n)``.  The camera
    centre's region is ``code = 9 * ca + 3 * cb + cn``, each digit 0 (below
    the box along that axis), 1 (within its slab) or 2 (above).  The outline
    of the projected box is the loop of edges between a face turned to the
    camera and one turned away: 4 or 6 corners, listed in loop order.
    """
    coords = [((k >> 1) & 1, k & 1, (k >> 2) & 1) for k in range(8)]
    table = np.full((27, 6), -1, np.int64)
    count = np.zeros(27, np.int64)
    for code in range(27):
        cc = (code // 9, (code // 3) % 3, code % 3)
        if cc == (1, 1, 1):
            continue  # camera inside the box: it does not see it
        front = {(d, side) for d in range(3) for side in (0, 1) if cc[d] == 2 * side}
        adj = {}
        for k1 in range(8):
            for k2 in range(k1 + 1, 8):
                diff = [d for d in range(3) if coords[k1][d] != coords[k2][d]]
                if len(diff) != 1:
                    continue
                d1, d2 = [d for d in range(3) if d != diff[0]]
                if ((d1, coords[k1][d1]) in front) != ((d2, coords[k1][d2]) in front):
                    adj.setdefault(k1, []).append(k2)
                    adj.setdefault(k2, []).append(k1)
        loop = [min(adj)]
        prev = None
        while True:
            cur = loop[-1]
            nxt = adj[cur][0] if adj[cur][0] != prev else adj[cur][1]
            if nxt == loop[0]:
                break
            loop.append(nxt)
            prev = cur
        table[code, : len(loop)] = loop
        count[code] = len(loop)
    return table, count


_SIL_TABLE, _SIL_COUNT = _silhouette_table()


@nb.njit(cache=True, nogil=True)
def _nb_region(c, lo, hi):
    return 0 if c < lo else (2 if c > hi else 1)


@nb.njit(cache=True, nogil=True)
def _nb_hull(px, py, code, width, height, ex, ey, ec):
    """Footprint of a box from its 8 projected corners and the camera's region code.

    Writes the outline's edges as half-planes ``ex*u + ey*v + ec >= 0``.
    Returns ``(n_edges, c0, c1, r0, r1, fu, fv)``: the pixel range of the
    outline's bounding box clipped to the image (empty when ``c0 > c1``), and
    ``(fu, fv)`` the pixel nearest to the corners' mean (``-1`` if outside the
    image), used when no pixel centre falls in the outline.
    """
    n = _SIL_COUNT[code]
    fu = int(np.floor(px.mean() + 0.5))
    fv = int(np.floor(py.mean() + 0.5))
    if fu < 0 or fu >= width or fv < 0 or fv >= height:
        fu = -1
        fv = -1
    if n == 0:
        return 0, 0, -1, 0, -1, -1, -1
    umin = np.inf
    umax = -np.inf
    vmin = np.inf
    vmax = -np.inf
    area = 0.0
    for a in range(n):
        i0 = _SIL_TABLE[code, a]
        i1 = _SIL_TABLE[code, a + 1 if a + 1 < n else 0]
        area += px[i0] * py[i1] - px[i1] * py[i0]
        umin = min(umin, px[i0])
        umax = max(umax, px[i0])
        vmin = min(vmin, py[i0])
        vmax = max(vmax, py[i0])
    c0 = max(int(np.ceil(umin)), 0)
    c1 = min(int(np.floor(umax)), width - 1)
    r0 = max(int(np.ceil(vmin)), 0)
    r1 = min(int(np.floor(vmax)), height - 1)
    if c0 > c1 or r0 > r1 or area == 0.0:
        return 0, c0, c1, r0, r1, fu, fv
    sign = 1.0 if area > 0.0 else -1.0
    for a in range(n):
        i0 = _SIL_TABLE[code, a]
        i1 = _SIL_TABLE[code, a + 1 if a + 1 < n else 0]
        # inside <=> sign * cross(p0, p1, p) >= 0
        ex[a] = -sign * (py[i1] - py[i0])
        ey[a] = sign * (px[i1] - px[i0])
        ec[a] = -(ex[a] * px[i0] + ey[a] * py[i0])
    return n, c0, c1, r0, r1, fu, fv


@nb.njit(cache=True, nogil=True)
def _nb_layer_code(centre, o, en, dims, a, b):
    """Region code of a camera centre around voxel (a, b) of a layer (local axes ``dims``)."""
    h = en[dims[2]]
    lo0 = o[dims[0]] + a * h
    lo1 = o[dims[1]] + b * h
    lo2 = o[dims[2]]
    return (
        9 * _nb_region(centre[dims[0]], lo0, lo0 + h)
        + 3 * _nb_region(centre[dims[1]], lo1, lo1 + h)
        + _nb_region(centre[dims[2]], lo2, lo2 + h)
    )


@nb.njit(cache=True, nogil=True)
def _nb_voxel_code(cam, cx, cy, cz, half):
    """Region code of the camera centre around a voxel, local axes x, y, z."""
    # centre = -R.T @ t
    ox = -(cam[0] * cam[9] + cam[3] * cam[10] + cam[6] * cam[11])
    oy = -(cam[1] * cam[9] + cam[4] * cam[10] + cam[7] * cam[11])
    oz = -(cam[2] * cam[9] + cam[5] * cam[10] + cam[8] * cam[11])
    return (
        9 * _nb_region(ox, cx - half, cx + half)
        + 3 * _nb_region(oy, cy - half, cy + half)
        + _nb_region(oz, cz - half, cz + half)
    )


@nb.njit(cache=True, nogil=True)
def _nb_span(ex, ey, ec, n, r, c0, c1):
    """Columns ``lo..hi`` of row ``r`` whose pixel centres lie in the hull (empty if lo > hi)."""
    lo = float(c0)
    hi = float(c1)
    for a in range(n):
        rhs = -(ey[a] * r + ec[a])
        if ex[a] > 0.0:
            b = rhs / ex[a]
            if b > lo:
                lo = b
        elif ex[a] < 0.0:
            b = rhs / ex[a]
            if b < hi:
                hi = b
        elif rhs > 0.0:
            return 1, 0
    return int(np.ceil(lo)), int(np.floor(hi))


@nb.njit(cache=True, nogil=True)
def _nb_project_layer(v0, v1, needed, o, ea, eb, en, cams, proj, ok):
    """Project the needed corners ``o + i*ea + j*eb + s*en`` of a layer in every view.

    needed : (na + 1, nb + 1) bool; proj : (V, 2, na + 1, nb + 1, 2) px;
    ok : (V, 2, na + 1, nb + 1), False for unneeded corners and for corners
    on or behind the camera plane.
    """
    for v in range(v0, v1):
        cam = cams[v]
        for s in range(2):
            for i in range(needed.shape[0]):
                for j in range(needed.shape[1]):
                    if not needed[i, j]:
                        ok[v, s, i, j] = False
                        continue
                    x = o[0] + i * ea[0] + j * eb[0] + s * en[0]
                    y = o[1] + i * ea[1] + j * eb[1] + s * en[1]
                    z = o[2] + i * ea[2] + j * eb[2] + s * en[2]
                    u, w, zc = _nb_project(cam, x, y, z)
                    proj[v, s, i, j, 0] = u
                    proj[v, s, i, j, 1] = w
                    ok[v, s, i, j] = zc > 0.0


@nb.njit(cache=True, nogil=True)
def _nb_gather(proj, ok, a, b, px, py):
    """The 8 projected corners of voxel (a, b) of a layer; False if one is behind the camera."""
    k = 0
    for s in range(2):
        for i in range(2):
            for j in range(2):
                if not ok[s, a + i, b + j]:
                    return False
                px[k] = proj[s, a + i, b + j, 0]
                py[k] = proj[s, a + i, b + j, 1]
                k += 1
    return True


@nb.njit(cache=True, nogil=True)
def _nb_accumulate(img, mk, bgv, use_bg, owner, m, zb, ob, use_buf, depth, ex, ey, ec, n, c0, c1, r0, r1, fu, fv, out):
    """Visit a footprint; pool its pixels into out.

    A pixel is visible when it is not background and ``mk[r, c] == owner``
    (``owner = 0``: unmarked, for the layered pass; ``owner = m``: owned in
    the item buffer) and, with ``use_buf``, no nearer voxel of the layer's
    buffer covers it (``ob[r, c] == m`` or ``zb[r, c] > depth``).  out = [footprint pixels, background pixels, non-
    background pixels, visible pixels, sum c0..c2, sumsq c0..c2].
    """
    C = img.shape[2]
    k = 0
    nbg = 0
    ntot = 0
    nvis = 0
    s0 = 0.0
    s1 = 0.0
    s2 = 0.0
    q0 = 0.0
    q1 = 0.0
    q2 = 0.0
    for attempt in range(2):
        if attempt == 1:
            if k > 0 or fu < 0:
                break
            r0 = fv
            r1 = fv
        elif n == 0:
            continue
        for r in range(r0, r1 + 1):
            if attempt == 0:
                lo, hi = _nb_span(ex, ey, ec, n, r, c0, c1)
            else:
                lo = fu
                hi = fu
            for col in range(lo, hi + 1):
                k += 1
                if use_bg and bgv[r, col]:
                    nbg += 1
                    continue
                ntot += 1
                if mk[r, col] != owner:
                    continue
                if use_buf and ob[r, col] != m and not zb[r, col] > depth:
                    continue
                nvis += 1
                p = np.float64(img[r, col, 0])
                s0 += p
                q0 += p * p
                if C == 3:
                    p = np.float64(img[r, col, 1])
                    s1 += p
                    q1 += p * p
                    p = np.float64(img[r, col, 2])
                    s2 += p
                    q2 += p * p
    out[0] = k
    out[1] = nbg
    out[2] = ntot
    out[3] = nvis
    out[4] = s0
    out[5] = s1
    out[6] = s2
    out[7] = q0
    out[8] = q1
    out[9] = q2


@nb.njit(cache=True, nogil=True)
def _nb_store(out, v, m, C, n_vis, n_tot, sums, sq, bgcnt, cnt):
    cnt[v, m] = int(out[0])
    bgcnt[v, m] = int(out[1])
    n_tot[v, m] = int(out[2])
    n_vis[v, m] = int(out[3])
    for c in range(C):
        sums[v, m, c] = out[4 + c]
        sq[v, m, c] = out[7 + c]


@nb.njit(cache=True, nogil=True)
def _nb_clear(v, m, C, n_vis, n_tot, sums, sq, bgcnt, cnt):
    cnt[v, m] = 0
    bgcnt[v, m] = 0
    n_tot[v, m] = 0
    n_vis[v, m] = 0
    for c in range(C):
        sums[v, m, c] = 0.0
        sq[v, m, c] = 0.0


@nb.njit(cache=True, nogil=True)
def _nb_layer_stats(v0, v1, ab, sel, proj, ok, o, ea, eb, en, dims, centres, cams, images, marks, zbuf, obuf, bg, use_bg, n_vis, n_tot, sums, sq, bgcnt, cnt):
    """Per view and voxel of one layer: counts and sums of the footprint's pixels.

    A pixel is visible to a voxel if it is unmarked and the voxel owns it in
    the layer's item buffer ``zbuf`` / ``obuf`` (or lies in front of its owner).

    ab : (M, 2) in-layer indices relative to the corner origin ``o``.
    Outputs (V, M[, C]): n_vis (unmarked, non-background footprint pixels),
    n_tot (non-background footprint pixels), sums and sq (per channel, of
    the visible pixels), bgcnt (background footprint pixels), cnt (all
    footprint pixels).
    """
    M = ab.shape[0]
    H = images.shape[1]
    W = images.shape[2]
    C = images.shape[3]
    for v in range(v0, v1):
        px = np.empty(8)
        py = np.empty(8)
        ex = np.empty(16)
        ey = np.empty(16)
        ec = np.empty(16)
        out = np.empty(10)
        bgv = bg[v] if use_bg else bg[0]
        for m in range(M):
            if not sel[m] or not _nb_gather(proj[v], ok[v], ab[m, 0], ab[m, 1], px, py):
                _nb_clear(v, m, C, n_vis, n_tot, sums, sq, bgcnt, cnt)
                continue
            code = _nb_layer_code(centres[v], o, en, dims, ab[m, 0], ab[m, 1])
            n, c0, c1, r0, r1, fu, fv = _nb_hull(px, py, code, W, H, ex, ey, ec)
            depth = _nb_layer_depth(cams[v], o, ea, eb, en, ab[m, 0], ab[m, 1])
            _nb_accumulate(images[v], marks[v], bgv, use_bg, 0, m, zbuf[v], obuf[v], True, depth, ex, ey, ec, n, c0, c1, r0, r1, fu, fv, out)
            _nb_store(out, v, m, C, n_vis, n_tot, sums, sq, bgcnt, cnt)


@nb.njit(cache=True, nogil=True)
def _nb_layer_mark(v0, v1, ab, keep, proj, ok, o, ea, eb, en, dims, centres, cams, marks):
    """Mark, in every view, the footprint pixels of the kept voxels of a layer."""
    M = ab.shape[0]
    H = marks.shape[1]
    W = marks.shape[2]
    for v in range(v0, v1):
        px = np.empty(8)
        py = np.empty(8)
        ex = np.empty(16)
        ey = np.empty(16)
        ec = np.empty(16)
        mk = marks[v]
        for m in range(M):
            if not keep[m]:
                continue
            if not _nb_gather(proj[v], ok[v], ab[m, 0], ab[m, 1], px, py):
                continue
            code = _nb_layer_code(centres[v], o, en, dims, ab[m, 0], ab[m, 1])
            n, c0, c1, r0, r1, fu, fv = _nb_hull(px, py, code, W, H, ex, ey, ec)
            k = 0
            if n > 0:
                for r in range(r0, r1 + 1):
                    lo, hi = _nb_span(ex, ey, ec, n, r, c0, c1)
                    for col in range(lo, hi + 1):
                        mk[r, col] = 1
                        k += 1
            if k == 0 and fu >= 0:
                mk[fv, fu] = 1


@nb.njit(cache=True, nogil=True)
def _nb_layer_depth(cam, o, ea, eb, en, a, b):
    """Camera-frame depth of the centre of voxel (a, b) of a layer."""
    x = o[0] + (a + 0.5) * ea[0] + (b + 0.5) * eb[0] + 0.5 * en[0]
    y = o[1] + (a + 0.5) * ea[1] + (b + 0.5) * eb[1] + 0.5 * en[1]
    z = o[2] + (a + 0.5) * ea[2] + (b + 0.5) * eb[2] + 0.5 * en[2]
    return cam[6] * x + cam[7] * y + cam[8] * z + cam[11]


@nb.njit(cache=True, nogil=True)
def _nb_layer_buffer(v0, v1, ab, keep, proj, ok, o, ea, eb, en, dims, centres, cams, zbuf, obuf, box):
    """Item buffer of the kept voxels of one layer: per pixel the nearest one (centre depth).

    ``zbuf`` / ``obuf`` must hold inf / -1 on entry; ``box[v]`` receives the
    touched pixel rectangle ``(r0, r1, c0, c1)`` so that it can be cleared.
    """
    M = ab.shape[0]
    H = zbuf.shape[1]
    W = zbuf.shape[2]
    for v in range(v0, v1):
        px = np.empty(8)
        py = np.empty(8)
        ex = np.empty(16)
        ey = np.empty(16)
        ec = np.empty(16)
        zb = zbuf[v]
        ob = obuf[v]
        br0 = H
        br1 = -1
        bc0 = W
        bc1 = -1
        for m in range(M):
            if not keep[m]:
                continue
            if not _nb_gather(proj[v], ok[v], ab[m, 0], ab[m, 1], px, py):
                continue
            code = _nb_layer_code(centres[v], o, en, dims, ab[m, 0], ab[m, 1])
            n, c0, c1, r0, r1, fu, fv = _nb_hull(px, py, code, W, H, ex, ey, ec)
            depth = _nb_layer_depth(cams[v], o, ea, eb, en, ab[m, 0], ab[m, 1])
            k = 0
            if n > 0:
                for r in range(r0, r1 + 1):
                    lo, hi = _nb_span(ex, ey, ec, n, r, c0, c1)
                    for col in range(lo, hi + 1):
                        k += 1
                        if depth < zb[r, col]:
                            zb[r, col] = depth
                            ob[r, col] = m
                    if lo <= hi:
                        br0 = min(br0, r)
                        br1 = max(br1, r)
                        bc0 = min(bc0, lo)
                        bc1 = max(bc1, hi)
            if k == 0 and fu >= 0:
                if depth < zb[fv, fu]:
                    zb[fv, fu] = depth
                    ob[fv, fu] = m
                br0 = min(br0, fv)
                br1 = max(br1, fv)
                bc0 = min(bc0, fu)
                bc1 = max(bc1, fu)
        box[v, 0] = br0
        box[v, 1] = br1
        box[v, 2] = bc0
        box[v, 3] = bc1


@nb.njit(cache=True, nogil=True)
def _nb_clear_buffer(v0, v1, zbuf, obuf, box):
    for v in range(v0, v1):
        for r in range(box[v, 0], box[v, 1] + 1):
            for c in range(box[v, 2], box[v, 3] + 1):
                zbuf[v, r, c] = np.inf
                obuf[v, r, c] = -1


@nb.njit(cache=True, nogil=True)
def _nb_layer_background(v0, v1, needed, ab, proj, ok, o, ea, eb, en, dims, centres, cams, bg, bgcnt, cnt):
    """Project a layer's corners, and count each voxel's footprint pixels and background pixels per view."""
    _nb_project_layer(v0, v1, needed, o, ea, eb, en, cams, proj, ok)
    M = ab.shape[0]
    H = bg.shape[1]
    W = bg.shape[2]
    px = np.empty(8)
    py = np.empty(8)
    ex = np.empty(16)
    ey = np.empty(16)
    ec = np.empty(16)
    for v in range(v0, v1):
        bgv = bg[v]
        for m in range(M):
            bgcnt[v, m] = 0
            cnt[v, m] = 0
            if not _nb_gather(proj[v], ok[v], ab[m, 0], ab[m, 1], px, py):
                continue
            code = _nb_layer_code(centres[v], o, en, dims, ab[m, 0], ab[m, 1])
            n, c0, c1, r0, r1, fu, fv = _nb_hull(px, py, code, W, H, ex, ey, ec)
            k = 0
            nbg = 0
            if n > 0:
                for r in range(r0, r1 + 1):
                    lo, hi = _nb_span(ex, ey, ec, n, r, c0, c1)
                    for col in range(lo, hi + 1):
                        k += 1
                        if bgv[r, col]:
                            nbg += 1
            if k == 0 and fu >= 0:
                k = 1
                if bgv[fv, fu]:
                    nbg += 1
            bgcnt[v, m] = nbg
            cnt[v, m] = k


@nb.njit(cache=True, nogil=True)
def _nb_layer_pass(v0, v1, ab, keep, sel, proj, ok, o, ea, eb, en, dims, centres, cams, images, marks, zbuf, obuf, box, bg, use_bg, n_vis, n_tot, sums, sq, bgcnt, cnt):
    """One test of a layer in views v0..v1-1 (corners already in ``proj``): item buffer of the kept voxels, statistics."""
    _nb_layer_buffer(v0, v1, ab, keep, proj, ok, o, ea, eb, en, dims, centres, cams, zbuf, obuf, box)
    _nb_layer_stats(v0, v1, ab, sel, proj, ok, o, ea, eb, en, dims, centres, cams, images, marks, zbuf, obuf, bg, use_bg, n_vis, n_tot, sums, sq, bgcnt, cnt)
    _nb_clear_buffer(v0, v1, zbuf, obuf, box)


@nb.njit(cache=True, nogil=True)
def _nb_voxel_corners(cam, cx, cy, cz, half, px, py):
    k = 0
    for s in range(2):
        for i in range(2):
            for j in range(2):
                u, v, z = _nb_project(cam, cx + (2 * i - 1) * half, cy + (2 * j - 1) * half, cz + (2 * s - 1) * half)
                if z <= 0.0:
                    return False
                px[k] = u
                py[k] = v
                k += 1
    return True


@nb.njit(cache=True, nogil=True)
def _nb_item_buffers(v0, v1, ijk, origin, vs, cams, zbuf, ids):
    """Per view: the voxel nearest the camera (by centre depth) over each pixel."""
    M = ijk.shape[0]
    H = zbuf.shape[1]
    W = zbuf.shape[2]
    half = 0.5 * vs
    for v in range(v0, v1):
        px = np.empty(8)
        py = np.empty(8)
        ex = np.empty(16)
        ey = np.empty(16)
        ec = np.empty(16)
        zb = zbuf[v]
        idv = ids[v]
        for r in range(H):
            for col in range(W):
                zb[r, col] = np.inf
                idv[r, col] = -1
        cam = cams[v]
        for m in range(M):
            cx = origin[0] + ijk[m, 0] * vs
            cy = origin[1] + ijk[m, 1] * vs
            cz = origin[2] + ijk[m, 2] * vs
            if not _nb_voxel_corners(cam, cx, cy, cz, half, px, py):
                continue
            depth = cam[6] * cx + cam[7] * cy + cam[8] * cz + cam[11]
            code = _nb_voxel_code(cam, cx, cy, cz, half)
            n, c0, c1, r0, r1, fu, fv = _nb_hull(px, py, code, W, H, ex, ey, ec)
            k = 0
            if n > 0:
                for r in range(r0, r1 + 1):
                    lo, hi = _nb_span(ex, ey, ec, n, r, c0, c1)
                    for col in range(lo, hi + 1):
                        k += 1
                        if depth < zb[r, col]:
                            zb[r, col] = depth
                            idv[r, col] = m
            if k == 0 and fu >= 0 and depth < zb[fv, fu]:
                zb[fv, fu] = depth
                idv[fv, fu] = m


@nb.njit(cache=True, nogil=True)
def _nb_owned_stats(v0, v1, ijk, origin, vs, cams, images, ids, bg, use_bg, n_vis, n_tot, sums, sq, bgcnt, cnt):
    """Like _nb_layer_stats, but a pixel is visible to the voxel that owns it in the item buffer."""
    M = ijk.shape[0]
    H = images.shape[1]
    W = images.shape[2]
    C = images.shape[3]
    half = 0.5 * vs
    for v in range(v0, v1):
        px = np.empty(8)
        py = np.empty(8)
        ex = np.empty(16)
        ey = np.empty(16)
        ec = np.empty(16)
        out = np.empty(10)
        cam = cams[v]
        bgv = bg[v] if use_bg else bg[0]
        for m in range(M):
            cx = origin[0] + ijk[m, 0] * vs
            cy = origin[1] + ijk[m, 1] * vs
            cz = origin[2] + ijk[m, 2] * vs
            if not _nb_voxel_corners(cam, cx, cy, cz, half, px, py):
                _nb_clear(v, m, C, n_vis, n_tot, sums, sq, bgcnt, cnt)
                continue
            code = _nb_voxel_code(cam, cx, cy, cz, half)
            n, c0, c1, r0, r1, fu, fv = _nb_hull(px, py, code, W, H, ex, ey, ec)
            _nb_accumulate(images[v], ids[v], bgv, use_bg, m, m, ids[v], ids[v], False, 0.0, ex, ey, ec, n, c0, c1, r0, r1, fu, fv, out)
            _nb_store(out, v, m, C, n_vis, n_tot, sums, sq, bgcnt, cnt)

