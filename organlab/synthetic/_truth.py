"""Distance from points to the exact surface of a synthetic specimen.

Used to score reconstructions against :mod:`organlab.synthetic`'s solids:
a :class:`~organlab.synthetic.Sphere` has a closed form; the other solids
(the AAA phantom's star-shaped aorta and clipped cylindrical legs, the
grooved specimen, the cylinder) are sampled densely on their boundary with
outward normals, the samples inside another part of the union dropped, and a
point's distance is its offset along the normal of the nearest sample (the
tangent plane), exact to second order in the sample spacing.
"""

from __future__ import annotations

import numpy as np

from . import _render
from ._specimens import Cylinder, Sphere, _ClippedCylinder, _StarSolid


def _star_samples(star, h):
    z = np.arange(star.z_lo, star.z_hi + h / 2, h)
    z[-1] = min(z[-1], star.z_hi)
    n_phi = int(np.ceil(2 * np.pi * star.r_max / h))
    phi = np.arange(n_phi) * (2 * np.pi / n_phi)
    P, Z = np.meshgrid(phi, z)
    p, zz = P.ravel().copy(), Z.ravel().copy()
    r, rp, rz = _render.star_radius(p, zz, star.terms)
    c, s = np.cos(p), np.sin(p)
    pts = np.stack([r * c, r * s, zz], axis=1)
    g = np.stack([c + s * rp / r, s - c * rp / r, -rz], axis=1)
    nrm = g / np.linalg.norm(g, axis=1, keepdims=True)
    out = [(pts, nrm)]
    # caps: polar grid inside r(phi, z_cap)
    for zc, sign in ((star.z_lo, -1.0), (star.z_hi, 1.0)):
        x = np.arange(-star.r_max, star.r_max + h, h)
        X, Y = np.meshgrid(x, x)
        q = np.stack([X.ravel(), Y.ravel(), np.full(X.size, zc)], axis=1)
        rr = star.radius(np.arctan2(q[:, 1], q[:, 0]), q[:, 2])
        q = q[np.hypot(q[:, 0], q[:, 1]) <= rr]
        out.append((q, np.tile([0.0, 0.0, sign], (len(q), 1))))
    return out


def _cylinder_samples(cyl, h):
    u = cyl.axis
    e1 = np.cross(u, [1.0, 0.0, 0.0] if abs(u[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(u, e1)
    # axial parameter range covering z0..z1 (axis not horizontal)
    ts = [(z - cyl.point[2]) / u[2] for z in (cyl.z0, cyl.z1)]
    pad = cyl.radius * np.sqrt(max(1.0 / u[2] ** 2 - 1.0, 0.0)) + h
    t = np.arange(min(ts) - pad, max(ts) + pad, h)
    n_a = int(np.ceil(2 * np.pi * cyl.radius / h))
    a = np.arange(n_a) * (2 * np.pi / n_a)
    T, A = np.meshgrid(t, a)
    radial = np.cos(A.ravel())[:, None] * e1 + np.sin(A.ravel())[:, None] * e2
    pts = cyl.point + T.ravel()[:, None] * u + cyl.radius * radial
    keep = (pts[:, 2] >= cyl.z0) & (pts[:, 2] <= cyl.z1)
    out = [(pts[keep], radial[keep])]
    for zc, sign in ((cyl.z0, -1.0), (cyl.z1, 1.0)):
        c = cyl.point + (zc - cyl.point[2]) / u[2] * u
        reach = cyl.radius / abs(u[2]) + h
        x = np.arange(-reach, reach + h, h)
        X, Y = np.meshgrid(x, x)
        q = np.stack([c[0] + X.ravel(), c[1] + Y.ravel(), np.full(X.size, zc)], axis=1)
        q = q[cyl._inside(q)]
        out.append((q, np.tile([0.0, 0.0, sign], (len(q), 1))))
    return out


def surface_samples(specimen, *, spacing=0.25):
    """Points on a synthetic specimen's boundary and their outward normals.

    Parameters
    ----------
    specimen : organlab.synthetic.Specimen
        A sphere, cylinder, AAA phantom or grooved specimen.
    spacing : float, mm

    Returns
    -------
    points, normals : (N, 3) float64, mm, world frame; unit normals
    """
    if isinstance(specimen, Sphere):
        n = int(4 * np.pi * specimen.radius**2 / spacing**2)
        k = np.arange(n) + 0.5
        phi = np.arccos(1 - 2 * k / n)
        th = np.pi * (1 + 5**0.5) * k
        nrm = np.stack([np.cos(th) * np.sin(phi), np.sin(th) * np.sin(phi), np.cos(phi)], axis=1)
        return specimen.center + specimen.radius * nrm, nrm
    parts = [specimen._cyl] if isinstance(specimen, Cylinder) else list(getattr(specimen, "parts", []))
    if not parts:
        raise ValueError(f"no exact surface known for {specimen!r}")
    pieces = []
    for part in parts:
        if isinstance(part, _StarSolid):
            pieces += _star_samples(part, spacing)
        elif isinstance(part, _ClippedCylinder):
            pieces += _cylinder_samples(part, spacing)
        else:
            raise ValueError(f"no exact surface known for a part of type {type(part).__name__}")
    pts = np.concatenate([p for p, _ in pieces])
    nrm = np.concatenate([n for _, n in pieces])
    # on the union's boundary: just outside the point along its normal is outside every part
    eps = 1e-6
    keep = ~specimen.inside(pts + eps * nrm)
    return pts[keep], nrm[keep]


def distance_to_specimen(points, specimen, *, spacing=0.25, samples=None):
    """Signed distance from points to a synthetic specimen's exact surface.

    Parameters
    ----------
    points : (N, 3) float64, mm, world frame
    specimen : organlab.synthetic.Specimen
    spacing : float, mm
        Sample spacing on the true surface (ignored for a sphere).
    samples : tuple, optional
        ``surface_samples(specimen)`` computed once, to score several meshes.

    Returns
    -------
    (N,) float64, mm
        Positive outside the solid, negative inside.
    """
    from scipy.spatial import cKDTree

    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if isinstance(specimen, Sphere):
        return np.linalg.norm(p - specimen.center, axis=1) - specimen.radius
    sp, sn = samples if samples is not None else surface_samples(specimen, spacing=spacing)
    dist, idx = cKDTree(sp).query(p)
    off = p - sp[idx]
    along = np.abs(np.einsum("ij,ij->i", off, sn[idx]))
    lateral = np.sqrt(np.maximum(dist**2 - along**2, 0.0))
    # the tangent plane when the foot lies within a sample's reach, else the point distance (edges, rims)
    d = np.where(lateral <= spacing, along, dist)
    return np.where(specimen.inside(p), -d, d)
