"""The two methods of :mod:`organlab.coloring`: layered voxel colouring and space carving (see docs/coloring.md)."""

from __future__ import annotations

import numpy as np

from ._common import _AXES
from ._kernels import (
    _nb_item_buffers,
    _nb_layer_background,
    _nb_layer_mark,
    _nb_layer_pass,
    _nb_owned_stats,
    _nb_project_layer,
)
from ._statistics import _Stats, _rgb, _seen_through, _support_2d, _support_3d, _within
from ._visibility import _all_within, _candidate_bounds, _occlusion_reach, _over_views, check_ordinal_visibility

_REFINE = 2
_DEBUG = None  # set to a list to collect (ijk, _Stats) per layer or pass (tests, tuning)


def _bg_arg(bg):
    return (bg, True) if bg is not None else (np.zeros((1, 1, 1), np.uint8), False)


def _layer_geometry(active, layer, axis, ax_a, ax_b, origin, h):
    """The active voxels of one layer: in-layer indices, the layer's corner, grid indices, needed corners.

    Returns ``ab`` (n, 2) int64 in-layer indices from the active box's corner, the box's size
    ``na``, ``nb``, its lowest corner (3,) mm, ``ijk`` (n, 3) grid indices and ``needed``
    (na + 1, nb + 1) bool: the voxel corners that some active voxel uses.
    """
    ia, ib = np.nonzero(active)
    a0, b0 = ia.min(), ib.min()
    na, nb = int(ia.max() - a0 + 1), int(ib.max() - b0 + 1)
    ab = np.stack([ia - a0, ib - b0], axis=1).astype(np.int64)
    corner = np.empty(3)
    corner[ax_a] = origin[ax_a] + (a0 - 0.5) * h
    corner[ax_b] = origin[ax_b] + (b0 - 0.5) * h
    corner[axis] = origin[axis] + (layer - 0.5) * h
    ijk = np.empty((len(ab), 3), np.int64)
    ijk[:, ax_a], ijk[:, ax_b], ijk[:, axis] = ia, ib, layer
    needed = np.zeros((na + 1, nb + 1), bool)
    for di in (0, 1):
        for dj in (0, 1):
            needed[ab[:, 0] + di, ab[:, 1] + dj] = True
    return ab, na, nb, corner, ijk, needed


def _voxel_coloring(stack, cams, cameras, bg, candidates, grid, threshold, measure, min_pix, min_frac, support, progress):
    """Seitz & Dyer's layered pass (see the module docstring)."""
    V, C = stack.shape[0], stack.shape[3]
    occ = candidates.copy()
    colors = np.zeros(grid.shape + (3,), np.uint8)
    colored = np.zeros(grid.shape, bool)
    counts = dict(carved_bg=0, hidden=0, untested=0)
    if not candidates.any():
        return occ, colors, colored, counts, None, 1
    lo, hi = _candidate_bounds(candidates, grid)
    axis, descending = check_ordinal_visibility(cameras, lo, hi)
    sweep = ("-" if descending else "+") + _AXES[axis]
    ax_a, ax_b = [d for d in range(3) if d != axis]
    h = grid.voxel_size
    origin = np.asarray(grid.origin, dtype=np.float64)
    ea, eb, en = np.zeros(3), np.zeros(3), np.zeros(3)
    ea[ax_a] = eb[ax_b] = en[axis] = h
    dims = np.array([ax_a, ax_b, axis], np.int64)
    centres = np.array([c.center for c in cameras], dtype=np.float64)
    bg_arr, use_bg = _bg_arg(bg)
    marks = np.zeros(stack.shape[:3], np.uint8)
    zbuf = np.full(stack.shape[:3], np.inf, np.float32)
    obuf = np.full(stack.shape[:3], -1, np.int32)
    box = np.empty((V, 4), np.int64)
    n_layers = grid.shape[axis]
    order = range(n_layers - 1, -1, -1) if descending else range(n_layers)
    reach = _occlusion_reach(cameras, lo, hi, axis, descending)
    prev = None  # occupancy of the previous layer, in-layer axes (a, b)
    for step, layer in enumerate(order):
        sub = np.take(candidates, layer, axis=axis)
        # Voxels under a fully kept neighbourhood of the previous layer are
        # hidden in every view (their pixels are all marked): skip them.
        active = sub if prev is None else sub & ~_all_within(prev, reach)
        n_hidden_skipped = int(np.count_nonzero(sub)) - int(np.count_nonzero(active))
        counts["hidden"] += n_hidden_skipped
        if active.any():
            ab, na, nb_, corner, ijk, needed = _layer_geometry(active, layer, axis, ax_a, ax_b, origin, h)
            proj = np.empty((V, 2, na + 1, nb_ + 1, 2))
            ok = np.empty((V, 2, na + 1, nb_ + 1), bool)
            # Voxels seen through to the background in some view go first.
            seen_through = np.zeros(len(ab), bool)
            if use_bg:
                v_bg = np.empty((V, len(ab)), np.int32)
                v_cnt = np.empty((V, len(ab)), np.int32)
                _over_views(_nb_layer_background, V, needed, ab, proj, ok, corner, ea, eb, en, dims, centres, cams, bg_arr, v_bg, v_cnt)
                seen_through = _seen_through(v_bg, v_cnt)
            else:
                _over_views(_nb_project_layer, V, needed, corner, ea, eb, en, cams, proj, ok)
            # Then the colour test, first with every other candidate of the
            # layer opaque (exact visibility within the layer), then again
            # with the voxels kept so far, until the decisions settle.
            keep = ~seen_through
            test = np.ones(len(ab), bool)  # voxels (re)tested in this pass
            render = keep  # kept voxels drawn into the layer's item buffer
            full = None
            for _ in range(1 + _REFINE):
                st = _Stats(V, len(ab), C)
                _over_views(
                    _nb_layer_pass, V, ab, render, test, proj, ok, corner, ea, eb, en, dims, centres,
                    cams, stack, marks, zbuf, obuf, box, bg_arr, use_bg, *st.arrays(),
                )
                st.pool()
                full = st if full is None else full.merge(st, test)
                bad, seen, tested = full.decide(threshold, measure, min_pix, min_frac)
                bad = _support_2d(ab, na, nb_, bad, support)
                carve = bad | seen_through
                changed = carve == keep
                if not changed.any():
                    break
                keep = ~carve
                # Only voxels whose footprints can overlap a changed one's need a new test.
                test = _within(ab, na, nb_, changed, None if reach is None else reach + 1)
                render = keep & _within(ab, na, nb_, changed, None if reach is None else 2 * reach + 2)
            st = full
            if keep.any():
                _over_views(_nb_layer_mark, V, ab, keep, proj, ok, corner, ea, eb, en, dims, centres, cams, marks)
            if _DEBUG is not None:
                _DEBUG.append((ijk, st))
            ci = ijk[carve]
            occ[ci[:, 0], ci[:, 1], ci[:, 2]] = False
            good = keep & seen
            ki = ijk[good]
            colored[ki[:, 0], ki[:, 1], ki[:, 2]] = True
            colors[ki[:, 0], ki[:, 1], ki[:, 2]] = _rgb(st.mean()[good], C)
            counts["carved_bg"] += int(np.count_nonzero(seen_through))
            counts["hidden"] += int(np.count_nonzero(keep & ~seen))
            counts["untested"] += int(np.count_nonzero(good & ~tested))
        prev = np.take(occ, layer, axis=axis)
        progress(step + 1, n_layers)
    return occ, colors, colored, counts, sweep, 1


def _owned(stack, cams, bg, ijk, grid):
    """Statistics of the pixels each voxel of ``ijk`` owns in the item buffers."""
    V, C = stack.shape[0], stack.shape[3]
    origin = np.asarray(grid.origin, dtype=np.float64)
    zbuf = np.empty(stack.shape[:3], np.float32)
    ids = np.empty(stack.shape[:3], np.int32)
    _over_views(_nb_item_buffers, V, ijk, origin, grid.voxel_size, cams, zbuf, ids)
    del zbuf
    bg_arr, use_bg = _bg_arg(bg)
    st = _Stats(V, len(ijk), C)
    _over_views(_nb_owned_stats, V, ijk, origin, grid.voxel_size, cams, stack, ids, bg_arr, use_bg, *st.arrays())
    return st.pool()


def _space_carving(stack, cams, cameras, bg, candidates, grid, threshold, measure, min_pix, min_frac, support, progress):
    """Generalized voxel colouring: carve surface voxels with exact visibility until nothing changes."""
    C = stack.shape[3]
    occ = candidates.copy()
    colors = np.zeros(grid.shape + (3,), np.uint8)
    colored = np.zeros(grid.shape, bool)
    counts = dict(carved_bg=0, hidden=0, untested=0)
    iterations = 0
    while True:
        iterations += 1
        ijk = np.argwhere(_surface(occ)).astype(np.int64)
        if len(ijk) == 0:
            break
        st = _owned(stack, cams, bg, ijk, grid)
        bad, seen, tested = st.decide(threshold, measure, min_pix, min_frac)
        carve = _support_3d(ijk, grid.shape, bad, support) | st.bgv
        if _DEBUG is not None:
            _DEBUG.append((ijk, st))
        if not carve.any():
            good = seen
            ki = ijk[good]
            colored[ki[:, 0], ki[:, 1], ki[:, 2]] = True
            colors[ki[:, 0], ki[:, 1], ki[:, 2]] = _rgb(st.mean()[good], C)
            counts["untested"] = int(np.count_nonzero(good & ~tested))
            progress(iterations, iterations)
            break
        ci = ijk[carve]
        occ[ci[:, 0], ci[:, 1], ci[:, 2]] = False
        counts["carved_bg"] += int(np.count_nonzero(st.bgv))
        progress(iterations, iterations + 1)
    counts["hidden"] = int(np.count_nonzero(occ & ~colored))
    return occ, colors, colored, counts, None, iterations


def _surface(occ):
    """Occupied voxels with an empty (or outside-the-grid) 6-neighbour."""
    p = np.pad(occ, 1, constant_values=False)
    interior = p[1:-1, 1:-1, 1:-1].copy()
    for a in range(3):
        for s in (0, 2):
            sl = [slice(1, -1)] * 3
            sl[a] = slice(s, s + occ.shape[a])
            interior &= p[tuple(sl)]
    return occ & ~interior

