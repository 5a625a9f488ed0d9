"""The hull field in a narrow band: cost that grows with the surface, not the volume.

:func:`organlab.carving.hull_field` samples, at every voxel centre, a field
clipped to ``[-0.5, 1.5]``: only voxels less than one voxel from the hull's
surface hold anything but the two clip values.  This module finds those
voxels coarse to fine and computes the field only there:

1. Per view, the signed distance image ``sdf`` (px, as the dense field) and
   two summed-area tables: of the pixels with ``sdf >= T`` and of those with
   ``sdf <= -T``, where ``T`` (px) bounds one voxel seen at the grid's
   nearest depth, magnified by the lens: ``T >= voxel * sqrt(det J) / Z``
   for every voxel, with ``Z`` the smallest depth of the grid's corners and
   ``sqrt(det J)`` the largest over the box of their normalized image
   coordinates (sampled 17 x 17, times 1.1).
2. Blocks of voxels, from ``B * 2**L`` down to ``B`` voxels a side, are tested
   view by view with the conservative pixel range of their voxel centres
   (:func:`organlab.carving._bbox_numba._block_range`, interval arithmetic on
   the distortion), widened by the one pixel bilinear sampling reaches.  If
   that range lies in the image and every pixel of it has ``sdf >= T``, the
   bilinear sample at every voxel centre is ``>= T`` px, i.e. at least one
   voxel inside: the view leaves the block at the clip value.  If every pixel
   has ``sdf <= -T``, the view carves the whole block.  A block that ``k + 1``
   views carve (``tolerance=k``) is empty; a block that every view leaves
   inside (or cannot see) is full; only the others are split, and only the
   views that did not decide a block are tested again on its children.
3. In the leaf blocks still undecided (the band) the field is computed voxel
   by voxel exactly as the dense field (the same numba code), with the views
   the block's ancestors decided folded in as their clip values.

The result is the dense field's, value for value (the tests check 0
differences); memory is a block label per ``B**3`` voxels plus the band's
values.  :class:`organlab.bandfield.BandField` (plain data, ground floor) holds it
and gives the dense field and the occupancy; its surface is
:func:`organlab.surface.mesh_from_field` (marching cubes on the band only).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from ..bandfield import BAND, BandField
from ..nbcam import N_CP, pack_camera, to_camera
from ._bbox_numba import _block_uv, _rect_sum
from ._sample import insert_smallest, view_dmm

__all__ = ["band_field"]

_UNDECIDED = 3
_UNSEEN = 2


# ------------------------------------------------- per-view preparation
def _sqrt_det(cp, xn, yn):
    """``sqrt(det J)`` of the projection at normalized coordinates (as ``view_dmm``), vectorized."""
    k1, k2, p1, p2, k3 = cp[17:22]
    r2 = xn * xn + yn * yn
    rad = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    drad = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)
    j00 = rad + 2.0 * xn * xn * drad + 2.0 * p1 * yn + 6.0 * p2 * xn
    j01 = 2.0 * xn * yn * drad + 2.0 * p1 * xn + 2.0 * p2 * yn
    j11 = rad + 2.0 * yn * yn * drad + 6.0 * p1 * yn + 2.0 * p2 * xn
    return np.sqrt(np.abs(j00 * j11 - j01 * j01) * cp[12] * cp[15])


def _threshold_px(camera, grid):
    """``T`` (px): one voxel at the grid's nearest depth times the largest lens magnification, with margin.

    ``inf`` (the view decides no block; the band field is still exact, only
    slower) when the grid reaches within a voxel of the camera plane.
    """
    lo, hi = grid.bounds
    corners = np.array([[a, b, c] for a in (lo[0], hi[0]) for b in (lo[1], hi[1]) for c in (lo[2], hi[2])])
    pc = camera.world_to_camera(corners)
    zmin = pc[:, 2].min()
    if zmin <= grid.voxel_size:
        return math.inf
    xn, yn = pc[:, 0] / pc[:, 2], pc[:, 1] / pc[:, 2]
    gx, gy = np.meshgrid(np.linspace(xn.min(), xn.max(), 17), np.linspace(yn.min(), yn.max(), 17))
    mag = _sqrt_det(pack_camera(camera), gx, gy).max()
    return 1.1 * grid.voxel_size * mag / zmin + 1e-3


def _view_tables(sdfs, hmax, wmax, tpx):
    """Per view, summed-area tables (H + 1, W + 1) int32 of ``sdf >= T`` and ``sdf <= -T``, as a
    ``(V, hmax + 1, wmax + 1)`` pair (zero beyond a smaller view's table).

    ``cv2.integral`` of the two masks: the same integers as summing them in a numba kernel, at about
    0.04 s CPU for the sample's 36 views of 640 x 480 px against its 0.10-0.13 s (best of 10; issue 24).
    The comparisons are float32 against ``T`` rounded up to float32 (:func:`_at_least_float32`), the
    same as comparing in float64.
    """
    import cv2

    nv = len(sdfs)
    sats_in = np.zeros((nv, hmax + 1, wmax + 1), dtype=np.int32)
    sats_out = np.zeros((nv, hmax + 1, wmax + 1), dtype=np.int32)
    for v, s in enumerate(sdfs):
        h, w = s.shape
        t = _at_least_float32(tpx[v])
        s = np.asarray(s, dtype=np.float32)
        sats_in[v, : h + 1, : w + 1] = cv2.integral((s >= t).view(np.uint8), sdepth=cv2.CV_32S)
        sats_out[v, : h + 1, : w + 1] = cv2.integral((s <= -t).view(np.uint8), sdepth=cv2.CV_32S)
    return sats_in, sats_out


def _at_least_float32(t):
    """The smallest float32 ``>= t`` (a float): for float32 ``d``, ``d >= t`` exactly when ``d >= it``, and
    ``d <= -t`` exactly when ``d <= -it`` (no float32 lies between the two)."""
    t32 = np.float32(t)
    return np.nextafter(t32, np.float32(np.inf)) if float(t32) < float(t) else t32  # compared as doubles


# --------------------------------------------------------- classification
@njit(cache=True, nogil=True)
def _view_state(cp, sat_in, sat_out, w, h, ax, ay, az, x0, x1, y0, y1, z0, z1):
    """State of the voxel centres ``[x0, x1] x [y0, y1] x [z0, z1]`` (inclusive) in one view.

    0 every centre carved (``dmm = -lim``), 1 every centre at the clip value
    ``+lim``, 2 the view sees none of them, 3 undecided.
    """
    ok, ul, uh, vl, vh, eu, ev = _block_uv(cp, ax, ay, az, x0, x1, y0, y1, z0, z1)
    if not ok:
        for a in range(2):
            for b in range(2):
                for c in range(2):
                    X = ax[x0] if a == 0 else ax[x1]
                    Y = ay[y0] if b == 0 else ay[y1]
                    Z = az[z0] if c == 0 else az[z1]
                    if to_camera(cp, X, Y, Z)[2] > 0.0:
                        return 3
        return 2  # wholly on or behind the camera plane (the block is convex)
    if uh + eu < -0.5 or ul - eu > w - 0.5 or vh + ev < -0.5 or vl - ev > h - 0.5:
        return 2  # every centre projects beyond the image's outer edge
    # the pixels bilinear sampling reads for any centre of the block
    c0 = np.floor(ul - eu)
    c1 = np.floor(uh + eu) + 1.0
    r0 = np.floor(vl - ev)
    r1 = np.floor(vh + ev) + 1.0
    if c0 < 0 or r0 < 0 or c1 > w - 1 or r1 > h - 1:
        return 3
    area = (c1 - c0 + 1) * (r1 - r0 + 1)
    if _rect_sum(sat_in, int(c0), int(c1), int(r0), int(r1)) == area:
        return 1
    if _rect_sum(sat_out, int(c0), int(c1), int(r0), int(r1)) == area:
        return 0
    return 3


@njit(cache=True, parallel=True)
def _classify(blocks, size, active, nout, nseen, cps, sats_in, sats_out, whs, ax, ay, az, tol, min_views):
    """Decide blocks of ``size`` voxels; update their active views, carve and seen counts.

    Returns ``state`` per block: 0 outside, 1 inside, 3 split further.
    """
    n = blocks.shape[0]
    nv = cps.shape[0]
    nx, ny, nz = ax.shape[0], ay.shape[0], az.shape[0]
    state = np.empty(n, dtype=np.int8)
    for q in prange(n):
        x0 = blocks[q, 0] * size
        y0 = blocks[q, 1] * size
        z0 = blocks[q, 2] * size
        x1 = min(x0 + size, nx) - 1
        y1 = min(y0 + size, ny) - 1
        z1 = min(z0 + size, nz) - 1
        undecided = False
        st = -1
        for v in range(nv):
            if active[q, v] == 0:
                continue
            s = _view_state(cps[v], sats_in[v], sats_out[v], whs[v, 0], whs[v, 1], ax, ay, az, x0, x1, y0, y1, z0, z1)
            if s == 3:
                undecided = True
                continue
            active[q, v] = 0
            if s == 0:
                nout[q] += 1
                nseen[q] += 1
                if nout[q] > tol:
                    st = 0
                    break
            elif s == 1:
                nseen[q] += 1
        if st < 0:
            if undecided:
                st = 3
            elif nseen[q] < min_views:
                st = 0
            else:
                st = 1
        state[q] = st
    return state


@njit(cache=True)
def _paint(states, blocks, st, scale):
    """Set the leaf blocks covered by decided blocks (``scale`` leaves a side)."""
    bx, by, bz = states.shape
    for q in range(blocks.shape[0]):
        s = st[q]
        if s > 1:
            continue
        for i in range(blocks[q, 0] * scale, min(blocks[q, 0] * scale + scale, bx)):
            for j in range(blocks[q, 1] * scale, min(blocks[q, 1] * scale + scale, by)):
                for k in range(blocks[q, 2] * scale, min(blocks[q, 2] * scale + scale, bz)):
                    states[i, j, k] = s


# ------------------------------------------------------------ the band
@njit(cache=True, parallel=True)
def _band_values(blocks, B, active, nout, nseen, sdfs, whs, cps, origin, vs, shape, lim, tol, min_views):
    """The field, voxel by voxel as the dense field, in the band blocks."""
    n = blocks.shape[0]
    nv = cps.shape[0]
    nx, ny, nz = shape[0], shape[1], shape[2]
    kk = tol + 1
    out = np.full((n, B, B, B), np.float32(-0.5))
    for q in prange(n):
        views = np.empty(nv, dtype=np.int64)
        m = 0
        for v in range(nv):
            if active[q, v] != 0:
                views[m] = v
                m += 1
        best = np.empty(kk, dtype=np.float32)
        first = 0
        for i in range(blocks[q, 0] * B, min(blocks[q, 0] * B + B, nx)):
            x = origin[0] + i * vs
            for j in range(blocks[q, 1] * B, min(blocks[q, 1] * B + B, ny)):
                y = origin[1] + j * vs
                for k in range(blocks[q, 2] * B, min(blocks[q, 2] * B + B, nz)):
                    z = origin[2] + k * vs
                    best[:] = lim
                    for c in range(min(nout[q], kk)):
                        best[c] = -lim
                    seen = nseen[q]
                    carver = first
                    # the view that carved the previous voxel first: neighbours are carved by the same
                    # views, and the value does not depend on the order
                    for a in range(m):
                        if best[kk - 1] <= -lim:
                            break
                        v = views[(a + first) % m]
                        ok, dmm = view_dmm(sdfs[v], whs[v, 1], whs[v, 0], cps[v], x, y, z, lim)
                        if ok:
                            seen += 1
                            insert_smallest(best, dmm)
                            if dmm <= -lim:
                                carver = (a + first) % m
                    first = carver
                    f = 0.5 + np.float64(best[tol]) / vs
                    f = min(max(f, -0.5), 1.5)
                    if min_views > 0 and seen < min_views:
                        f = -0.5
                    out[q, i - blocks[q, 0] * B, j - blocks[q, 1] * B, k - blocks[q, 2] * B] = f
    return out


_OFFSETS = np.array([[a, b, c] for a in (0, 1) for b in (0, 1) for c in (0, 1)], dtype=np.int64)


def band_field(sdfs, cameras, grid, *, tolerance, min_views, block=4, levels=4):
    """Narrow-band hull field from the views' signed distance images.

    Parameters
    ----------
    sdfs : (V, H, W) float32 array or list of (H, W) float32, px, inside positive
        From ``_field._signed_distance``, one per view.
    cameras : list of Camera
    grid : VoxelGrid
    tolerance, min_views : int
        As in :func:`organlab.carving.hull_field` (validated there).
    block : int
        Leaf block edge, voxels.
    levels : int
        Coarse levels above the leaves: blocks of ``block * 2**levels`` voxels first.

    Returns
    -------
    BandField
    """
    nv = len(cameras)
    shape = np.asarray(grid.shape, dtype=np.int64)
    B = int(block)
    nb = -(-shape // B)
    L = int(max(0, min(levels, math.ceil(math.log2(max(nb.max(), 1))))))
    lim = np.float32(grid.voxel_size)
    ax, ay, az = (np.ascontiguousarray(a, dtype=np.float64) for a in grid.axes())
    hmax = max(s.shape[0] for s in sdfs)
    wmax = max(s.shape[1] for s in sdfs)
    cps = np.stack([pack_camera(c) for c in cameras]).reshape(nv, N_CP)
    whs = np.array([[s.shape[1], s.shape[0]] for s in sdfs], dtype=np.int64)
    tpx = np.array([_threshold_px(c, grid) for c in cameras], dtype=np.float64)
    if isinstance(sdfs, np.ndarray):
        stack = np.ascontiguousarray(sdfs, dtype=np.float32)
    elif all(s.shape == (hmax, wmax) for s in sdfs):
        stack = np.stack(sdfs)
    else:
        stack = np.zeros((nv, hmax, wmax), dtype=np.float32)
        for v, s in enumerate(sdfs):
            stack[v, : s.shape[0], : s.shape[1]] = s
    sats_in, sats_out = _view_tables(sdfs, hmax, wmax, tpx)

    states = np.zeros(tuple(nb), dtype=np.int8)
    top = -(-nb // (1 << L))
    # C order, as the later levels' blocks (boolean-indexed) are: one specialisation of _classify and _paint
    blocks = np.ascontiguousarray(np.indices(tuple(int(t) for t in top)).reshape(3, -1).T, dtype=np.int64)
    active = np.ones((len(blocks), nv), dtype=np.uint8)
    nout = np.zeros(len(blocks), dtype=np.int64)
    nseen = np.zeros(len(blocks), dtype=np.int64)
    for lev in range(L, -1, -1):
        st = _classify(blocks, B << lev, active, nout, nseen, cps, sats_in, sats_out, whs, ax, ay, az,
                       int(tolerance), int(min_views))
        _paint(states, blocks, st, 1 << lev)
        und = st == 3
        blocks, active, nout, nseen = blocks[und], active[und], nout[und], nseen[und]
        if lev == 0:
            break
        kids = (blocks[:, None, :] * 2 + _OFFSETS[None]).reshape(-1, 3)
        keep = np.all(kids * (B << (lev - 1)) < shape, axis=1)
        rep = lambda a: np.repeat(a, 8, axis=0)[keep]  # noqa: E731
        blocks, active, nout, nseen = kids[keep], rep(active), rep(nout), rep(nseen)
    values = _band_values(blocks, B, active, nout, nseen, stack, whs, cps, np.asarray(grid.origin, np.float64),
                          float(grid.voxel_size), shape, lim, int(tolerance), int(min_views))
    index = np.full(tuple(nb), -1, dtype=np.int32)
    if len(blocks):
        states[blocks[:, 0], blocks[:, 1], blocks[:, 2]] = BAND
        index[blocks[:, 0], blocks[:, 1], blocks[:, 2]] = np.arange(len(blocks), dtype=np.int32)
    return BandField(grid, B, states, index, values)
