"""Surfaces from points: the Voronoi-based crust, and screened Poisson for comparison.

The crust (Amenta, Bern and Kamvysselis 1998) on ``scipy.spatial``: the
Voronoi vertices of the samples are the circumcentres of their Delaunay
tetrahedra; each sample's *poles* are the farthest Voronoi vertex of its cell
(``p+``) and the farthest on the other side (``p-``), which approximate the
medial axis.  In the Delaunay triangulation of samples and poles together,
the triangles whose three vertices are samples form the crust: a medial-axis
ball separates the two sides of the surface, so only triangles near the
surface survive.  Eight far box corners are added so that every sample's
Voronoi cell is bounded.

The crust is not guaranteed to be a manifold: sliver tetrahedra of nearly
co-spherical samples (marching-cubes vertices lie on a grid) leave extra and
missing triangles.  :func:`crust` reports its defects; :func:`finish_surface`
can repair it.  Screened Poisson (pymeshlab, Kazhdan and Hoppe 2013) fits an
implicit function to oriented points and is closed by construction.
"""

from __future__ import annotations

import numpy as np

from ._mesh import Mesh


def _circumcentres(p):
    """Circumcentres of tetrahedra ``p`` (T, 4, 3); NaN for flat ones."""
    a = p[:, 1:] - p[:, :1]
    rhs = 0.5 * np.sum(a * a, axis=2)
    det = np.linalg.det(a)
    ok = np.abs(det) > 1e-12 * np.max(np.abs(a), axis=(1, 2)) ** 3
    x = np.full((len(p), 3), np.nan)
    x[ok] = np.linalg.solve(a[ok], rhs[ok][..., None])[..., 0]
    return p[:, 0] + x


def poles(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The two poles of every sample's Voronoi cell.

    Parameters
    ----------
    points : (N, 3) float64, mm

    Returns
    -------
    p_plus, p_minus : (N, 3) float64, mm
        Farthest Voronoi vertex, and farthest on the opposite side (NaN when none).
    """
    from scipy.spatial import Delaunay

    pts = np.asarray(points, dtype=np.float64)
    n = len(pts)
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    c, ext = 0.5 * (lo + hi), (hi - lo).max()
    box = c + 3.0 * ext * (np.indices((2, 2, 2)).reshape(3, -1).T - 0.5)
    tri = Delaunay(np.concatenate([pts, box]))
    cc = _circumcentres(tri.points[tri.simplices])
    vert = tri.simplices.ravel()
    tet = np.repeat(np.arange(len(tri.simplices)), 4)
    keep = (vert < n) & np.isfinite(cc[tet, 0])
    vert, tet = vert[keep], tet[keep]
    d = np.linalg.norm(cc[tet] - pts[vert], axis=1)
    far = np.full(n, -1.0)
    np.maximum.at(far, vert, d)
    is_far = d == far[vert]
    first = np.full(n, -1)
    first[vert[is_far]] = tet[is_far]
    p_plus = cc[first]
    side = np.einsum("ij,ij->i", cc[tet] - pts[vert], p_plus[vert] - pts[vert]) < 0
    d2 = np.where(side, d, -1.0)
    far2 = np.full(n, -1.0)
    np.maximum.at(far2, vert, d2)
    is_far2 = side & (d2 == far2[vert])
    second = np.full(n, -1)
    second[vert[is_far2]] = tet[is_far2]
    p_minus = np.where((second >= 0)[:, None], cc[np.maximum(second, 0)], np.nan)
    return p_plus, p_minus


def crust(points: np.ndarray, *, max_angle_deg: float | None = None) -> Mesh:
    """Crust of surface samples (Amenta, Bern and Kamvysselis).

    Parameters
    ----------
    points : (N, 3) float64, mm, world frame
        Samples of a closed surface (e.g. marching-cubes vertices).
    max_angle_deg : float, optional
        The crust's normal filter: drop triangles whose normal makes more
        than this angle with the pole vector ``p+ - p`` of any of its vertices
        (the pole vector is nearly normal to the surface).

    Returns
    -------
    Mesh
        The crust's triangles over ``points`` (not oriented; may have
        boundary and non-manifold edges, see :func:`mesh_quality`).
    """
    from scipy.spatial import Delaunay

    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) < 4:
        raise ValueError(f"points must be (N >= 4, 3), got {pts.shape}")
    p_plus, p_minus = poles(pts)
    extra = np.concatenate([p_plus, p_minus[np.isfinite(p_minus[:, 0])]])
    tri = Delaunay(np.concatenate([pts, extra]))
    s = tri.simplices
    faces = np.concatenate([s[:, [0, 1, 2]], s[:, [0, 1, 3]], s[:, [0, 2, 3]], s[:, [1, 2, 3]]])
    faces = faces[(faces < len(pts)).all(axis=1)]
    faces = np.unique(np.sort(faces, axis=1), axis=0)
    if max_angle_deg is not None:
        t = pts[faces]
        n = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
        pv = p_plus[faces] - t
        pv /= np.linalg.norm(pv, axis=2, keepdims=True)
        cos = np.abs(np.einsum("ij,ikj->ik", n, pv)).min(axis=1)
        faces = faces[cos >= np.cos(np.radians(max_angle_deg))]
    return Mesh(pts, faces.astype(np.int64))


def poisson_surface(points: np.ndarray, normals: np.ndarray, *, depth: int = 8) -> Mesh:
    """Screened Poisson surface of oriented points (pymeshlab).

    Parameters
    ----------
    points : (N, 3) float64, mm, world frame
    normals : (N, 3) float64
        Outward unit normals.
    depth : int
        Octree depth.

    Returns
    -------
    Mesh
    """
    import pymeshlab

    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=np.asarray(points, np.float64), v_normals_matrix=np.asarray(normals, np.float64)))
    ms.generate_surface_reconstruction_screened_poisson(depth=int(depth), preclean=True)
    m = ms.current_mesh()
    out = Mesh(np.asarray(m.vertex_matrix(), np.float64), np.asarray(m.face_matrix(), np.int64))
    return out if out.volume >= 0 else Mesh(out.vertices, out.faces[:, ::-1].copy())


def vertex_normals(mesh: Mesh) -> np.ndarray:
    """Area-weighted outward unit normals at the vertices, ``(V, 3)``."""
    v, f = mesh.vertices, mesh.faces
    fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    idx = np.asarray(f).T.ravel()  # the faces' normals summed at their corners' vertices
    n = np.stack([np.bincount(idx, weights=np.tile(fn[:, k], 3), minlength=len(v)) for k in range(3)], axis=1)
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)


def labelled_balls(points: np.ndarray, normals: np.ndarray) -> Mesh:
    """Closed surface from oriented samples by labelling Delaunay balls inside or outside.

    Each Delaunay tetrahedron of the samples has a Delaunay ball centred at
    a Voronoi vertex (the power crust's idea, without its power diagram): the
    ball is *inside* when its centre lies behind the samples' oriented
    normals on average over its four corners.  The surface is the boundary of
    the union of the inside tetrahedra: closed by construction (every edge
    has an even number of boundary faces), with non-manifold edges only where
    inside tetrahedra meet along an edge.

    Parameters
    ----------
    points : (N, 3) float64, mm, world frame
    normals : (N, 3) float64
        Outward unit normals.

    Returns
    -------
    Mesh
        Outward-oriented faces over ``points``.
    """
    from scipy.spatial import Delaunay

    pts = np.asarray(points, dtype=np.float64)
    nrm = np.asarray(normals, dtype=np.float64)
    if pts.shape != nrm.shape or pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points and normals must both be (N, 3), got {pts.shape} and {nrm.shape}")
    tri = Delaunay(pts)
    s = tri.simplices
    p = pts[s]
    cc = _circumcentres(p)
    cc = np.where(np.isfinite(cc), cc, p.mean(axis=1))  # flat tets: their centroid
    side = np.einsum("tkj,tkj->tk", cc[:, None] - p, nrm[s]).mean(axis=1)
    inside = side < 0
    # faces of inside tets whose neighbour across is outside (or missing: the hull)
    nb = tri.neighbors
    out_faces = []
    for k in range(4):
        other = [j for j in range(4) if j != k]
        border = inside & ((nb[:, k] < 0) | ~inside[np.maximum(nb[:, k], 0)])
        f = s[border][:, other]
        # orient along the samples' normals (the opposite vertex of a flat tet is no guide)
        a, b, c = pts[f[:, 0]], pts[f[:, 1]], pts[f[:, 2]]
        back = np.einsum("ij,ij->i", np.cross(b - a, c - a), nrm[f].sum(axis=1)) < 0
        f[back] = f[back][:, ::-1]
        out_faces.append(f)
    faces = np.concatenate(out_faces).astype(np.int64)
    return Mesh(pts, faces)
