"""Voxel colouring and space carving: the concavities no silhouette shows.

A visual hull cannot remove a concavity that lies inside every silhouette
(an aneurysm's neck, the crotch between the iliac arteries, a dent in a real
specimen).  Colour can: a hull voxel that fills a concavity projects, in the
views that see it, onto *different* surface points behind it, so the pixels
it projects to disagree; a voxel on the true surface projects onto the same
surface point in every view that sees it, so its pixels agree.  This module
removes the voxels whose pixels disagree.

Two methods
-----------
``method="voxel_coloring"`` -- Seitz & Dyer (1999), single pass, layered.
    Voxels are visited in layers (voxel slabs) of increasing distance from
    the cameras, so that every voxel that can occlude another is decided
    first.  Each view keeps a *mark* per pixel; a voxel's *visible* pixels
    are the unmarked pixels of its footprint.  A voxel is tested on its
    visible pixels of all views; a voxel that is kept marks its footprint
    pixels, so the voxels behind it no longer see them.
``method="space_carving"`` -- generalized voxel colouring (Culbertson,
    Malzbender & Slabaugh 2000), a multi-pass space carving (Kutulakos &
    Seitz 2000) with exact visibility, for any camera layout.  Repeat until
    nothing changes: render, for every view, an item buffer of the current
    surface voxels (each footprint pixel belongs to the surface voxel whose
    centre is nearest the camera); test every surface voxel on the pixels it
    owns; carve the inconsistent ones.  Slower (one pass per voxel of
    carving depth).

The ordinal visibility constraint
---------------------------------
A point ``P`` can occlude a point ``Q`` in a camera with centre ``C`` only if
``P = C + s (Q - C)`` with ``0 < s < 1``.  For a sweep direction ``d`` (unit
vector) this gives ``d.P = (1 - s) d.C + s d.Q``, so ``d.P > d.Q`` whenever
``d.C > d.Q``.  Hence: *if every camera centre lies strictly beyond the
volume along* ``d`` (``d.C > max d.X`` over the candidate voxels' boxes, for
every camera), sweeping planes ``d.X = const`` from the cameras' side visits
every occluder before what it occludes.  Layers are voxel slabs, so ``d`` is
one of the six grid axes; for a turntable whose cameras all look down from
above the specimen it is ``+z``: every camera centre above the top face of
the topmost candidate voxel (not merely above the roi's top: the hull's top
suffices), planes swept from the top down.  When no axis qualifies (a
camera below the top of the specimen, cameras on both sides)
:func:`color_voxels` raises :class:`VisibilityConstraintError`; use
``method="space_carving"`` there.

Visibility within a layer
-------------------------
Points of one slab cannot occlude each other, but voxels can: a ray crosses
a slab sideways, through the face of one voxel into its neighbour (seen at
27 degrees of elevation, a 1 mm slab is crossed over 2 mm).  Seitz & Dyer
ignore this; on a horizontal face seen obliquely it pollutes every voxel's
footprint with its neighbours' texture and, carving true surface voxels,
opens holes that the sweep then digs deeper.  Here each layer is decided
exactly: an item buffer of the layer's voxels (nearest voxel centre per
pixel, per view) takes the place of the marks inside the layer.  First all
candidates of the layer are opaque; the test is repeated (up to two more
times) with only the voxels kept so far, until the decisions settle.  Then
the kept voxels mark their footprints.

Voxels that cannot be seen are skipped: a pixel ray through a voxel reaches
the previous layer within ``0.5 + 1 / tan(elevation)`` voxels of it, so a
voxel below a fully kept neighbourhood of that size is hidden in every view.

Footprints
----------
The footprint of a voxel in a view is the set of pixels whose centres lie in
the projected outline of the voxel (its 8 corners projected with the full
camera model, distortion and skew included; the outline's 4 or 6 corners
follow from the camera's position relative to the box), clipped to the
image.  A voxel too small to contain a pixel centre gets the pixel nearest
to its projected centre.  A view in which a corner of the voxel lies on or
behind the camera plane does not see the voxel.

Consistency
-----------
Grey levels (0-255), ``sqrt`` of the mean per-channel variance (one channel
for grey images), of the visible pixels of all views:

* ``measure="between"`` (default): the variance of the per-view mean colours
  (each view weighted by its number of visible pixels).  The texture inside
  one footprint does not count, only the disagreement between views.
* ``measure="pooled"``: the variance of all visible pixels pooled (Seitz &
  Dyer's standard deviation).  It adds the texture inside the footprint, so
  textured true surfaces fail it more often.

A voxel is consistent when this standard deviation is at most
``threshold``.  A voxel's colour is the mean of its visible pixels.
``support`` asks an inconsistent voxel for inconsistent neighbours in its
layer before it is carved (concavities are regions; a lone failure on a
true surface is a texture edge or a crease).

``completeness`` (Seitz & Dyer's trade-off between a *complete*
reconstruction, without holes, and a *sound* one, without extra voxels):
with few visible pixels the standard deviation says little, and carving on
it punches holes.  A voxel with fewer visible pixels than ``completeness``
(an integer count, or a fraction in ``(0, 1)`` of its in-image, non-
background footprint pixels over all views) is not tested: it is kept,
marks its pixels and is coloured.  ``None`` tests every voxel with at least
one visible pixel.

A solid, not a shell
--------------------
Voxel colouring proper returns the *colour invariants*: the consistent
voxels that some view sees, i.e. a surface shell.  A voxel that no view sees
(every pixel of its footprint already marked) is not determined by the
images at all.  organlab measures volumes, so the result must be a solid:
only voxels that are *seen and inconsistent* (or seen through, below) are
carved; voxels that are never seen stay occupied as interior ("hidden" in
the statistics).  The output occupancy is the candidates minus the carved
voxels.

Silhouettes
-----------
With ``start="hull"`` (the default, which the thesis found necessary) the
candidates are the visual hull's voxels; voxels outside it are empty and
claim no pixel.  With ``start="roi"`` every voxel of the grid is a candidate
(Seitz & Dyer's original setting; a uniform background makes empty space
consistent, so expect floating voxels unless ``masks`` are given).  When
``masks`` are given, pixels outside the silhouettes show the background:
they are never used for colours or consistency, and a voxel whose footprint
in some view is mostly (more than half) background pixels is carved, since
the rays through it reach the background.

Defaults were tuned on the synthetic grooved specimen
(:mod:`organlab.synthetic`, 36 views of 640 x 480 px, 1 mm voxels): about
63 % of the hull's excess volume carved for 0.4 % of the true volume lost
(``docs/benchmarks.md``).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numba as nb
import numpy as np

from ._nbcam import pack_cameras, to_camera, to_pixel
from .camera import Camera
from .errors import OrganlabError
from .grid import VoxelGrid

__all__ = [
    "VisibilityConstraintError",
    "ColoringResult",
    "color_voxels",
    "voxel_colors",
    "check_ordinal_visibility",
    "DEFAULT_THRESHOLD",
    "DEFAULT_SUPPORT",
]

#: Default photo-consistency threshold, grey levels (standard deviation).
DEFAULT_THRESHOLD = 18.0

#: Default spatial support of a carve (inconsistent voxels in a 3 x 3 neighbourhood).
DEFAULT_SUPPORT = 3

_AXES = "xyz"


class VisibilityConstraintError(OrganlabError, ValueError):
    """The cameras do not allow a layered (single sweep) voxel colouring."""


@dataclass(frozen=True)
class ColoringResult:
    """What :func:`color_voxels` returns.

    Attributes
    ----------
    occupancy : (nx, ny, nz) bool
        The solid after colouring: candidates minus carved voxels.
    colors : (nx, ny, nz, 3) uint8
        RGB colour of every coloured voxel (mean of its visible pixels);
        zeros elsewhere.
    colored : (nx, ny, nz) bool
        The voxels that were seen and kept, i.e. those with a colour.
    n_candidates : int
        Voxels tested (hull or whole grid).
    n_carved : int
        Voxels removed.
    n_carved_background : int
        Of those, voxels carved because a view saw mostly background through them.
    n_visible : int
        Kept voxels that some view sees (== ``colored.sum()``).
    n_hidden : int
        Kept voxels that no view sees (interior).
    n_untested : int
        Kept voxels seen by fewer pixels than ``completeness`` asks.
    seconds : float
        Wall time.
    method : str
    sweep : str or None
        Layered sweep direction, e.g. ``"-z"`` (planes from the top down);
        None for space carving.
    iterations : int
        Passes (1 for voxel colouring).
    threshold : float
    """

    occupancy: np.ndarray
    colors: np.ndarray
    colored: np.ndarray
    n_candidates: int
    n_carved: int
    n_carved_background: int
    n_visible: int
    n_hidden: int
    n_untested: int
    seconds: float
    method: str
    sweep: str | None
    iterations: int
    threshold: float

    def stats(self):
        """The scalar fields as a JSON-ready dict."""
        return {
            "method": self.method,
            "threshold": self.threshold,
            "sweep": self.sweep,
            "iterations": self.iterations,
            "n_candidates": self.n_candidates,
            "n_carved": self.n_carved,
            "n_carved_background": self.n_carved_background,
            "n_visible": self.n_visible,
            "n_hidden": self.n_hidden,
            "n_untested": self.n_untested,
            "seconds": self.seconds,
        }


# =====================================================================
# numba kernels
# =====================================================================
# A camera is packed by organlab._nbcam.pack_camera: R (9, row major), t (3),
# fx, K[0, 1], cx, fy, cy, k1, k2, p1, p2, k3, |t|_1.


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


def _n_threads():
    try:
        return max(1, int(nb.get_num_threads()))
    except Exception:  # pragma: no cover
        return 1


def _over_views(kernel, V, *args):
    """Run ``kernel(v0, v1, *args)`` on slices of the V views, one per thread.

    The kernels release the GIL; threads that wait do so passively, which
    keeps a shared, oversubscribed machine responsive (numba's OpenMP
    workers spin while they wait and slow every short parallel region).
    """
    n = min(_n_threads(), V)
    if n <= 1:
        kernel(0, V, *args)
        return
    from concurrent.futures import ThreadPoolExecutor

    global _POOL
    if _POOL is None or _POOL._max_workers < n:
        _POOL = ThreadPoolExecutor(max_workers=n, thread_name_prefix="organlab-coloring")
    edges = np.linspace(0, V, n + 1).astype(int)
    futures = [_POOL.submit(kernel, int(a), int(b), *args) for a, b in zip(edges[:-1], edges[1:]) if b > a]
    for f in futures:
        f.result()


_POOL = None


# =====================================================================
# validation and packing
# =====================================================================
def _check_inputs(images, cameras, grid, masks):
    if not isinstance(grid, VoxelGrid):
        raise TypeError(f"grid must be an organlab.grid.VoxelGrid, got {type(grid).__name__}")
    cameras = [cameras] if isinstance(cameras, Camera) else list(cameras)
    if isinstance(images, np.ndarray) and images.ndim in (2, 3) and images.dtype == np.uint8 and len(cameras) == 1:
        if images.ndim == 2 or images.shape[-1] == 3:
            images = [images]
    images = list(images)
    if len(images) != len(cameras):
        raise ValueError(f"got {len(images)} images but {len(cameras)} cameras: give one camera per image")
    if not images:
        raise ValueError("no views: give at least one image and its camera")
    for i, c in enumerate(cameras):
        if not isinstance(c, Camera):
            raise TypeError(f"camera {i} must be an organlab.camera.Camera, got {type(c).__name__}")
    shapes = set()
    for i, (im, cam) in enumerate(zip(images, cameras)):
        a = np.asarray(im)
        if a.dtype != np.uint8 or not (a.ndim == 2 or (a.ndim == 3 and a.shape[2] == 3)):
            raise ValueError(f"image {i} must be an (H, W) or (H, W, 3) uint8 array, got {a.dtype} {a.shape}")
        if (a.shape[1], a.shape[0]) != tuple(cam.image_size):
            raise ValueError(
                f"image {i} is {a.shape[1]}x{a.shape[0]} px but its camera's image_size is "
                f"{cam.image_size[0]}x{cam.image_size[1]}"
            )
        shapes.add(a.shape)
    if len(shapes) != 1:
        raise ValueError(f"all images must have the same shape, got {sorted(shapes)}")
    shape = shapes.pop()
    stack = np.empty((len(images),) + shape[:2] + (shape[2] if len(shape) == 3 else 1,), np.uint8)
    for i, im in enumerate(images):
        stack[i] = np.asarray(im).reshape(stack.shape[1:])
    bg = None
    if masks is not None:
        masks = list(masks)
        if len(masks) != len(images):
            raise ValueError(f"got {len(masks)} masks but {len(images)} images: give one mask per image")
        bg = np.empty(stack.shape[:3], np.uint8)
        for i, m in enumerate(masks):
            m = np.asarray(m)
            if m.shape != shape[:2]:
                raise ValueError(f"mask {i} has shape {m.shape} but image {i} has (H, W) = {shape[:2]}")
            bg[i] = m == 0
    return stack, cameras, pack_cameras(cameras), bg


def _check_occupancy(occupancy, grid):
    occ = np.asarray(occupancy)
    if occ.shape != grid.shape:
        raise ValueError(f"occupancy has shape {occ.shape} but the grid's shape is {grid.shape}")
    if occ.dtype != bool:
        raise ValueError(f"occupancy must be a bool array, got {occ.dtype}")
    return occ


def _candidate_bounds(candidates, grid):
    idx = [np.flatnonzero(candidates.any(axis=tuple(a for a in range(3) if a != k))) for k in range(3)]
    lo_i = np.array([i[0] for i in idx])
    hi_i = np.array([i[-1] for i in idx])
    o = np.asarray(grid.origin)
    h = grid.voxel_size
    return o + (lo_i - 0.5) * h, o + (hi_i + 0.5) * h


def check_ordinal_visibility(cameras, bounds_min, bounds_max):
    """Find a layered sweep that meets the ordinal visibility constraint.

    The constraint holds for sweep direction ``d`` if every camera centre lies
    strictly beyond the box along ``d``: ``d . C > max(d . X)`` over the box,
    for every camera.  Then a point can only be occluded by points with a
    larger ``d . X``, and planes ``d . X = const`` swept from the cameras'
    side (decreasing ``d . X``) visit every occluder first.  The six axis
    directions are tried, ``+z`` (cameras above, sweep top down) first.

    Parameters
    ----------
    cameras : sequence of Camera
    bounds_min, bounds_max : (3,) float, mm, world frame
        The box holding every voxel that may be occupied.

    Returns
    -------
    axis : int
        0, 1 or 2 (x, y, z): the layers are slabs normal to this axis.
    descending : bool
        True: layers are visited from the largest coordinate down.

    Raises
    ------
    VisibilityConstraintError
        When no axis direction has every camera beyond the box.
    """
    cameras = [cameras] if isinstance(cameras, Camera) else list(cameras)
    centres = np.array([c.center for c in cameras], dtype=np.float64).reshape(-1, 3)
    lo = np.asarray(bounds_min, dtype=np.float64)
    hi = np.asarray(bounds_max, dtype=np.float64)
    for axis, descending in ((2, True), (2, False), (0, True), (0, False), (1, True), (1, False)):
        if descending and np.all(centres[:, axis] > hi[axis]):
            return axis, True
        if not descending and np.all(centres[:, axis] < lo[axis]):
            return axis, False
    worst = int(np.argmin(centres[:, 2]))
    raise VisibilityConstraintError(
        f"the cameras break the ordinal visibility constraint of layered voxel colouring: camera {worst}'s "
        f"centre is at z = {centres[worst, 2]:.1f} mm, not above the top of the volume (z = {hi[2]:.1f} mm), "
        "and no other axis has every camera on one side of the volume; "
        "use method='space_carving' (exact visibility, any camera layout)"
    )


def _completeness_rule(completeness):
    if completeness is None:
        return 1, 0.0
    if isinstance(completeness, bool):
        raise ValueError(f"completeness must be None, an integer >= 1 or a fraction in (0, 1), got {completeness!r}")
    if isinstance(completeness, (int, np.integer)):
        if completeness < 1:
            raise ValueError(f"completeness must be an integer >= 1 (visible pixels), got {completeness}")
        return int(completeness), 0.0
    c = float(completeness)
    if not 0.0 < c < 1.0:
        raise ValueError(f"completeness as a fraction must lie in (0, 1), got {completeness!r}")
    return 1, c


_BG_FRACTION = 0.5
_REFINE = 2
_BG_VIEWS = 1
_DEBUG = None  # set to a list to collect (ijk, _Stats) per layer or pass (tests, tuning)


class _Stats:
    """Pixel statistics of M voxels in V views, filled by the kernels, then pooled."""

    def __init__(self, V, M, C):
        self.v_vis = np.empty((V, M), np.int32)
        self.v_tot = np.empty((V, M), np.int32)
        self.v_sums = np.empty((V, M, C))
        self.v_sq = np.empty((V, M, C))
        self.v_bg = np.empty((V, M), np.int32)
        self.v_cnt = np.empty((V, M), np.int32)

    def arrays(self):
        return self.v_vis, self.v_tot, self.v_sums, self.v_sq, self.v_bg, self.v_cnt

    def pool(self):
        self.n_vis = self.v_vis.sum(axis=0, dtype=np.int64)
        self.n_tot = self.v_tot.sum(axis=0, dtype=np.int64)
        self.sums = self.v_sums.sum(axis=0)
        self.sq = self.v_sq.sum(axis=0)
        with np.errstate(invalid="ignore", divide="ignore"):
            per_view = np.where(self.v_vis[:, :, None] > 0, self.v_sums**2 / self.v_vis[:, :, None], 0.0)
        self.bw = per_view.sum(axis=0)
        self.bgv = _seen_through(self.v_bg, self.v_cnt)
        return self

    def merge(self, other, rows):
        """Take the pooled statistics of ``rows`` from ``other``; returns self."""
        for name in ("n_vis", "n_tot", "sums", "sq", "bw", "bgv"):
            getattr(self, name)[rows] = getattr(other, name)[rows]
        return self

    def mean(self):
        return self.sums / np.maximum(self.n_vis, 1)[:, None]

    def std(self, measure="pooled"):
        """Standard deviation, grey levels: ``sqrt`` of the mean per-channel variance.

        ``pooled``: of all visible pixels (Seitz & Dyer); ``between``: of the
        per-view mean colours, each weighted by its number of pixels (the
        texture inside one footprint does not count).
        """
        n = np.maximum(self.n_vis, 1)[:, None]
        mean = self.sums / n
        second = self.sq if measure == "pooled" else self.bw
        var = np.maximum(second / n - mean * mean, 0.0)
        return np.sqrt(var.mean(axis=1))

    def decide(self, threshold, measure, min_pix, min_frac):
        """Per voxel: inconsistent, seen, tested (bool arrays)."""
        seen = self.n_vis > 0
        tested = seen & (self.n_vis >= min_pix) & (self.n_vis >= min_frac * self.n_tot)
        return tested & (self.std(measure) > threshold), seen, tested


def _within(ab, na, nb_, flags, radius):
    """Voxels of a layer within chessboard distance ``radius`` of a flagged one (all when radius is None)."""
    if radius is None:
        return np.ones(len(ab), bool)
    from scipy import ndimage

    g = np.zeros((na, nb_), bool)
    g[ab[flags, 0], ab[flags, 1]] = True
    g = ndimage.binary_dilation(g, structure=np.ones((3, 3), bool), iterations=int(radius))
    return g[ab[:, 0], ab[:, 1]]


def _support_2d(ab, na, nb_, flags, support):
    """Keep the flags of voxels with at least ``support`` flagged voxels in their 3 x 3 in-layer neighbourhood."""
    if support <= 1 or not flags.any():
        return flags
    g = np.zeros((na + 2, nb_ + 2), np.int32)
    g[ab[:, 0] + 1, ab[:, 1] + 1] = flags
    count = np.zeros_like(g)
    for da in (-1, 0, 1):
        for db in (-1, 0, 1):
            count[1:-1, 1:-1] += g[1 + da : na + 1 + da, 1 + db : nb_ + 1 + db]
    return flags & (count[ab[:, 0] + 1, ab[:, 1] + 1] >= support)


def _support_3d(ijk, shape, flags, support):
    """Keep the flags of voxels with at least ``support`` flagged voxels in their 3 x 3 x 3 neighbourhood."""
    if support <= 1 or not flags.any():
        return flags
    from scipy import ndimage

    g = np.zeros(shape, np.int32)
    g[ijk[:, 0], ijk[:, 1], ijk[:, 2]] = flags
    count = ndimage.correlate(g, np.ones((3, 3, 3), np.int32), mode="constant")
    return flags & (count[ijk[:, 0], ijk[:, 1], ijk[:, 2]] >= support)


def _seen_through(v_bg, v_cnt):
    """Voxels whose footprint is mostly background pixels in some view: (V, M) counts -> (M,) bool."""
    return np.count_nonzero(v_bg > _BG_FRACTION * v_cnt, axis=0) >= _BG_VIEWS


def _rgb(mean, C):
    col = np.clip(np.rint(mean), 0, 255).astype(np.uint8)
    return np.repeat(col, 3, axis=1) if C == 1 else col


# =====================================================================
# public
# =====================================================================
def color_voxels(
    images,
    cameras,
    occupancy,
    grid,
    *,
    threshold=DEFAULT_THRESHOLD,
    method="voxel_coloring",
    start="hull",
    completeness=None,
    masks=None,
    measure="between",
    support=DEFAULT_SUPPORT,
    progress=None,
):
    """Carve the voxels whose colours disagree between the views.

    See the module docstring for the algorithms, the visibility constraint
    and why voxels no view sees are kept.

    Parameters
    ----------
    images : sequence of (H, W, 3) or (H, W) uint8
        The views, RGB (or grey), one per camera.
    cameras : sequence of Camera
        The calibrated camera of each view, ``image_size == (W, H)``.
    occupancy : (nx, ny, nz) bool or None
        The visual hull on ``grid`` (e.g. from :func:`organlab.carving.carve`).
        Only needed with ``start="hull"``.
    grid : VoxelGrid
    threshold : float
        Photo-consistency threshold: largest standard deviation (grey levels,
        ``sqrt`` of the mean per-channel variance) of a kept voxel's visible
        pixels.
    method : {'voxel_coloring', 'space_carving'}
        Seitz & Dyer's single layered pass (needs the ordinal visibility
        constraint), or multi-pass carving with exact visibility (any cameras).
    start : {'hull', 'roi'}
        Candidates: the hull's voxels, or every voxel of the grid.
    completeness : None, int >= 1 or float in (0, 1)
        Voxels with fewer visible pixels (a count, or a fraction of their
        in-image, non-background footprint pixels over all views) are kept
        untested.
    masks : sequence of (H, W) bool, optional
        Silhouettes (True = specimen).  Background pixels are never used for
        colours; a voxel seen mostly through background in a view is carved.
    measure : {'pooled', 'between'}
        ``'pooled'``: the standard deviation of all visible pixels pooled
        over the views (Seitz & Dyer); ``'between'``: of the per-view mean
        colours (weighted by pixel counts), blind to the texture inside one
        footprint.
    support : int
        Spatial support of a carve: an inconsistent voxel is carved only if
        at least ``support`` inconsistent voxels (itself included) lie in its
        3 x 3 neighbourhood within its layer (3 x 3 x 3 for space carving).
        ``1`` is the plain per-voxel test.  Concavities are regions; a lone
        inconsistent voxel on a true surface (a texture edge, a crease) is
        kept, which stops it from opening a hole that the sweep would then
        dig deeper.
    progress : callable(done, total), optional
        Called after every layer (or pass).

    Returns
    -------
    ColoringResult

    Raises
    ------
    VisibilityConstraintError
        ``method="voxel_coloring"`` with cameras that allow no layered sweep.
    ValueError
        Mismatched numbers of images, cameras and masks, an image that is not
        ``(H, W)`` / ``(H, W, 3)`` uint8 or not its camera's size, an
        occupancy that is not bool of ``grid.shape``, or an invalid option.
    TypeError
        A camera that is not a :class:`~organlab.camera.Camera` or a grid that
        is not a :class:`~organlab.grid.VoxelGrid`.
    """
    t0 = time.perf_counter()
    stack, cameras, cams, bg = _check_inputs(images, cameras, grid, masks)
    if method not in ("voxel_coloring", "space_carving"):
        raise ValueError(f"method must be 'voxel_coloring' or 'space_carving', got {method!r}")
    if start == "hull":
        if occupancy is None:
            raise ValueError("start='hull' needs the visual hull as occupancy (or use start='roi')")
        candidates = _check_occupancy(occupancy, grid)
    elif start == "roi":
        candidates = np.ones(grid.shape, dtype=bool)
    else:
        raise ValueError(f"start must be 'hull' or 'roi', got {start!r}")
    if isinstance(threshold, bool) or not isinstance(threshold, (int, float, np.integer, np.floating)) or not threshold >= 0:
        raise ValueError(f"threshold must be a number >= 0 (grey levels), got {threshold!r}")
    threshold = float(threshold)
    min_pix, min_frac = _completeness_rule(completeness)
    if measure not in ("pooled", "between"):
        raise ValueError(f"measure must be 'pooled' or 'between', got {measure!r}")
    if isinstance(support, bool) or not isinstance(support, (int, np.integer)) or not 1 <= support <= 27:
        raise ValueError(f"support must be an integer in 1..27 (voxels), got {support!r}")
    progress = progress or (lambda done, total: None)

    run = _voxel_coloring if method == "voxel_coloring" else _space_carving
    occ, colors, colored, counts, sweep, iterations = run(
        stack, cams, cameras, bg, candidates, grid, threshold, measure, min_pix, min_frac, support, progress
    )
    n_cand = int(np.count_nonzero(candidates))
    return ColoringResult(
        occupancy=occ,
        colors=colors,
        colored=colored,
        n_candidates=n_cand,
        n_carved=n_cand - int(np.count_nonzero(occ)),
        n_carved_background=counts["carved_bg"],
        n_visible=int(np.count_nonzero(colored)),
        n_hidden=counts["hidden"],
        n_untested=counts["untested"],
        seconds=time.perf_counter() - t0,
        method=method,
        sweep=sweep,
        iterations=iterations,
        threshold=threshold,
    )


def _bg_arg(bg):
    return (bg, True) if bg is not None else (np.zeros((1, 1, 1), np.uint8), False)


def _occlusion_reach(cameras, lo, hi, axis, descending):
    """How far (voxels, in-layer chessboard distance) a ray crossing one layer travels sideways.

    A pixel ray through a voxel of layer k reaches layer k - 1 (toward the
    cameras) within ``0.5 + 1 / tan(elevation)`` voxels of it, the elevation
    being the ray's angle to the layer planes; the smallest elevation of a
    ray from any camera to the candidates' box bounds it.
    """
    centres = np.array([c.center for c in cameras], dtype=np.float64)
    other = [d for d in range(3) if d != axis]
    rise = centres[:, axis] - hi[axis] if descending else lo[axis] - centres[:, axis]
    corners = np.array([[x, y] for x in (lo[other[0]], hi[other[0]]) for y in (lo[other[1]], hi[other[1]])])
    run = np.max(np.linalg.norm(centres[:, None, other] - corners[None], axis=2), axis=1)
    tan_min = float(np.min(rise / np.maximum(run, 1e-9)))
    if not tan_min > 1e-6:
        return None
    return int(np.ceil(0.5 + 1.0 / tan_min))


def _all_within(occ2d, reach):
    """True where every cell within chessboard distance ``reach`` is occupied (False beyond the edges)."""
    if reach is None:
        return np.zeros(occ2d.shape, bool)
    from scipy import ndimage

    return ndimage.minimum_filter(occ2d.astype(np.uint8), size=2 * reach + 1, mode="constant", cval=0).astype(bool)


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
            ia, ib = np.nonzero(active)
            a0, b0 = ia.min(), ib.min()
            na, nb_ = int(ia.max() - a0 + 1), int(ib.max() - b0 + 1)
            ab = np.stack([ia - a0, ib - b0], axis=1).astype(np.int64)
            corner = np.empty(3)
            corner[ax_a] = origin[ax_a] + (a0 - 0.5) * h
            corner[ax_b] = origin[ax_b] + (b0 - 0.5) * h
            corner[axis] = origin[axis] + (layer - 0.5) * h
            ijk = np.empty((len(ab), 3), np.int64)
            ijk[:, ax_a], ijk[:, ax_b], ijk[:, axis] = ia, ib, layer
            needed = np.zeros((na + 1, nb_ + 1), bool)
            for di in (0, 1):
                for dj in (0, 1):
                    needed[ab[:, 0] + di, ab[:, 1] + dj] = True
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


def voxel_colors(images, cameras, occupancy, grid, *, masks=None):
    """Colour the surface voxels of an occupancy, without carving.

    Every view renders an item buffer of the surface voxels (each footprint
    pixel goes to the surface voxel nearest the camera); a voxel's colour is
    the mean of the pixels it owns, over all views.  For mesh vertex colours.

    Parameters
    ----------
    images : sequence of (H, W, 3) or (H, W) uint8
    cameras : sequence of Camera
    occupancy : (nx, ny, nz) bool
    grid : VoxelGrid
    masks : sequence of (H, W) bool, optional
        Background pixels (False) are not used.

    Returns
    -------
    colors : (nx, ny, nz, 3) uint8
        RGB; zeros where a voxel is empty, interior or seen by no view.
    """
    stack, cameras, cams, bg = _check_inputs(images, cameras, grid, masks)
    occ = _check_occupancy(occupancy, grid)
    colors = np.zeros(grid.shape + (3,), np.uint8)
    ijk = np.argwhere(_surface(occ)).astype(np.int64)
    if len(ijk) == 0:
        return colors
    st = _owned(stack, cams, bg, ijk, grid)
    seen = st.n_vis > 0
    ki = ijk[seen]
    colors[ki[:, 0], ki[:, 1], ki[:, 2]] = _rgb(st.mean()[seen], stack.shape[3])
    return colors
