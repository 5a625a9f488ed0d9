"""Private workers of :mod:`organlab.synthetic`: ray generation, ray casting, shading.

Everything here works on flat arrays of rays (origins and unit directions in
the world frame, mm).  The public wrappers live in :mod:`organlab.synthetic`.
"""

from __future__ import annotations

from functools import lru_cache

import numba
import numpy as np

from ..camera import Camera
from ..nbcam import undistort_points

# Lighting fixed relative to the camera: mostly ambient, mild diffuse.
AMBIENT = 0.82
DIFFUSE = 0.22
# Unit vector toward the light, camera frame (upper left, behind the camera).
LIGHT_CAM = np.array([-0.35, -0.6, -1.0]) / np.linalg.norm([-0.35, -0.6, -1.0])

# Albedo (grey level) of the board's black and white squares.
BOARD_BLACK = 28.0
BOARD_WHITE = 212.0

# Turntable plate: a disk, top at z = 0, side down to PLATE_BOTTOM.
PLATE_RADIUS = 125.0
PLATE_BOTTOM = -14.0

CHUNK = 1 << 20


# --------------------------------------------------------------------- rays
@lru_cache(maxsize=2)
def _camera_frame_rays(K_bytes, dist_bytes, size, supersample):
    """Unit ray directions, camera frame, of every sub-pixel sample.

    Order: ``((v * W + u) * ss + sv) * ss + su``; a sample sits at
    ``u + (su + 0.5) / ss - 0.5``, ``v + (sv + 0.5) / ss - 0.5``.
    """
    K = np.frombuffer(K_bytes, dtype=np.float64).reshape(3, 3)
    dist = np.frombuffer(dist_bytes, dtype=np.float64)
    cam = Camera(K, dist, image_size=size)
    w, h = size
    ss = int(supersample)
    off = (np.arange(ss) + 0.5) / ss - 0.5
    v = np.arange(h)[:, None, None, None] + off[None, None, :, None]
    u = np.arange(w)[None, :, None, None] + off[None, None, None, :]
    v, u = np.broadcast_arrays(v, u)
    pix = np.stack([u.ravel(), v.ravel()], axis=1).astype(np.float64)
    dirs = np.empty((pix.shape[0], 3))
    for s in range(0, pix.shape[0], CHUNK):
        # Camera.rays with the identity pose gives camera-frame directions; _normalized_chunk is its
        # pixels_to_normalized (undistort's Newton steps, stopping for the whole chunk) compiled
        xn = _normalized_chunk(pix[s : s + CHUNK], cam.K, cam.dist, 30) if np.any(cam.dist) else None
        dirs[s : s + CHUNK] = cam.rays(pix[s : s + CHUNK])[1] if xn is None else _unit_rays(xn)
    dirs.setflags(write=False)
    return dirs


def _unit_rays(xn):
    """``Camera.rays``' directions for the identity pose from undistorted normalized coordinates ``(N, 2)``."""
    d = np.concatenate([xn, np.ones((xn.shape[0], 1))], axis=1)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return d


@numba.njit(cache=True)
def _normalized_chunk(px, K, dist, iterations):
    """:meth:`Camera.pixels_to_normalized` of pixels ``(N, 2)``: the same operations in the same order.

    :func:`organlab.camera.undistort`'s Newton steps on every point (:func:`organlab.nbcam.undistort_points`),
    until the largest residual of the chunk (NaN ignored) is below 1e-14 or ``iterations`` steps.
    """
    xy = np.empty((px.shape[0], 2))
    for i in range(px.shape[0]):
        xy[i, 1] = (px[i, 1] - K[1, 2]) / K[1, 1]
        xy[i, 0] = (px[i, 0] - K[0, 2] - K[0, 1] * xy[i, 1]) / K[0, 0]
    return undistort_points(xy, dist, iterations)


def camera_frame_rays(camera, supersample):
    """Camera-frame unit directions of all sub-pixel samples of ``camera`` (cached)."""
    return _camera_frame_rays(
        np.ascontiguousarray(camera.K).tobytes(),
        np.ascontiguousarray(camera.dist).tobytes(),
        tuple(camera.image_size),
        int(supersample),
    )


@lru_cache(maxsize=2)
def _backdrop_layer(K_bytes, dist_bytes, size, supersample):
    layer = backdrop(_camera_frame_rays(K_bytes, dist_bytes, size, supersample))
    layer.setflags(write=False)
    return layer


def backdrop_layer(camera, supersample):
    """:func:`backdrop` of all sub-pixel samples of ``camera`` (cached on the intrinsics: fixed to the camera)."""
    return _backdrop_layer(
        np.ascontiguousarray(camera.K).tobytes(),
        np.ascontiguousarray(camera.dist).tobytes(),
        tuple(camera.image_size),
        int(supersample),
    )


def downsample(samples, size, supersample):
    """Box-filter ``(N, C)`` sub-pixel samples to an ``(H, W, C)`` image."""
    w, h = size
    ss = int(supersample)
    c = samples.shape[1]
    return samples.reshape(h, w, ss * ss, c).mean(axis=2)


# ------------------------------------------------------------------ shading
def shade(albedo, normals, light_world):
    """Ambient + mild two-sided diffuse shading.  ``albedo (N, 3)``, ``normals (N, 3)``."""
    lam = np.abs(np.einsum("ij,j->i", normals, light_world))
    return albedo * (AMBIENT + DIFFUSE * lam)[:, None]


def backdrop(d_cam):
    """Backdrop colour for rays hitting nothing: a dark smooth gradient of the camera-frame direction."""
    y = d_cam[:, 1] / d_cam[:, 2].clip(0.2)
    x = d_cam[:, 0] / d_cam[:, 2].clip(0.2)
    g = 34.0 + 14.0 * np.tanh(y) + 5.0 * np.cos(1.3 * x)
    return np.stack([g * 0.95, g, g * 1.12], axis=1)


def plate_hits(o, d):
    """First hit of rays with the turntable plate (top disk + side wall).

    Returns ``t`` (inf for misses), the colour albedo ``(N, 3)`` and normals.
    """
    return _plate_kernel(np.ascontiguousarray(o, dtype=np.float64), np.ascontiguousarray(d, dtype=np.float64))


@numba.njit(cache=True, error_model="numpy")
def _plate_kernel(o, d):
    """:func:`plate_hits` ray by ray: the operations of the vectorized version this replaced."""
    n = d.shape[0]
    t = np.full(n, np.inf)
    albedo = np.zeros((n, 3))
    normal = np.zeros((n, 3))
    R = PLATE_RADIUS
    for i in range(n):
        o0, o1, o2 = o[i, 0], o[i, 1], o[i, 2]
        d0, d1, d2 = d[i, 0], d[i, 1], d[i, 2]
        # top disk z = 0, seen from above
        tt = -o2 / d2
        rho = np.hypot(o0 + tt * d0, o1 + tt * d1)
        if tt > 0 and rho <= R and o2 > 0:
            t[i] = tt
            g = 128.0 + 10.0 * np.cos(2 * np.pi * rho / 24.0)
            albedo[i, 0] = g
            albedo[i, 1] = g
            albedo[i, 2] = g * 0.97
            normal[i, 2] = 1.0
        # side wall, rho = R, PLATE_BOTTOM <= z <= 0
        a = d0 * d0 + d1 * d1
        b = o0 * d0 + o1 * d1
        c = o0 * o0 + o1 * o1 - R * R
        disc = b * b - a * c
        ts = (-b - np.sqrt(disc)) / a
        zs = o2 + ts * d2
        if disc > 0 and ts > 0 and zs <= 0 and zs >= PLATE_BOTTOM and ts < t[i]:
            t[i] = ts
            albedo[i, 0] = 70.0
            albedo[i, 1] = 70.0
            albedo[i, 2] = 72.0
            normal[i, 0] = (o0 + ts * d0) / R
            normal[i, 1] = (o1 + ts * d1) / R
            normal[i, 2] = 0.0
    return t, albedo, normal


def board_hits(o, d, R_board, t_board, inner_corners, square, margin):
    """Hits of rays with a printed checkerboard (a zero-thickness rectangle).

    The board frame has the inner corners at ``(i * square, j * square, 0)``;
    square ``(a, b)`` (``a = 0..cols``, ``b = 0..rows``) spans
    ``x in [(a - 1) s, a s]``, ``y in [(b - 1) s, b s]`` and is black when
    ``a + b`` is even, so the corner squares at ``x < 0`` are black and those
    at the far ``+x`` end are white (10 x 7 squares for 9 x 6 inner corners).
    """
    n_x, n_y = inner_corners
    s = float(square)
    R_board = np.ascontiguousarray(R_board, dtype=np.float64)
    t_board = np.ascontiguousarray(t_board, dtype=np.float64)
    normal_w = np.ascontiguousarray(R_board[:, 2])
    t_dot_n = t_board @ normal_w
    limits = np.array([-s - margin, n_x * s + margin, -s - margin, n_y * s + margin])
    t_out, grey = _board_kernel(np.ascontiguousarray(o, dtype=np.float64), np.ascontiguousarray(d, dtype=np.float64),
                                normal_w, t_dot_n, R_board, t_board, s, limits, int(n_x), int(n_y))
    albedo = np.zeros((d.shape[0], 3))
    albedo[:] = grey[:, None]
    normal = np.broadcast_to(normal_w, d.shape)
    return t_out, albedo, normal


@numba.njit(cache=True, error_model="numpy")
def _board_kernel(o, d, nw, t_dot_n, R, tb, s, limits, n_x, n_y):
    """Per ray: the board's ``t`` (inf: no hit) and grey albedo (0: no hit), the operations of the
    vectorized version this replaced (einsum's sums in index order), ray by ray."""
    n = d.shape[0]
    t_out = np.full(n, np.inf)
    grey = np.zeros(n)
    for i in range(n):
        denom = 0.0
        on_ = 0.0
        for j in range(3):
            denom += d[i, j] * nw[j]
        for j in range(3):
            on_ += o[i, j] * nw[j]
        t = (t_dot_n - on_) / denom
        if not (np.isfinite(t) and t > 0):
            continue
        q0 = o[i, 0] + t * d[i, 0] - tb[0]
        q1 = o[i, 1] + t * d[i, 1] - tb[1]
        q2 = o[i, 2] + t * d[i, 2] - tb[2]
        x = 0.0
        x += q0 * R[0, 0]
        x += q1 * R[1, 0]
        x += q2 * R[2, 0]
        y = 0.0
        y += q0 * R[0, 1]
        y += q1 * R[1, 1]
        y += q2 * R[2, 1]
        if not ((x >= limits[0]) and (x <= limits[1]) and (y >= limits[2]) and (y <= limits[3])):
            continue
        a = np.int64(np.floor(x / s)) + 1
        b = np.int64(np.floor(y / s)) + 1
        t_out[i] = t
        if (a >= 0) and (a <= n_x) and (b >= 0) and (b <= n_y) and ((a + b) % 2 == 0):
            grey[i] = BOARD_BLACK
        else:
            grey[i] = BOARD_WHITE
    return t_out, grey


@numba.njit(cache=True)
def _box_hits(origin, d, lo, hi):
    n = d.shape[0]
    keep = np.zeros(n, dtype=np.bool_)
    for i in range(n):
        t0 = -np.inf
        t1 = np.inf
        for k in range(3):
            if d[i, k] != 0.0:
                ta = (lo[k] - origin[k]) / d[i, k]
                tb = (hi[k] - origin[k]) / d[i, k]
                if ta > tb:
                    ta, tb = tb, ta
                t0 = max(t0, ta)
                t1 = min(t1, tb)
            elif origin[k] < lo[k] or origin[k] > hi[k]:
                t1 = -np.inf
        keep[i] = t1 >= t0 and t1 > 0
    return keep


@numba.njit(cache=True)
def _box_hits_each(o, d, lo, hi):
    n = d.shape[0]
    keep = np.zeros(n, dtype=np.bool_)
    for i in range(n):
        keep[i] = _box_hits(o[i], d[i : i + 1], lo, hi)[0]
    return keep


def box_candidates_each(o, d, lo, hi, pad=0.5):
    """:func:`box_candidates` for rays with their own origins ``o (N, 3)``."""
    lo = np.asarray(lo, dtype=np.float64) - pad
    hi = np.asarray(hi, dtype=np.float64) + pad
    return np.flatnonzero(_box_hits_each(np.ascontiguousarray(o, dtype=np.float64), np.ascontiguousarray(d), lo, hi))


def box_candidates(origin, d, lo, hi, pad=0.5):
    """Indices of the rays from ``origin`` (3,) along ``d`` (N, 3) that meet the box ``[lo - pad, hi + pad]``."""
    lo = np.asarray(lo, dtype=np.float64) - pad
    hi = np.asarray(hi, dtype=np.float64) + pad
    return np.flatnonzero(_box_hits(np.asarray(origin, dtype=np.float64), np.ascontiguousarray(d), lo, hi))


def world_rays(camera, supersample, start, stop):
    """World-frame unit directions of samples ``start:stop`` of ``camera``."""
    d_cam = camera_frame_rays(camera, supersample)[start:stop]
    return _rows_times(d_cam, np.ascontiguousarray(camera.R, dtype=np.float64))  # R.T @ d_cam per row


@numba.njit(cache=True)
def _rows_times(a, R):
    """``a @ R`` for ``a (N, 3)``, each sum in index order (as ``np.einsum("ij,jk->ik")``, no BLAS threads)."""
    n = a.shape[0]
    out = np.empty((n, 3))
    for i in range(n):
        for k in range(3):
            acc = 0.0
            for j in range(3):
                acc += a[i, j] * R[j, k]
            out[i, k] = acc
    return out


_BG_CACHE = {}


def background_layer(camera, supersample, plate):
    """Backdrop + plate: per-sample colour ``(N, 3)`` and depth ``(N,)``.

    The plate is rotationally symmetric and the backdrop and light are fixed
    to the camera, so this layer is the same for every table angle: it is
    cached on the intrinsics and the pose's invariants under rotations about
    Z (``t`` and ``R @ e_z``).
    """
    key = (
        camera.K.tobytes(),
        camera.dist.tobytes(),
        camera.image_size,
        int(supersample),
        bool(plate),
        tuple(np.round(camera.t, 9)),
        tuple(np.round(camera.R[:, 2], 12)),
    )
    hit = _BG_CACHE.get(key)
    if hit is not None:
        return hit
    d_cam_all = camera_frame_rays(camera, supersample)
    light_world = LIGHT_CAM @ camera.R  # R.T @ l_cam
    centre = camera.center
    n = d_cam_all.shape[0]
    colour = np.empty((n, 3), dtype=np.float32)
    depth = np.full(n, np.inf)
    for s in range(0, n, CHUNK):
        d_cam = d_cam_all[s : s + CHUNK]
        c = backdrop(d_cam)
        if plate:
            d = world_rays(camera, supersample, s, s + CHUNK)
            t, albedo, normal = plate_hits(np.broadcast_to(centre, d.shape), d)
            m = np.isfinite(t)
            c[m] = shade(albedo[m], normal[m], light_world)
            depth[s : s + CHUNK] = t
        colour[s : s + CHUNK] = c
    colour.setflags(write=False)
    depth.setflags(write=False)
    _BG_CACHE.clear()
    _BG_CACHE[key] = (colour, depth)
    return colour, depth


def render(camera, *, supersample, board=None, specimen=None, plate=True):
    """Ray-cast the scene seen by ``camera``; float64 ``(H, W, 3)`` RGB in [0, ~255].

    ``board`` is ``(R_board, t_board, inner_corners, square, margin)`` in the
    world frame of ``camera``; ``specimen`` an object with ``_intersect(o, d)``
    returning ``(t, normals)`` and ``albedo(points)``.
    """
    bg_colour, bg_depth = background_layer(camera, supersample, plate)
    light_world = LIGHT_CAM @ camera.R  # R.T @ l_cam
    centre = camera.center
    out = bg_colour.astype(np.float64)
    t_best = bg_depth.copy()
    n = out.shape[0]
    for s in range(0, n, CHUNK):
        d = world_rays(camera, supersample, s, s + CHUNK)
        colour = out[s : s + CHUNK]  # views: written in place
        tb_chunk = t_best[s : s + CHUNK]
        if board is not None:
            o = np.broadcast_to(centre, d.shape)
            tb, ab, nb = board_hits(o, d, *board)
            tb = tb * (1.0 - 1e-9)  # the printed sheet lies on the plate top: it wins the tie
            closer = tb < tb_chunk
            if np.any(closer):
                colour[closer] = shade(ab[closer], nb[closer], light_world)
                tb_chunk[closer] = tb[closer]
        if specimen is not None:
            idx = box_candidates(centre, d, *specimen.bounds)
            if idx.size:
                di = d[idx]
                t, normal = specimen._intersect(np.broadcast_to(centre, di.shape), di, t_max=tb_chunk[idx])
                closer = t < tb_chunk[idx]
                if np.any(closer):
                    p = centre + t[closer, None] * di[closer]
                    colour[idx[closer]] = shade(specimen.albedo(p), normal[closer], light_world)
                    tb_chunk[idx[closer]] = t[closer]
    return downsample(out, camera.image_size, supersample)


def coverage(camera, specimen, *, supersample):
    """Fraction ``(H, W)`` float32 of each pixel's samples whose ray hits ``specimen``."""
    d_cam_all = camera_frame_rays(camera, supersample)
    centre = camera.center
    out = np.empty((d_cam_all.shape[0], 1))
    for s in range(0, d_cam_all.shape[0], CHUNK):
        d = world_rays(camera, supersample, s, s + CHUNK)
        hit = np.zeros(d.shape[0])
        idx = box_candidates(centre, d, *specimen.bounds)
        if idx.size:
            di = d[idx]
            hit[idx] = specimen._any_hit(np.broadcast_to(centre, di.shape), di)
        out[s : s + CHUNK, 0] = hit
    return downsample(out, camera.image_size, supersample)[:, :, 0].astype(np.float32)


def quantize(image, noise_sigma, rng):
    """Add Gaussian noise (grey levels) and round to uint8."""
    img = np.asarray(image, dtype=np.float64)
    if noise_sigma > 0:
        img = img + rng.normal(0.0, noise_sigma, size=img.shape)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


# ------------------------------------------------------------ star solids
# A star solid about the Z axis: {rho <= r(phi, z), z_lo <= z <= z_hi} with
# r(phi, z) = sum_k A_k * Z_k(z) * P_k(phi).  One row per term:
#   [A, ztype, z1, z2, ptype, m_or_kappa, mu]
# ztype 0: 1;  1: sin^2(pi (z - z1) / (z2 - z1)) on [z1, z2], else 0;
#       2: (1 - (z - z1) / (z2 - z1))^2 on [z1, z2], 1 below z1, 0 above z2.
# ptype 0: 1;  1: cos(m (phi - mu));  2: exp(kappa (cos(phi - mu) - 1)).


@numba.njit(cache=True)
def _star_r(phi, z, terms):
    r = 0.0
    r_phi = 0.0
    r_z = 0.0
    for k in range(terms.shape[0]):
        A = terms[k, 0]
        zt = terms[k, 1]
        z1 = terms[k, 2]
        z2 = terms[k, 3]
        pt = terms[k, 4]
        m = terms[k, 5]
        mu = terms[k, 6]
        if zt == 0.0:
            Z = 1.0
            dZ = 0.0
        elif zt == 1.0:
            if z <= z1 or z >= z2:
                continue
            L = z2 - z1
            a = np.pi * (z - z1) / L
            s = np.sin(a)
            Z = s * s
            dZ = 2.0 * s * np.cos(a) * np.pi / L
        else:
            if z >= z2:
                continue
            if z <= z1:
                Z = 1.0
                dZ = 0.0
            else:
                L = z2 - z1
                q = 1.0 - (z - z1) / L
                Z = q * q
                dZ = -2.0 * q / L
        if pt == 0.0:
            P = 1.0
            dP = 0.0
        elif pt == 1.0:
            P = np.cos(m * (phi - mu))
            dP = -m * np.sin(m * (phi - mu))
        else:
            c = np.cos(phi - mu)
            P = np.exp(m * (c - 1.0))
            dP = -m * np.sin(phi - mu) * P
        r += A * Z * P
        r_phi += A * Z * dP
        r_z += A * dZ * P
    return r, r_phi, r_z


@numba.njit(cache=True)
def _same_z(terms):
    """Per term, the index of the first term with the same sin^2 z profile (``ztype`` 1, same ``z1``, ``z2``), or -1."""
    n = terms.shape[0]
    src = np.full(n, -1, dtype=np.int64)
    for k in range(n):
        if terms[k, 1] == 1.0:
            for j in range(k):
                if src[j] == -1 and terms[j, 1] == 1.0 and terms[j, 2] == terms[k, 2] and terms[j, 3] == terms[k, 3]:
                    src[k] = j
                    break
    return src


@numba.njit(cache=True)
def _star_r_only(phi, z, terms, zsrc, zbuf):
    """``r(phi, z)`` alone: :func:`_star_r`'s first value (the same operations), without the derivatives.

    ``zsrc`` (:func:`_same_z`): a term whose z profile an earlier term has takes that term's value
    (the same number, kept in the scratch ``zbuf``) instead of computing the same sine again.
    """
    r = 0.0
    for k in range(terms.shape[0]):
        A = terms[k, 0]
        zt = terms[k, 1]
        z1 = terms[k, 2]
        z2 = terms[k, 3]
        pt = terms[k, 4]
        m = terms[k, 5]
        mu = terms[k, 6]
        if zt == 0.0:
            Z = 1.0
        elif zt == 1.0:
            if z <= z1 or z >= z2:
                continue
            j = zsrc[k]
            if j >= 0:
                Z = zbuf[j]
            else:
                L = z2 - z1
                a = np.pi * (z - z1) / L
                s = np.sin(a)
                Z = s * s
                zbuf[k] = Z
        else:
            if z >= z2:
                continue
            if z <= z1:
                Z = 1.0
            else:
                L = z2 - z1
                q = 1.0 - (z - z1) / L
                Z = q * q
        if pt == 0.0:
            P = 1.0
        elif pt == 1.0:
            P = np.cos(m * (phi - mu))
        else:
            c = np.cos(phi - mu)
            P = np.exp(m * (c - 1.0))
        r += A * Z * P
    return r


@numba.njit(cache=True)
def star_radius(phi, z, terms):
    """Vectorized ``r, r_phi, r_z`` at ``(N,)`` angles (rad) and heights (mm)."""
    n = phi.shape[0]
    r = np.empty(n)
    rp = np.empty(n)
    rz = np.empty(n)
    for i in range(n):
        r[i], rp[i], rz[i] = _star_r(phi[i], z[i], terms)
    return r, rp, rz


@numba.njit(cache=True)
def _star_f(ox, oy, oz, dx, dy, dz, t, terms, zsrc, zbuf):
    x = ox + t * dx
    y = oy + t * dy
    z = oz + t * dz
    return np.sqrt(x * x + y * y) - _star_r_only(np.arctan2(y, x), z, terms, zsrc, zbuf)


@numba.njit(cache=True)
def star_trace(o, d, t_max, terms, z_lo, z_hi, rmax, lip, hmin, tol, first=True):
    """First hit of rays with a star solid.

    Sphere tracing on ``f = rho - r(phi, z)`` with the Lipschitz bound
    ``lip`` (``f / lip`` never overshoots the surface), minimum step
    ``hmin``, then bisection to ``tol`` mm.  Returns ``t`` (inf: no hit) and
    the kind of hit: 0 none, 1 side, 2 top cap, 3 bottom cap.  ``first=False``
    (any hit, for shadow rays): the same steps, without the bisection, so
    ``t`` is finite for exactly the same rays but not refined.
    """
    n = d.shape[0]
    t_out = np.full(n, np.inf)
    kind = np.zeros(n, dtype=np.int8)
    zsrc = _same_z(terms)
    zbuf = np.zeros(terms.shape[0])
    for i in range(n):
        ox, oy, oz = o[i, 0], o[i, 1], o[i, 2]
        dx, dy, dz = d[i, 0], d[i, 1], d[i, 2]
        # slab z_lo <= z <= z_hi
        if abs(dz) < 1e-15:
            if oz < z_lo or oz > z_hi:
                continue
            t0 = -np.inf
            t1 = np.inf
        else:
            ta = (z_lo - oz) / dz
            tb = (z_hi - oz) / dz
            t0 = min(ta, tb)
            t1 = max(ta, tb)
        # bounding cylinder rho <= rmax
        a = dx * dx + dy * dy
        b = ox * dx + oy * dy
        c = ox * ox + oy * oy - rmax * rmax
        if a < 1e-15:
            if c > 0:
                continue
            c0 = -np.inf
            c1 = np.inf
        else:
            disc = b * b - a * c
            if disc <= 0:
                continue
            sq = np.sqrt(disc)
            c0 = (-b - sq) / a
            c1 = (-b + sq) / a
        tin = max(t0, c0, 0.0)
        tend = min(t1, c1, t_max[i])
        if tin >= tend:
            continue
        f = _star_f(ox, oy, oz, dx, dy, dz, tin, terms, zsrc, zbuf)
        if f <= 0.0:
            t_out[i] = tin
            if tin == t0 and t0 > c0:
                kind[i] = 2 if dz < 0 else 3
            else:
                kind[i] = 1
            continue
        t = tin
        while True:
            step = f / lip
            if step < hmin:
                step = hmin
            tn = t + step
            last = False
            if tn >= tend:
                tn = tend
                last = True
            fn = _star_f(ox, oy, oz, dx, dy, dz, tn, terms, zsrc, zbuf)
            if fn <= 0.0:
                if not first:
                    t_out[i] = tn
                    kind[i] = 1
                    break
                lo = t
                hi = tn
                while hi - lo > tol:
                    mid = 0.5 * (lo + hi)
                    if _star_f(ox, oy, oz, dx, dy, dz, mid, terms, zsrc, zbuf) <= 0.0:
                        hi = mid
                    else:
                        lo = mid
                t_out[i] = hi
                kind[i] = 1
                break
            if last:
                break
            t = tn
            f = fn
    return t_out, kind
