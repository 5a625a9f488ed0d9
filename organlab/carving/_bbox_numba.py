"""numba kernels of :func:`organlab.carving.carve`: the bounding-box test
decided coarse to fine with a summed-area table.

Blocks of ``2**l`` voxels (level ``l``; level 0 = one voxel) are tested with a
*conservative* pixel range that contains the pixel range of every voxel in the
block:

* the block's 8 corners are in front of the camera, so the pinhole projection
  of the (convex) block lies in the bounding box of the 8 corners' normalized
  coordinates (widened by a rounding margin);
* the distortion of that rectangle is bounded by interval arithmetic on the
  distortion polynomial, then mapped to pixels and widened by a margin.

If that range lies inside the image and holds fewer than ``min_pixels``
silhouette pixels, every voxel of the block is carved; if every in-image pixel
of it is silhouette (``min_pixels == 1``) or it lies wholly outside the image,
every voxel is kept; otherwise the 8 children are tested.  A block of 2x2x2
voxels that is still undecided projects its 27 corners (in numba, within a
few 1e-6 px of :meth:`Camera.project`) and decides each voxel with an outer
and an inner pixel range; the rare voxel the two ranges do not decide (a box
edge within a rounding margin of a pixel edge, a corner near the camera
plane) is deferred to an exact test through :meth:`Camera.project` itself,
which makes the occupancy bit for bit that of :func:`carve_reference`.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from ..nbcam import to_camera, to_pixel


@njit(cache=True)
def sat_of(mask):
    """Summed-area table (H + 1, W + 1) int32 of a bool mask (as ``_bbox._sat``)."""
    h, w = mask.shape
    s = np.zeros((h + 1, w + 1), dtype=np.int32)
    for r in range(h):
        acc = 0
        for c in range(w):
            acc += mask[r, c]
            s[r + 1, c + 1] = s[r, c + 1] + acc
    return s


@njit(cache=True, inline="always")
def _rect_sum(sat, c0, c1, r0, r1):
    return sat[r1 + 1, c1 + 1] - sat[r0, c1 + 1] - sat[r1 + 1, c0] + sat[r0, c0]


@njit(cache=True, inline="always")
def _imul(al, ah, bl, bh):
    p1 = al * bl
    p2 = al * bh
    p3 = ah * bl
    p4 = ah * bh
    return min(min(p1, p2), min(p3, p4)), max(max(p1, p2), max(p3, p4))


@njit(cache=True, inline="always")
def _isq(l, h):
    if l >= 0.0:
        return l * l, h * h
    if h <= 0.0:
        return h * h, l * l
    return 0.0, max(l * l, h * h)


@njit(cache=True, inline="always")
def _iscale(k, l, h):
    if k >= 0.0:
        return k * l, k * h
    return k * h, k * l


@njit(cache=True)
def _block_range(cp, ax, ay, az, x0, x1, y0, y1, z0, z1):
    """Conservative pixel range of the voxels in corners [x0, x1] x ... .

    Returns (ok, c0, c1, r0, r1) as floats; ok False if undecidable (a corner
    near or behind the camera plane, non-finite values).
    """
    ok, ul, uh, vl, vh, eu, ev = _block_uv(cp, ax, ay, az, x0, x1, y0, y1, z0, z1)
    if not ok:
        return False, 0.0, 0.0, 0.0, 0.0
    return True, np.ceil(ul - eu - 0.5), np.floor(uh + eu + 0.5), np.ceil(vl - ev - 0.5), np.floor(vh + ev + 0.5)


@njit(cache=True)
def _block_uv(cp, ax, ay, az, x0, x1, y0, y1, z0, z1):
    """Bounds of the projections (px) of the box with corners [x0, x1] x ... .

    Returns (ok, ul, uh, vl, vh, eu, ev): every point of the box projects
    within ``[ul - eu, uh + eu] x [vl - ev, vh + ev]``; ok False if
    undecidable (a corner near or behind the camera plane, non-finite values).
    """
    xl = np.inf
    xh = -np.inf
    yl = np.inf
    yh = -np.inf
    pn = 0.0
    for a in range(2):
        X = ax[x0] if a == 0 else ax[x1]
        for b in range(2):
            Y = ay[y0] if b == 0 else ay[y1]
            for c in range(2):
                Z = az[z0] if c == 0 else az[z1]
                xc, yc, zc = to_camera(cp, X, Y, Z)
                mag = abs(X) + abs(Y) + abs(Z) + cp[22] + 1.0
                if not zc > 1e-6 * mag:
                    return False, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
                x = xc / zc
                y = yc / zc
                xl = min(xl, x)
                xh = max(xh, x)
                yl = min(yl, y)
                yh = max(yh, y)
                pn = max(pn, mag / zc)
    d = 1e-9 * (1.0 + max(abs(xl), abs(xh)) + max(abs(yl), abs(yh)) + pn)
    xl -= d
    xh += d
    yl -= d
    yh += d
    k1, k2, p1, p2, k3 = cp[17], cp[18], cp[19], cp[20], cp[21]
    x2l, x2h = _isq(xl, xh)
    y2l, y2h = _isq(yl, yh)
    r2l = x2l + y2l
    r2h = x2h + y2h
    r4l = r2l * r2l
    r4h = r2h * r2h
    r6l = r4l * r2l
    r6h = r4h * r2h
    t1l, t1h = _iscale(k1, r2l, r2h)
    t2l, t2h = _iscale(k2, r4l, r4h)
    t3l, t3h = _iscale(k3, r6l, r6h)
    radl = 1.0 + t1l + t2l + t3l
    radh = 1.0 + t1h + t2h + t3h
    xyl, xyh = _imul(xl, xh, yl, yh)
    axl, axh = _imul(xl, xh, radl, radh)
    ayl, ayh = _imul(yl, yh, radl, radh)
    b1l, b1h = _iscale(2.0 * p1, xyl, xyh)
    b2l, b2h = _iscale(p2, r2l + 2.0 * x2l, r2h + 2.0 * x2h)
    xdl = axl + b1l + b2l
    xdh = axh + b1h + b2h
    c1l, c1h = _iscale(p1, r2l + 2.0 * y2l, r2h + 2.0 * y2h)
    c2l, c2h = _iscale(2.0 * p2, xyl, xyh)
    ydl = ayl + c1l + c2l
    ydh = ayh + c1h + c2h
    fx, k01, cx, fy, cy = cp[12], cp[13], cp[14], cp[15], cp[16]
    ul0, uh0 = _iscale(fx, xdl, xdh)
    ul1, uh1 = _iscale(k01, ydl, ydh)
    ul = ul0 + ul1 + cx
    uh = uh0 + uh1 + cx
    vl, vh = _iscale(fy, ydl, ydh)
    vl += cy
    vh += cy
    if not (ul == ul and uh == uh and vl == vl and vh == vh):
        return False, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    eu = 1e-6 + 1e-9 * (abs(ul) + abs(uh) + abs(ul0) + abs(uh0) + abs(cx))
    ev = 1e-6 + 1e-9 * (abs(vl) + abs(vh) + abs(cy))
    return True, ul, uh, vl, vh, eu, ev


@njit(cache=True, inline="always")
def _range_decision(sat, w, h, c0, c1, r0, r1, min_pixels, allow_keep):
    """0 = carve all, 1 = keep all, 2 = undecided, for a conservative range."""
    inside = c0 >= 0 and r0 >= 0 and c1 <= w - 1 and r1 <= h - 1
    if inside:
        s = _rect_sum(sat, int(c0), int(c1), int(r0), int(r1))
        if s < min_pixels:
            return 0
        if allow_keep and s == (c1 - c0 + 1) * (r1 - r0 + 1):
            return 1
        return 2
    # clip to the image; outside pixels count as silhouette
    cc0 = max(c0, 0.0)
    cc1 = min(c1, w - 1.0)
    rr0 = max(r0, 0.0)
    rr1 = min(r1, h - 1.0)
    if cc0 > cc1 or rr0 > rr1:
        return 1  # wholly outside the image: nothing known, nothing carved
    if allow_keep:
        s = _rect_sum(sat, int(cc0), int(cc1), int(rr0), int(rr1))
        if s == (cc1 - cc0 + 1) * (rr1 - rr0 + 1):
            return 1
    return 2


@njit(cache=True, inline="always")
def _pyr_index(off, dims, l, x, y, z):
    return off[l] + ((x >> l) * dims[l, 1] + (y >> l)) * dims[l, 2] + (z >> l)


@njit(cache=True)
def _kill(counts, pyr, off, dims, L, x, y, z, tol):
    """One more view carves voxel (x, y, z) (alive on entry)."""
    c = counts[x, y, z] + 1
    counts[x, y, z] = c
    if c > tol:
        for l in range(1, L + 1):
            pyr[_pyr_index(off, dims, l, x, y, z)] -= 1


@njit(cache=True)
def _carve_box(counts, pyr, off, dims, L, x0, x1, y0, y1, z0, z1, tol):
    for x in range(x0, x1):
        for y in range(y0, y1):
            for z in range(z0, z1):
                if counts[x, y, z] <= tol:
                    _kill(counts, pyr, off, dims, L, x, y, z, tol)


# A kernel longer than the project's 80-line rule, on purpose: it is the innermost loop of
# `carve` (corner projection, conservative pixel range and the summed-area test of the 8
# voxels of a block), kept in one piece so that the hot loop makes no further calls.
@njit(cache=True)
def _leaf(cp, sat, w, h, ax, ay, az, counts, pyr, off, dims, L, x0, y0, z0, tol, min_pixels, deferred, nd_start, nd,
          U, V, S):
    """Decide every alive voxel of the 2x2x2 block at (x0, y0, z0).

    Returns the new number of deferred voxels of the top block.
    """
    nx, ny, nz = counts.shape
    x1 = min(x0 + 2, nx)
    y1 = min(y0 + 2, ny)
    z1 = min(z0 + 2, nz)
    # U, V, S: (3, 3, 3) scratch: projected corners, 1 front / 0 near plane / -1 behind
    k1, k2, p1, p2, k3 = cp[17], cp[18], cp[19], cp[20], cp[21]
    fx, k01, cx, fy, cy = cp[12], cp[13], cp[14], cp[15], cp[16]
    e = 0.0
    for i in range(x1 - x0 + 1):
        X = ax[x0 + i]
        for j in range(y1 - y0 + 1):
            Y = ay[y0 + j]
            for k in range(z1 - z0 + 1):
                Z = az[z0 + k]
                xc, yc, zc = to_camera(cp, X, Y, Z)
                mag = abs(X) + abs(Y) + abs(Z) + cp[22] + 1.0
                if zc > 1e-6 * mag:
                    S[i, j, k] = 1
                elif zc < -1e-6 * mag:
                    S[i, j, k] = -1
                    continue
                else:
                    S[i, j, k] = 0
                    continue
                x = xc / zc
                y = yc / zc
                u, v = to_pixel(cp, x, y)
                U[i, j, k] = u
                V[i, j, k] = v
                if not (u == u and v == v):
                    S[i, j, k] = 0
                    continue
                r2 = x * x + y * y
                ar = 1.0 + abs(k1) * r2 + abs(k2) * r2 * r2 + abs(k3) * r2 * r2 * r2
                ar += 3.0 * (abs(p1) + abs(p2)) * (1.0 + abs(x) + abs(y))
                sc = (fx + abs(k01) + fy) * (1.0 + abs(x) + abs(y) + mag / zc) * ar + abs(cx) + abs(cy)
                e = max(e, 1e-6 + 1e-9 * sc)
    for x in range(x0, x1):
        for y in range(y0, y1):
            for z in range(z0, z1):
                if counts[x, y, z] > tol:
                    continue
                i = x - x0
                j = y - y0
                k = z - z0
                behind = False
                near = False
                umin = np.inf
                umax = -np.inf
                vmin = np.inf
                vmax = -np.inf
                for a in range(2):
                    for b in range(2):
                        for c in range(2):
                            s = S[i + a, j + b, k + c]
                            if s < 0:
                                behind = True
                            elif s == 0:
                                near = True
                            else:
                                uu = U[i + a, j + b, k + c]
                                vv = V[i + a, j + b, k + c]
                                umin = min(umin, uu)
                                umax = max(umax, uu)
                                vmin = min(vmin, vv)
                                vmax = max(vmax, vv)
                if behind:
                    continue  # a corner surely behind the camera: not carved
                if near:
                    deferred[nd_start + nd] = (x * ny + y) * nz + z
                    nd += 1
                    continue
                # outer range: contains the exact one
                oc0 = np.ceil(umin - e - 0.5)
                oc1 = np.floor(umax + e + 0.5)
                or0 = np.ceil(vmin - e - 0.5)
                or1 = np.floor(vmax + e + 0.5)
                if oc0 >= 0 and or0 >= 0 and oc1 <= w - 1 and or1 <= h - 1:
                    if _rect_sum(sat, int(oc0), int(oc1), int(or0), int(or1)) < min_pixels:
                        _kill(counts, pyr, off, dims, L, x, y, z, tol)
                        continue
                # inner range: contained in the exact one
                ic0 = np.ceil(umin + e - 0.5)
                ic1 = np.floor(umax - e + 0.5)
                ir0 = np.ceil(vmin + e - 0.5)
                ir1 = np.floor(vmax - e + 0.5)
                if ic0 <= ic1 and ir0 <= ir1:
                    if ic0 < 0 or ir0 < 0 or ic1 > w - 1 or ir1 > h - 1:
                        continue  # reaches outside the image: kept
                    if _rect_sum(sat, int(ic0), int(ic1), int(ir0), int(ir1)) >= min_pixels:
                        continue
                deferred[nd_start + nd] = (x * ny + y) * nz + z
                nd += 1
    return nd


@njit(cache=True, parallel=True)
def carve_view(cp, sat, w, h, ax, ay, az, counts, pyr, off, dims, L, tops, tol, min_pixels, deferred, ndef):
    """Apply one view to every alive voxel; fill ``deferred`` with undecided ones.

    tops : (n, 3) int64 indices of the top blocks (level L) to visit.
    deferred : per top block ``t`` the slots ``[t * 8**L, ...)``, count in ndef[t].
    """
    allow_keep = min_pixels <= 1
    nx, ny, nz = counts.shape
    cap = 1 << (3 * L)
    for t in prange(tops.shape[0]):
        ndef[t] = 0
        bx, by, bz = tops[t, 0], tops[t, 1], tops[t, 2]
        if pyr[off[L] + (bx * dims[L, 1] + by) * dims[L, 2] + bz] == 0:
            continue
        stack = np.empty((8 * L + 8, 4), dtype=np.int64)
        U = np.empty((3, 3, 3))
        V = np.empty((3, 3, 3))
        S = np.empty((3, 3, 3), dtype=np.int8)
        stack[0, 0] = L
        stack[0, 1] = bx
        stack[0, 2] = by
        stack[0, 3] = bz
        top = 1
        nd = 0
        while top > 0:
            top -= 1
            l = stack[top, 0]
            x0 = stack[top, 1] << l
            y0 = stack[top, 2] << l
            z0 = stack[top, 3] << l
            if pyr[_pyr_index(off, dims, l, x0, y0, z0)] == 0:
                continue
            x1 = min(x0 + (1 << l), nx)
            y1 = min(y0 + (1 << l), ny)
            z1 = min(z0 + (1 << l), nz)
            ok, c0, c1, r0, r1 = _block_range(cp, ax, ay, az, x0, x1, y0, y1, z0, z1)
            dec = 2
            if ok:
                dec = _range_decision(sat, w, h, c0, c1, r0, r1, min_pixels, allow_keep)
            if dec == 0:
                _carve_box(counts, pyr, off, dims, L, x0, x1, y0, y1, z0, z1, tol)
            elif dec == 2:
                if l == 1:
                    nd = _leaf(cp, sat, w, h, ax, ay, az, counts, pyr, off, dims, L, x0, y0, z0, tol, min_pixels,
                               deferred, t * cap, nd, U, V, S)
                else:
                    for a in range(2):
                        xa = x0 + (a << (l - 1))
                        if xa >= nx:
                            continue
                        for b in range(2):
                            yb = y0 + (b << (l - 1))
                            if yb >= ny:
                                continue
                            for c in range(2):
                                zc = z0 + (c << (l - 1))
                                if zc >= nz:
                                    continue
                                stack[top, 0] = l - 1
                                stack[top, 1] = xa >> (l - 1)
                                stack[top, 2] = yb >> (l - 1)
                                stack[top, 3] = zc >> (l - 1)
                                top += 1
        ndef[t] = nd


@njit(cache=True)
def kill_many(counts, pyr, off, dims, L, flat, tol):
    nx, ny, nz = counts.shape
    for n in range(flat.shape[0]):
        f = flat[n]
        z = f % nz
        y = (f // nz) % ny
        x = f // (nz * ny)
        if counts[x, y, z] <= tol:
            _kill(counts, pyr, off, dims, L, x, y, z, tol)


@njit(cache=True, parallel=True)
def build_pyramid(counts, pyr, off, dims, L, tol):
    """Alive-voxel counts of every block of every level 1..L."""
    pyr[:] = 0
    nx, ny, nz = counts.shape
    # level 1 from voxels, in parallel over x-pairs (disjoint writes)
    for bx in prange(dims[1, 0]):
        for x in range(2 * bx, min(2 * bx + 2, nx)):
            for y in range(ny):
                for z in range(nz):
                    if counts[x, y, z] <= tol:
                        pyr[off[1] + (bx * dims[1, 1] + (y >> 1)) * dims[1, 2] + (z >> 1)] += 1
    for l in range(2, L + 1):
        for x in range(dims[l - 1, 0]):
            for y in range(dims[l - 1, 1]):
                for z in range(dims[l - 1, 2]):
                    pyr[off[l] + ((x >> 1) * dims[l, 1] + (y >> 1)) * dims[l, 2] + (z >> 1)] += pyr[
                        off[l - 1] + (x * dims[l - 1, 1] + y) * dims[l - 1, 2] + z
                    ]
