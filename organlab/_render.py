"""Private workers of :mod:`organlab.synthetic`: ray generation, ray casting, shading.

Everything here works on flat arrays of rays (origins and unit directions in
the world frame, mm).  The public wrappers live in :mod:`organlab.synthetic`.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from .camera import Camera

# Lighting fixed relative to the camera: mostly ambient, mild diffuse.
AMBIENT = 0.82
DIFFUSE = 0.22
# Unit vector toward the light, camera frame (upper left, behind the camera).
LIGHT_CAM = np.array([-0.35, -0.6, -1.0]) / np.linalg.norm([-0.35, -0.6, -1.0])

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
        # Camera.rays with the identity pose gives camera-frame directions.
        dirs[s : s + CHUNK] = cam.rays(pix[s : s + CHUNK])[1]
    dirs.setflags(write=False)
    return dirs


def camera_frame_rays(camera, supersample):
    """Camera-frame unit directions of all sub-pixel samples of ``camera`` (cached)."""
    return _camera_frame_rays(
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
    lam = np.abs(normals @ light_world)
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
    n = d.shape[0]
    t = np.full(n, np.inf)
    albedo = np.zeros((n, 3))
    normal = np.zeros((n, 3))
    with np.errstate(divide="ignore", invalid="ignore"):
        # top disk z = 0, seen from above
        tt = -o[:, 2] / d[:, 2]
        p = o + tt[:, None] * d
        rho = np.hypot(p[:, 0], p[:, 1])
        top = (tt > 0) & (rho <= PLATE_RADIUS) & (o[:, 2] > 0)
        t[top] = tt[top]
        g = 128.0 + 10.0 * np.cos(2 * np.pi * rho[top] / 24.0)
        albedo[top] = np.stack([g, g, g * 0.97], axis=1)
        normal[top] = [0.0, 0.0, 1.0]
        # side wall, rho = R, PLATE_BOTTOM <= z <= 0
        a = d[:, 0] ** 2 + d[:, 1] ** 2
        b = o[:, 0] * d[:, 0] + o[:, 1] * d[:, 1]
        c = o[:, 0] ** 2 + o[:, 1] ** 2 - PLATE_RADIUS**2
        disc = b * b - a * c
        ts = (-b - np.sqrt(disc)) / a
        zs = o[:, 2] + ts * d[:, 2]
        side = (disc > 0) & (ts > 0) & (zs <= 0) & (zs >= PLATE_BOTTOM) & (ts < t)
    t[side] = ts[side]
    albedo[side] = [70.0, 70.0, 72.0]
    ps = o[side] + ts[side, None] * d[side]
    normal[side] = np.stack([ps[:, 0], ps[:, 1], np.zeros(len(ps))], axis=1) / PLATE_RADIUS
    return t, albedo, normal


def board_hits(o, d, R_board, t_board, inner_corners, square, margin, *, black=28.0, white=212.0):
    """Hits of rays with a printed checkerboard (a zero-thickness rectangle).

    The board frame has the inner corners at ``(i * square, j * square, 0)``;
    square ``(a, b)`` (``a = 0..cols``, ``b = 0..rows``) spans
    ``x in [(a - 1) s, a s]``, ``y in [(b - 1) s, b s]`` and is black when
    ``a + b`` is even, so the corner squares at ``x < 0`` are black and those
    at the far ``+x`` end are white (10 x 7 squares for 9 x 6 inner corners).
    """
    n_x, n_y = inner_corners
    s = float(square)
    normal_w = R_board[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = d @ normal_w
        t = ((t_board - o) @ normal_w) / denom
    t = np.where(np.isfinite(t) & (t > 0), t, np.inf)
    hit = np.isfinite(t)
    p = o[hit] + t[hit, None] * d[hit]
    local = (p - t_board) @ R_board  # R_board.T @ (p - t_board)
    x, y = local[:, 0], local[:, 1]
    lo_x, hi_x = -s - margin, n_x * s + margin
    lo_y, hi_y = -s - margin, n_y * s + margin
    on = (x >= lo_x) & (x <= hi_x) & (y >= lo_y) & (y <= hi_y)
    a = np.floor(x / s).astype(np.int64) + 1
    b = np.floor(y / s).astype(np.int64) + 1
    in_squares = (a >= 0) & (a <= n_x) & (b >= 0) & (b <= n_y)
    is_black = in_squares & ((a + b) % 2 == 0)
    g = np.where(is_black, black, white)
    idx = np.flatnonzero(hit)
    t_out = np.full(d.shape[0], np.inf)
    t_out[idx[on]] = t[idx[on]]
    albedo = np.zeros((d.shape[0], 3))
    albedo[idx[on]] = g[on, None]
    normal = np.broadcast_to(normal_w, d.shape)
    return t_out, albedo, normal


def render(camera, *, supersample, board=None, specimen=None, plate=True):
    """Ray-cast the scene seen by ``camera``; float64 ``(H, W, 3)`` RGB in [0, ~255].

    ``board`` is ``(R_board, t_board, inner_corners, square, margin)`` in the
    world frame of ``camera``; ``specimen`` an object with ``_intersect(o, d)``
    returning ``(t, normals)`` and ``albedo(points)``.
    """
    d_cam_all = camera_frame_rays(camera, supersample)
    R = camera.R
    light_world = LIGHT_CAM @ R  # R.T @ l_cam
    centre = camera.center
    out = np.empty((d_cam_all.shape[0], 3))
    for s in range(0, d_cam_all.shape[0], CHUNK):
        d_cam = d_cam_all[s : s + CHUNK]
        d = d_cam @ R
        o = np.broadcast_to(centre, d.shape)
        colour = backdrop(d_cam)
        t_best = np.full(d.shape[0], np.inf)
        layers = []
        if plate:
            layers.append(plate_hits(o, d))
        if board is not None:
            # the printed sheet lies on the plate top: it wins the tie
            tb, ab, nb = board_hits(o, d, *board)
            layers.append((tb * (1.0 - 1e-9), ab, nb))
        for t, albedo, normal in layers:
            closer = t < t_best
            if np.any(closer):
                colour[closer] = shade(albedo[closer], normal[closer], light_world)
                t_best[closer] = t[closer]
        if specimen is not None:
            t, normal = specimen._intersect(o, d, t_max=t_best)
            closer = t < t_best
            if np.any(closer):
                p = o[closer] + t[closer, None] * d[closer]
                colour[closer] = shade(specimen.albedo(p), normal[closer], light_world)
                t_best[closer] = t[closer]
        out[s : s + CHUNK] = colour
    return downsample(out, camera.image_size, supersample)


def coverage(camera, specimen, *, supersample):
    """Fraction ``(H, W)`` float32 of each pixel's samples whose ray hits ``specimen``."""
    d_cam_all = camera_frame_rays(camera, supersample)
    R = camera.R
    centre = camera.center
    out = np.empty((d_cam_all.shape[0], 1))
    for s in range(0, d_cam_all.shape[0], CHUNK):
        d = d_cam_all[s : s + CHUNK] @ R
        o = np.broadcast_to(centre, d.shape)
        t, _ = specimen._intersect(o, d, t_max=None)
        out[s : s + CHUNK, 0] = np.isfinite(t)
    return downsample(out, camera.image_size, supersample)[:, :, 0].astype(np.float32)


def quantize(image, noise_sigma, rng):
    """Add Gaussian noise (grey levels) and round to uint8."""
    img = np.asarray(image, dtype=np.float64)
    if noise_sigma > 0:
        img = img + rng.normal(0.0, noise_sigma, size=img.shape)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)
