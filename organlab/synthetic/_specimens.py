"""Synthetic specimens: analytic solids with known volumes, their tissue texture."""

from __future__ import annotations

import numpy as np

from ..camera import as_points, rot_z

from . import _render


def _texture_waves(seed):
    rng = np.random.default_rng([int(seed), 4242])
    n = 10
    k = rng.normal(size=(n, 3))
    k /= np.linalg.norm(k, axis=1, keepdims=True)
    lam = rng.uniform(12.0, 40.0, size=n)
    k *= (2 * np.pi / lam)[:, None]
    phase = rng.uniform(0, 2 * np.pi, size=n)
    amp = rng.uniform(0.6, 1.0, size=n)
    k2 = rng.normal(size=(3, 3))
    k2 /= np.linalg.norm(k2, axis=1, keepdims=True)
    k2 *= (2 * np.pi / rng.uniform(9.0, 16.0, size=3))[:, None]
    phase2 = rng.uniform(0, 2 * np.pi, size=3)
    return k, phase, amp, k2, phase2


_DARK = np.array([122.0, 44.0, 52.0])
_LIGHT = np.array([236.0, 176.0, 142.0])
_SPOT = np.array([112.0, 64.0, 150.0])


def tissue_albedo(points, *, seed=0):
    """Smooth, high-contrast, reddish tissue-like colour of surface points.

    Blotches from a sum of 3-D plane waves (wavelengths 12-40 mm) between a
    dark and a light red, with purple spots; a function of the point in the
    table frame, so it moves with the specimen.

    Parameters
    ----------
    points : (N, 3) float64, mm, world (table) frame

    Returns
    -------
    (N, 3) float64
        RGB albedo, 0-255 scale (grey levels about 60-200).
    """
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    k, phase, amp, k2, phase2 = _texture_waves(seed)
    v = np.einsum("ij,j->i", np.sin(np.einsum("ij,kj->ik", p, k) + phase), amp) / np.sqrt(np.sum(amp**2) / 2)
    s = 0.5 + 0.5 * np.tanh(1.3 * v)
    col = _DARK + s[:, None] * (_LIGHT - _DARK)
    w = np.prod(0.5 + 0.5 * np.sin(np.einsum("ij,kj->ik", p, k2) + phase2), axis=1)
    spot = np.clip((w - 0.35) / 0.25, 0.0, 1.0)
    spot = spot * spot * (3 - 2 * spot)
    return col + spot[:, None] * (_SPOT - col)


class Specimen:
    """A solid with an exactly known volume, standing on (or above) the table.

    Attributes
    ----------
    name : str
    volume : float
        Exact volume, mm^3.
    bounds : ((3,), (3,)) float64
        Axis-aligned box holding the solid, mm, world frame.
    """

    name = "specimen"
    texture_seed = 0

    def inside(self, points):
        """Membership test: ``(N,)`` bool for ``points (N, 3)`` mm, world frame (boundary counts as inside)."""
        p = as_points(points)
        return self._inside(p)

    def albedo(self, points):
        """Texture colour ``(N, 3)`` float64 RGB (0-255) at surface ``points (N, 3)``, mm, world frame."""
        return tissue_albedo(points, seed=self.texture_seed)

    def intersect(self, origins, directions):
        """First intersection of rays with the solid.

        Parameters
        ----------
        origins, directions : (N, 3) float64
            World frame, mm; directions unit vectors.

        Returns
        -------
        t : (N,) float64, mm
            Distance along the ray to the first hit, ``inf`` for a miss.
        normals : (N, 3) float64
            Outward unit normals at the hits (zeros for misses).
        """
        o = as_points(origins, "origins")
        d = as_points(directions, "directions")
        if o.shape != d.shape:
            o = np.broadcast_to(o, d.shape)
        return self._intersect(o, d, t_max=None)

    def _any_hit(self, o, d):
        """``(N,)`` bool: the rays that hit the solid (``np.isfinite`` of :meth:`_intersect`'s ``t``, ``t_max`` none)."""
        return np.isfinite(self._intersect(o, d, t_max=None)[0])

    def __repr__(self):
        return f"{type(self).__name__}(name={self.name!r}, volume={self.volume:.6g} mm^3)"


def _tmax(t_max, n):
    return np.full(n, np.inf) if t_max is None else np.asarray(t_max, dtype=np.float64)


class Sphere(Specimen):
    """A ball of radius ``radius`` mm centred at ``center`` (world frame, mm)."""

    def __init__(self, center=(0.0, 0.0, 40.0), radius=30.0, *, name="sphere"):
        self.center = np.asarray(center, dtype=np.float64).reshape(3)
        self.radius = float(radius)
        if not self.radius > 0:
            raise ValueError(f"radius must be > 0 mm, got {radius}")
        self.name = name
        self.volume = 4.0 / 3.0 * np.pi * self.radius**3
        self.bounds = (self.center - self.radius, self.center + self.radius)

    def _inside(self, p):
        return np.sum((p - self.center) ** 2, axis=1) <= self.radius**2

    def _intersect(self, o, d, t_max=None):
        oc = o - self.center
        b = np.sum(oc * d, axis=1)
        c = np.sum(oc * oc, axis=1) - self.radius**2
        disc = b * b - c
        with np.errstate(invalid="ignore"):
            t = -b - np.sqrt(disc)
        ok = (disc > 0) & (t > 0) & (t < _tmax(t_max, len(d)))
        t = np.where(ok, t, np.inf)
        normals = np.zeros_like(d)
        normals[ok] = (oc[ok] + t[ok, None] * d[ok]) / self.radius
        return t, normals


class _ClippedCylinder:
    """{dist(p, axis line) <= radius, z0 <= z <= z1}: a straight, possibly tilted, cylinder cut by two horizontal planes."""

    def __init__(self, point, axis, radius, z0, z1):
        self.point = np.asarray(point, dtype=np.float64)
        a = np.asarray(axis, dtype=np.float64)
        self.axis = a / np.linalg.norm(a)
        self.radius = float(radius)
        self.z0, self.z1 = float(z0), float(z1)

    @property
    def volume(self):
        # horizontal sections: ellipses of area pi rho^2 / cos(theta)
        return np.pi * self.radius**2 * (self.z1 - self.z0) / abs(self.axis[2])

    def _inside(self, p):
        q = p - self.point
        perp = q - np.outer(np.einsum("ij,j->i", q, self.axis), self.axis)
        return (np.sum(perp**2, axis=1) <= self.radius**2) & (p[:, 2] >= self.z0) & (p[:, 2] <= self.z1)

    def _intersect(self, o, d, t_max=None):
        n = len(d)
        u = self.axis
        q = o - self.point
        dp = d - np.outer(np.einsum("ij,j->i", d, u), u)
        qp = q - np.outer(np.einsum("ij,j->i", q, u), u)
        a = np.sum(dp * dp, axis=1)
        b = np.sum(dp * qp, axis=1)
        c = np.sum(qp * qp, axis=1) - self.radius**2
        with np.errstate(divide="ignore", invalid="ignore"):
            disc = b * b - a * c
            sq = np.sqrt(disc)
            ca = np.where(a > 1e-15, (-b - sq) / a, np.where(c <= 0, -np.inf, np.inf))
            cb = np.where(a > 1e-15, (-b + sq) / a, np.where(c <= 0, np.inf, -np.inf))
            za = (self.z0 - o[:, 2]) / d[:, 2]
            zb = (self.z1 - o[:, 2]) / d[:, 2]
        flat = np.abs(d[:, 2]) < 1e-15
        inslab = (o[:, 2] >= self.z0) & (o[:, 2] <= self.z1)
        s0 = np.where(flat, np.where(inslab, -np.inf, np.inf), np.minimum(za, zb))
        s1 = np.where(flat, np.where(inslab, np.inf, -np.inf), np.maximum(za, zb))
        tin = np.maximum(ca, s0)
        tout = np.minimum(cb, s1)
        ok = (disc > 0) & (tin < tout) & (tin > 0) & (tin < _tmax(t_max, n))
        t = np.where(ok, tin, np.inf)
        normals = np.zeros_like(d)
        side = ok & (ca >= s0)
        cap = ok & ~side
        ps = q[side] + t[side, None] * d[side]
        radial = ps - np.outer(np.einsum("ij,j->i", ps, u), u)
        normals[side] = radial / np.linalg.norm(radial, axis=1, keepdims=True)
        normals[cap, 2] = -np.sign(d[cap, 2])
        return t, normals


class Cylinder(Specimen):
    """A vertical circular cylinder: axis through ``center_xy``, radius mm, from ``z0`` to ``z1`` mm."""

    def __init__(self, center_xy=(0.0, 0.0), radius=30.0, z0=0.0, z1=80.0, *, name="cylinder"):
        if not radius > 0 or not z1 > z0:
            raise ValueError(f"need radius > 0 and z1 > z0, got radius={radius}, z0={z0}, z1={z1}")
        cx, cy = (float(v) for v in center_xy)
        self._cyl = _ClippedCylinder((cx, cy, 0.0), (0.0, 0.0, 1.0), radius, z0, z1)
        self.name = name
        self.volume = self._cyl.volume
        self.bounds = (np.array([cx - radius, cy - radius, z0]), np.array([cx + radius, cy + radius, z1]))

    def _inside(self, p):
        return self._cyl._inside(p)

    def _intersect(self, o, d, t_max=None):
        return self._cyl._intersect(o, d, t_max)


class _StarSolid:
    """{rho <= r(phi, z), z_lo <= z <= z_hi} with r a sum of separable terms (see ``_render``)."""

    _cache = {}

    def __init__(self, terms, z_lo, z_hi):
        self.terms = np.ascontiguousarray(terms, dtype=np.float64)
        self.z_lo, self.z_hi = float(z_lo), float(z_hi)
        key = (self.terms.tobytes(), self.z_lo, self.z_hi)
        if key in self._cache:
            self.r_min, self.r_max, self.lip, self.volume = self._cache[key]
            return
        phi = np.linspace(0, 2 * np.pi, 1441)
        z = np.linspace(self.z_lo - 5, self.z_hi + 5, 601)
        P, Z = np.meshgrid(phi, z)
        r, rp, rz = _render.star_radius(P.ravel(), Z.ravel(), self.terms)
        self.r_min = float(r.min())
        if self.r_min <= 0:
            raise ValueError("star solid radius must stay > 0")
        self.r_max = float(r.max()) * 1.02 + 0.5
        # Lipschitz bound of f = rho - r(phi, z) where rho >= r_min (with a safety factor)
        self.lip = 1.25 * float(np.sqrt(1.0 + (np.abs(rp).max() / self.r_min) ** 2 + np.abs(rz).max() ** 2))
        self.volume = self._volume()
        self._cache[key] = (self.r_min, self.r_max, self.lip, self.volume)

    def radius(self, phi, z):
        phi, z = np.broadcast_arrays(np.asarray(phi, float), np.asarray(z, float))
        r, _, _ = _render.star_radius(phi.ravel().copy(), z.ravel().copy(), self.terms)
        return r.reshape(phi.shape)

    def _volume(self, n_gauss=48, n_phi=2048):
        # breakpoints of the piecewise-smooth z profile
        br = {self.z_lo, self.z_hi}
        for row in self.terms:
            if row[1] != 0:
                br.update(v for v in row[2:4] if self.z_lo < v < self.z_hi)
        br = np.array(sorted(br))
        x, w = np.polynomial.legendre.leggauss(n_gauss)
        phi = np.arange(n_phi) * (2 * np.pi / n_phi)
        total = 0.0
        for a, b in zip(br[:-1], br[1:]):
            z = 0.5 * (b - a) * x + 0.5 * (a + b)
            r = self.radius(phi[None, :], z[:, None])
            area = 0.5 * np.mean(r**2, axis=1) * 2 * np.pi  # periodic trapezoid rule
            total += 0.5 * (b - a) * np.dot(w, area)
        return float(total)

    def _inside(self, p):
        rho = np.hypot(p[:, 0], p[:, 1])
        z = p[:, 2]
        ok = (z >= self.z_lo) & (z <= self.z_hi) & (rho <= self.r_max)
        out = np.zeros(len(p), dtype=bool)
        idx = np.flatnonzero(ok)
        if idx.size:
            r = self.radius(np.arctan2(p[idx, 1], p[idx, 0]), z[idx])
            out[idx] = rho[idx] <= r
        return out

    def _trace(self, o, d, t_max, first):
        o = np.ascontiguousarray(o, dtype=np.float64)
        d = np.ascontiguousarray(d, dtype=np.float64)
        t, kind = _render.star_trace(
            o, d, _tmax(t_max, len(d)), self.terms, self.z_lo, self.z_hi, self.r_max, self.lip, 0.02, 1e-5, first
        )
        return o, d, t, kind

    def _any_hit(self, o, d):
        # the same marching as _intersect (the same rays hit), without the bisection and the normals
        return np.isfinite(self._trace(o, d, None, False)[2])

    def _intersect(self, o, d, t_max=None):
        o, d, t, kind = self._trace(o, d, t_max, True)
        normals = np.zeros_like(d)
        normals[kind == 2, 2] = 1.0
        normals[kind == 3, 2] = -1.0
        side = np.flatnonzero(kind == 1)
        if side.size:
            p = o[side] + t[side, None] * d[side]
            phi = np.arctan2(p[:, 1], p[:, 0])
            rho = np.hypot(p[:, 0], p[:, 1])
            _, rp, rz = _render.star_radius(phi, p[:, 2].copy(), self.terms)
            c, s = np.cos(phi), np.sin(phi)
            gphi = -rp / rho
            g = np.stack([c - s * gphi, s + c * gphi, -rz], axis=1)
            normals[side] = g / np.linalg.norm(g, axis=1, keepdims=True)
        return t, normals


class _Union(Specimen):
    def __init__(self, parts, volume, bounds, name):
        self.parts = parts
        self.volume = float(volume)
        self.bounds = bounds
        self.name = name

    def _inside(self, p):
        out = np.zeros(len(p), dtype=bool)
        for part in self.parts:
            out |= part._inside(p)
        return out

    def _intersect(self, o, d, t_max=None):
        t_best = _tmax(t_max, len(d)).copy()
        normals = np.zeros_like(d)
        hit_any = np.zeros(len(d), dtype=bool)
        for part in self.parts:
            t, nrm = part._intersect(o, d, t_best)
            closer = t < t_best
            t_best[closer] = t[closer]
            normals[closer] = nrm[closer]
            hit_any |= closer
        return np.where(hit_any, t_best, np.inf), normals

    def _any_hit(self, o, d):
        # _intersect's t is finite where any part's is (a later part only gets a t_max where an earlier one hit)
        hit = np.zeros(len(d), dtype=bool)
        for part in self.parts:
            rest = np.flatnonzero(~hit)
            if rest.size == 0:
                break
            any_hit = getattr(part, "_any_hit", None)
            if any_hit is None:
                got = np.isfinite(part._intersect(o[rest], d[rest], None)[0])
            else:
                got = any_hit(o[rest], d[rest])
            hit[rest[got]] = True
        return hit


class AAAPhantom(_Union):
    """An abdominal-aortic-aneurysm-like phantom standing on the table (z >= 0).

    Above ``z_b`` (the bifurcation) a solid star-shaped about the Z axis,
    ``rho <= r(phi, z)``, closed by a flat cap at the top: the infrarenal
    aorta (diameter about 25 mm, flaring slightly toward the bifurcation)
    with an asymmetric fusiform aneurysm (maximum diameter about 54 mm).
    Below ``z_b`` two straight tilted circular cylinders (the iliac legs),
    clipped by ``z = 0`` and ``z = z_b``, whose horizontal sections are
    disjoint ellipses inside the aorta's section at ``z_b``.

    The volume is exact: ``int 0.5 r^2 dphi dz`` by Gauss-Legendre in z
    (per smooth piece) and the periodic trapezoid rule in phi (spectrally
    exact), plus ``2 pi rho^2 z_b / cos(theta)`` for the legs.
    """

    def __init__(self, *, name="aaa", shape_seed=None):
        z_b, z_top = 32.0, 172.0
        r_aorta = 12.6
        # shape_seed=None: the sample's phantom; an int: another AAA of the same family
        # (sac size, extent, asymmetry, bleb and ovality drawn within the family's ranges)
        g = None if shape_seed is None else np.random.default_rng([int(shape_seed), 2020])
        def u(default, lo, hi):
            return default if g is None else float(g.uniform(lo, hi))
        sac_lo, sac_hi = u(42.0, 38.0, 52.0), u(158.0, 140.0, 162.0)
        bleb_z = u(70.0, 55.0, 95.0)
        terms = [
            [r_aorta, 0, 0, 0, 0, 0, 0],
            [1.6, 2, z_b, z_b + 22.0, 0, 0, 0],  # flare toward the bifurcation
            [-0.8, 1, z_b + 90.0, z_top + 60.0, 0, 0, 0],  # gentle taper toward the top
            [u(13.4, 10.0, 15.0), 1, sac_lo, sac_hi, 0, 0, 0],  # fusiform aneurysm
            [u(2.4, 1.5, 4.0), 1, sac_lo, sac_hi, 1, 1, u(0.6, -np.pi, np.pi)],  # asymmetry
            [u(2.0, 1.5, 3.5), 1, bleb_z, bleb_z + 60.0, 2, 3.0, u(0.9, -np.pi, np.pi)],  # a bleb
            [u(0.5, 0.3, 1.5), 1, sac_lo, sac_hi, 1, 2, u(0.3, -np.pi, np.pi)],  # ovality
        ]
        star = _StarSolid(np.array(terms, dtype=np.float64), z_b, z_top)
        r_b = float(star.radius(np.linspace(0, 2 * np.pi, 721), np.full(721, z_b)).min())
        theta = np.deg2rad(18.0)
        psi = np.deg2rad(12.0)
        rho = 5.9
        A = rho / np.cos(theta)  # semi-axis of a leg's section along its tilt
        c = A + 0.45 * (r_b - 2 * A)  # ellipse centres at z_b: disjoint, inside the aorta
        assert c + A < r_b and c > A, "iliac legs must fit inside the aorta at z_b"
        legs = []
        for sgn in (1.0, -1.0):
            e = sgn * np.array([np.cos(psi), np.sin(psi), 0.0])
            axis = np.array([e[0] * np.sin(theta), e[1] * np.sin(theta), -np.cos(theta)])
            legs.append(_ClippedCylinder(np.array([c * e[0], c * e[1], z_b]), axis, rho, 0.0, z_b))
        volume = star.volume + sum(leg.volume for leg in legs)
        reach = max(star.r_max, c + z_b * np.tan(theta) + A)
        bounds = (np.array([-reach, -reach, 0.0]), np.array([reach, reach, z_top]))
        super().__init__([star, *legs], volume, bounds, name)
        self.star = star
        self.legs = legs
        self.z_b = z_b
        self.height = z_top


class _Stump:
    """A horizontal branch stump: ``{|q_perp| <= radius, s0 <= s <= s1} U ball(s1, radius)``, ``s`` along ``direction``.

    ``q = p - (0, 0, z)``, ``s = q . e`` with ``e = (cos a, sin a, 0)`` (``a`` = ``azimuth_deg``): a cylinder
    on a radial line of the table axis at height ``z``, closed by a flat cap at ``s0`` (buried in the aorta)
    and a hemisphere at ``s1``; a convex solid.
    """

    def __init__(self, azimuth_deg, z, radius, s0, s1):
        a = np.deg2rad(float(azimuth_deg))
        self.e = np.array([np.cos(a), np.sin(a), 0.0])
        self.azimuth = float(a)
        self.z, self.radius, self.s0, self.s1 = float(z), float(radius), float(s0), float(s1)
        self.point = np.array([0.0, 0.0, self.z])

    @property
    def volume(self):
        return np.pi * self.radius**2 * (self.s1 - self.s0) + 2.0 / 3.0 * np.pi * self.radius**3

    def _inside(self, p):
        q = p - self.point
        s = q @ self.e
        perp2 = np.sum(q * q, axis=1) - s * s
        tip = np.sum((q - self.s1 * self.e) ** 2, axis=1) <= self.radius**2
        return ((perp2 <= self.radius**2) & (s >= self.s0) & (s <= self.s1)) | tip

    def _intersect(self, o, d, t_max=None):
        # a convex solid: the first hit is the nearest entering hit on its side, tip or inner cap
        n = len(d)
        e, rr = self.e, self.radius
        q = o - self.point
        qs, ds = q @ e, d @ e
        qp, dp = q - qs[:, None] * e, d - ds[:, None] * e
        a = np.sum(dp * dp, axis=1)
        b = np.sum(dp * qp, axis=1)
        c = np.sum(qp * qp, axis=1) - rr**2
        with np.errstate(divide="ignore", invalid="ignore"):
            disc = b * b - a * c
            t_side = np.where((disc > 0) & (a > 1e-15), (-b - np.sqrt(disc)) / a, np.inf)
            s_side = qs + t_side * ds
            t_side = np.where((s_side >= self.s0) & (s_side <= self.s1), t_side, np.inf)
            qt = q - self.s1 * e
            bt = np.sum(qt * d, axis=1)
            ct = np.sum(qt * qt, axis=1) - rr**2
            dt = bt * bt - ct
            t_tip = np.where(dt > 0, -bt - np.sqrt(dt), np.inf)
            t_tip = np.where(qs + t_tip * ds >= self.s1, t_tip, np.inf)
            t_cap = np.where(ds > 1e-15, (self.s0 - qs) / ds, np.inf)
            pc = q + t_cap[:, None] * d
            pc_perp = pc - (pc @ e)[:, None] * e
            t_cap = np.where(np.sum(pc_perp * pc_perp, axis=1) <= rr**2, t_cap, np.inf)
        t_side = np.where(t_side > 0, t_side, np.inf)
        t_tip = np.where(t_tip > 0, t_tip, np.inf)
        t_cap = np.where(t_cap > 0, t_cap, np.inf)
        t = np.minimum(np.minimum(t_side, t_tip), t_cap)
        t = np.where(t < _tmax(t_max, n), t, np.inf)
        normals = np.zeros_like(d)
        hit = np.isfinite(t)
        p = q + np.where(hit, t, 0.0)[:, None] * d
        side = hit & (t == t_side)
        tip = hit & ~side & (t == t_tip)
        cap = hit & ~side & ~tip
        ps = p[side] - (p[side] @ e)[:, None] * e
        normals[side] = ps / np.linalg.norm(ps, axis=1, keepdims=True)
        normals[tip] = (p[tip] - self.s1 * e) / rr
        normals[cap] = -e
        return t, normals

    def overlap(self, star, n_r=24, n_theta=64):
        """Volume (mm^3) of this stump inside ``star``: ``int (s*(u, v) - s0) du dv`` over the cross-section,
        ``s*`` where the line along ``e`` at offset ``(u, v)`` leaves the star solid (Gauss-Legendre in the
        disc's radius, the periodic trapezoid rule about it; the integrand is smooth when no z breakpoint of
        the star's terms lies within the stump's height, checked)."""
        br = [row[2:4] for row in star.terms if row[1] != 0]
        lo, hi = self.z - self.radius, self.z + self.radius
        if any(lo <= v <= hi for pair in br for v in pair) or not star.z_lo < lo < hi < star.z_hi:
            raise ValueError("a branch must lie between the z breakpoints of the aorta's terms")
        x, w = np.polynomial.legendre.leggauss(n_r)
        rad = 0.5 * self.radius * (x + 1.0)
        wr = 0.5 * self.radius * w * rad  # r dr
        th = np.arange(n_theta) * (2 * np.pi / n_theta)
        R, T = np.meshgrid(rad, th)
        u, v = (R * np.cos(T)).ravel(), (R * np.sin(T)).ravel()
        z = self.z + v
        s = np.full(u.shape, star.r_min)
        for _ in range(60):  # fixed point of s = sqrt(r(phi(s), z)^2 - u^2): r varies slowly along the line
            s_new = np.sqrt(star.radius(self.azimuth + np.arctan2(u, s), z) ** 2 - u**2)
            if np.max(np.abs(s_new - s)) < 1e-13:
                s = s_new
                break
            s = s_new
        if not (np.all(s > self.s0) and np.all(s < self.s1)):
            raise ValueError("a branch must start inside the aorta and leave it before its tip")
        length = (s - self.s0).reshape(R.shape)
        return float(np.sum(length * wr[None, :]) * (2 * np.pi / n_theta))


class BranchedAAA(AAAPhantom):
    """An AAA of the family with short branch stumps (renal-artery-like) near the top: its outline shows its angles.

    :class:`AAAPhantom` (``shape_seed``) plus, per branch ``(azimuth_deg, z_mm, radius_mm, length_mm)``, a
    horizontal cylinder on a radial line of the table axis, buried in the aorta from 4 mm off the axis, leaving
    it ``length`` mm beyond the aorta's surface on that line and closed by a hemisphere.  An AAA is near
    symmetric about the table axis (a turn of the table moves its outline by a fraction of a pixel); a stump
    sticking out 10-20 mm moves its outline's top corners by about a pixel per degree.

    The volume is exact: the aorta's and legs' (:class:`AAAPhantom`) plus each stump's minus its part inside
    the aorta (:meth:`_Stump.overlap`, converged to about 1e-12 mm^3); the stumps are disjoint from each other
    and from the legs.
    """

    BRANCHES = ((80.0, 165.0, 3.2, 18.0), (235.0, 161.5, 3.0, 15.0))

    def __init__(self, *, name="aaa+branch", shape_seed=None, branches=BRANCHES):
        super().__init__(name=name, shape_seed=shape_seed)
        stumps = []
        for az, z, rad, length in branches:
            r_out = float(self.star.radius(np.deg2rad(az), z))
            stumps.append(_Stump(az, z, rad, 4.0, r_out + length - rad))
        for i, a in enumerate(stumps):  # disjoint: each lies within its radius of its axis segment, and two
            for b in stumps[i + 1 :]:  # segments at least 90 degrees apart are nearest at their inner ends
                gap = np.arccos(np.clip(a.e @ b.e, -1, 1))
                near = np.hypot(2 * a.s0 * np.sin(gap / 2), a.z - b.z)
                if abs(a.z - b.z) <= a.radius + b.radius and (gap < np.pi / 2 or near <= a.radius + b.radius):
                    raise ValueError("branches must be at least 90 degrees apart (or apart in height) and disjoint")
        over = [st.overlap(self.star) for st in stumps]
        self.parts = [*self.parts, *stumps]
        self.volume = float(self.volume + sum(st.volume - ov for st, ov in zip(stumps, over)))
        reach = max(float(np.abs(np.concatenate([self.bounds[0][:2], self.bounds[1][:2]])).max()),
                    max(st.s1 + st.radius for st in stumps))
        self.bounds = (np.array([-reach, -reach, 0.0]), np.array([reach, reach, self.height]))
        self.stumps = stumps


class GroovedSpecimen(_Union):
    """A textured star-shaped prism with hidden pockets no silhouette shows.

    ``rho <= r(phi, z)``, ``0 <= z <= height``: a rounded trefoil-ish
    section (radius about 30 mm) with ``n_grooves`` narrow vertical dents,
    ``depth`` mm deep at mid-height, cut into its side between
    ``z = 15`` and ``75`` mm (smooth in phi and z, closed above and below).
    Seen from cameras around and above the table, most of each dent stays
    inside the visual hull: silhouettes cannot carve it, only colour
    consistency can (of the about 17.8 cm^3 of pockets below the ungrooved
    surface, about 10.0 cm^3 project inside the silhouette in all 36 views
    of :func:`default_camera`).  Exact volume as for :class:`AAAPhantom`.
    """

    Z_POCKETS = (15.0, 75.0)

    def __init__(self, *, n_grooves=5, depth=11.0, height=115.0, name="grooved"):
        if n_grooves < 0 or not 0 <= depth < 20 or not height > self.Z_POCKETS[1]:
            raise ValueError(f"need n_grooves >= 0, 0 <= depth < 20 mm, height > {self.Z_POCKETS[1]} mm")
        terms = [[30.0, 0, 0, 0, 0, 0, 0], [2.0, 0, 0, 0, 1, 3, 0.2]]
        self.groove_angles = [0.5 + 2 * np.pi * k / n_grooves for k in range(int(n_grooves))]
        for mu in self.groove_angles:
            terms.append([-float(depth), 1, *self.Z_POCKETS, 2, 40.0, mu])
        star = _StarSolid(np.array(terms), 0.0, float(height))
        r = star.r_max
        super().__init__([star], star.volume, (np.array([-r, -r, 0.0]), np.array([r, r, float(height)])), name)
        self.star = star


def striped_albedo(points):
    """A greenish-yellow texture with fine dark stripes and speckles: unlike :func:`tissue_albedo`.

    Stripes (period about 7 mm, tilted) and a higher-frequency speckle over
    a green-to-ochre gradient in z; no default of organlab was tuned on it.

    Parameters
    ----------
    points : (N, 3) float64, mm, world (table) frame

    Returns
    -------
    (N, 3) float64
        RGB albedo, 0-255 scale.
    """
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    phi = np.arctan2(p[:, 1], p[:, 0])
    stripe = 0.5 + 0.5 * np.tanh(2.5 * np.sin(2 * np.pi * (p[:, 2] + 9.0 * phi) / 7.0))
    speck = 0.5 + 0.5 * np.sin(0.9 * p[:, 0] + 0.3) * np.sin(1.1 * p[:, 1] - 0.7) * np.sin(0.8 * p[:, 2] + 1.9)
    g = np.clip(p[:, 2] / 90.0, 0.0, 1.0)[:, None]
    base = (1 - g) * np.array([96.0, 170.0, 70.0]) + g * np.array([200.0, 160.0, 60.0])
    dark = np.array([40.0, 52.0, 30.0])
    col = dark + (base - dark) * (0.35 + 0.65 * stripe)[:, None]
    return col * (0.8 + 0.2 * speck)[:, None]


class DentedSpecimen(_Union):
    """A squat, textured, lobed solid with hidden dents (a specimen no default was tuned on).

    ``rho <= r(phi, z)``, ``0 <= z <= 90``: a four-lobed section (radius
    about 34 mm) with ``n_dents`` round dents, ``depth`` mm deep, each
    localised in phi and z (between 20 and 70 mm), on the lobes' flanks, so
    most of each dent lies inside every silhouette of a camera ring.  The
    texture is :func:`striped_albedo`.  Exact volume as for :class:`AAAPhantom`.
    """

    def __init__(self, *, n_dents=6, depth=8.0, height=90.0, name="dented"):
        if n_dents < 0 or not 0 <= depth < 16 or not height > 75.0:
            raise ValueError("need n_dents >= 0, 0 <= depth < 16 mm, height > 75 mm")
        terms = [[34.0, 0, 0, 0, 0, 0, 0], [3.0, 0, 0, 0, 1, 4, 0.3], [2.0, 1, -10.0, height + 10.0, 0, 0, 0]]
        self.dent_angles = [0.9 + 2 * np.pi * k / n_dents for k in range(int(n_dents))]
        for k, mu in enumerate(self.dent_angles):
            z0 = 20.0 + 8.0 * (k % 3)
            terms.append([-float(depth), 1, z0, z0 + 42.0, 2, 30.0, mu])
        star = _StarSolid(np.array(terms, dtype=np.float64), 0.0, float(height))
        r = star.r_max
        super().__init__([star], star.volume, (np.array([-r, -r, 0.0]), np.array([r, r, float(height)])), name)
        self.star = star

    def albedo(self, points):
        return striped_albedo(points)


class Moved(Specimen):
    """A specimen moved rigidly on the plate: ``X' = Rz(rotation_deg) @ X + (dx, dy, 0)``.

    Parameters
    ----------
    specimen : Specimen
    translation_mm : (2,) float
        ``(dx, dy)``, world frame, mm.
    rotation_deg : float
        About the table axis (+Z), degrees.
    """

    def __init__(self, specimen, translation_mm=(0.0, 0.0), rotation_deg=0.0):
        self.inner = specimen
        self.R = rot_z(rotation_deg)
        self.s = np.array([float(translation_mm[0]), float(translation_mm[1]), 0.0])
        self.volume = specimen.volume
        self.name = specimen.name
        self.texture_seed = getattr(specimen, "texture_seed", 0)
        lo, hi = (np.asarray(b, np.float64) for b in specimen.bounds)
        r = float(np.max(np.abs(np.concatenate([lo[:2], hi[:2]])))) * np.sqrt(2.0) + float(np.abs(self.s).max())
        self.bounds = (np.array([-r, -r, lo[2]]), np.array([r, r, hi[2]]))

    def _to_inner(self, p):
        return (p - self.s) @ self.R  # R.T @ (p - s) row-wise

    def _inside(self, p):
        return self.inner._inside(self._to_inner(p))

    def _intersect(self, o, d, t_max=None):
        t, nrm = self.inner._intersect(np.ascontiguousarray(self._to_inner(o)), np.ascontiguousarray(d @ self.R), t_max)
        return t, nrm @ self.R.T

    def _any_hit(self, o, d):
        return self.inner._any_hit(np.ascontiguousarray(self._to_inner(o)), np.ascontiguousarray(d @ self.R))

    def albedo(self, points):
        return self.inner.albedo(self._to_inner(np.asarray(points, np.float64)))


def make_specimen(name):
    """The specimen called ``name``: ``"aaa"`` (:class:`AAAPhantom`), ``"aaa-N"`` (another AAA of the family, shape seed N), ``"aaa+branch"`` / ``"aaa-N+branch"`` (the same with renal-artery-like stumps, :class:`BranchedAAA`), ``"grooved"`` (:class:`GroovedSpecimen`) or ``"dented"`` (:class:`DentedSpecimen`)."""
    if isinstance(name, Specimen):
        return name
    if name == "aaa":
        return AAAPhantom()
    if isinstance(name, str) and name.startswith("aaa-") and name[4:].isdigit():
        return AAAPhantom(name=name, shape_seed=int(name[4:]))
    if isinstance(name, str) and name.endswith("+branch") and (name == "aaa+branch" or (name.startswith("aaa-") and name[4:-7].isdigit())):
        return BranchedAAA(name=name, shape_seed=None if name == "aaa+branch" else int(name[4:-7]))
    if name == "grooved":
        return GroovedSpecimen()
    if name == "dented":
        return DentedSpecimen()
    raise ValueError(f"unknown specimen {name!r}; choose 'aaa', 'aaa-N' (N an integer), 'aaa-N+branch', 'grooved' or 'dented'")
