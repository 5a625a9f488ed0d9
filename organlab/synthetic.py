"""Synthetic sessions: a known camera, a known specimen, rendered images.

Every image is ray cast through the full :class:`~organlab.camera.Camera`
model (``Camera.rays`` of supersampled sub-pixel positions, box filter), so
the lens distortion in the images is exactly the one ``Camera.project``
models, and sub-pixel methods (corner detection, silhouettes) can be tested
against the truth.

Scene (world frame = turntable frame, mm, Z up along the table axis):

* a turntable plate, a grey disk of radius 125 mm whose top is ``z = 0``,
  rotationally symmetric so it looks the same at every table angle;
* a dark backdrop fixed to the camera (a function of the ray direction in the
  camera frame), so background frames match the views;
* lighting fixed to the camera, mostly ambient with mild diffuse shading;
* a checkerboard printed on a zero-thickness sheet, and a specimen
  (:class:`AAAPhantom`, :class:`GroovedSpecimen`, :class:`Sphere`,
  :class:`Cylinder`) standing on the plate.

``python -m organlab.synthetic OUT --seed 0`` writes a complete session
folder in the ``organlab.session/1`` format, with ``truth.json`` beside it.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from . import _render
from .camera import Camera, _as_points, rot_z
from .session import FORMAT, Pattern, write_json

__all__ = [
    "DEFAULT_PATTERN",
    "default_camera",
    "board_object_points",
    "board_outline",
    "turntable_board_pose",
    "turntable_board_points",
    "intrinsic_board_poses",
    "render_board",
    "tissue_albedo",
    "Specimen",
    "Sphere",
    "Cylinder",
    "AAAPhantom",
    "GroovedSpecimen",
    "make_specimen",
    "render_view",
    "render_masks",
    "make_session",
    "with_true_cameras",
    "DEFAULT_ROI",
]

DEFAULT_PATTERN = Pattern((9, 6), 20.0)
#: White margin around the squares of the synthetic board, mm.
BOARD_MARGIN = 15.0
#: Centre of the board (x, y), mm, as it lies on the table at angle 0.
BOARD_CENTER_XY = (15.0, -10.0)


# ------------------------------------------------------------------ camera
def default_camera(image_size=(640, 480)):
    """The true camera of synthetic sessions, posed at table angle 0.

    640 x 480 px, ``fx = 812.4``, ``fy = 809.7`` px, principal point
    ``(324.7, 236.1)``, strong barrel distortion ``k1 = -0.3``, ``k2 = 0.1``
    (with small ``p1``, ``p2``; ``k3 = 0``; no skew).  The camera centre is
    about 505 mm from the table axis and 350 mm above the table, looking
    down at the specimen.  Other image sizes scale the intrinsics (same field
    of view, same distortion in normalized coordinates).

    Parameters
    ----------
    image_size : (2,) int
        ``(width, height)`` in pixels; the aspect ratio should stay 4:3.

    Returns
    -------
    Camera
        ``R``, ``t`` = ``R_cam``, ``t_cam``: world (turntable frame at angle
        0) to camera, mm.
    """
    w, h = (int(v) for v in image_size)
    if w <= 0 or h <= 0:
        raise ValueError(f"image_size must be (width, height) > 0, got {image_size}")
    sx, sy = w / 640.0, h / 480.0
    fx, fy = 812.4 * sx, 809.7 * sy
    cx = (324.7 + 0.5) * sx - 0.5
    cy = (236.1 + 0.5) * sy - 0.5
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    dist = np.array([-0.30, 0.10, 1.2e-3, -0.8e-3, 0.0])
    # Camera centre: azimuth a little off -Y, above the roi; look at the axis.
    az = np.deg2rad(-90.0 + 8.0)
    centre = np.array([505.0 * np.cos(az), 505.0 * np.sin(az), 350.0])
    target = np.array([0.0, 0.0, 88.0])
    R = _look_at(centre, target, roll_deg=1.5)
    t = -R @ centre
    return Camera(K, dist, R, t, (w, h))


def _look_at(centre, target, *, roll_deg=0.0, up=(0.0, 0.0, 1.0)):
    """World-to-camera rotation of a camera at ``centre`` looking at ``target`` (OpenCV axes)."""
    z = np.asarray(target, float) - np.asarray(centre, float)
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])  # rows: camera axes in world coordinates
    return rot_z(roll_deg) @ R  # roll about the optical axis


# ------------------------------------------------------------------- board
def _as_pattern(pattern):
    if pattern is None:
        return DEFAULT_PATTERN
    if isinstance(pattern, Pattern):
        p = pattern
    elif isinstance(pattern, dict):
        p = Pattern(tuple(pattern["inner_corners"]), float(pattern["square_size"]))
    else:
        ic, sq = pattern
        p = Pattern(tuple(ic), float(sq))
    if len(p.inner_corners) != 2 or min(p.inner_corners) < 2 or not p.square_size > 0:
        raise ValueError(f"pattern needs inner_corners (cols >= 2, rows >= 2) and square_size > 0, got {p}")
    return Pattern(tuple(int(v) for v in p.inner_corners), float(p.square_size))


def board_object_points(pattern=None):
    """Inner corners of the board in the board frame.

    The board frame: x along the long side (``inner_corners[0]``) from the end
    whose corner squares are black toward the end whose corner squares are
    white, y along the other side, z = x cross y (the printed side's normal),
    origin at the first inner corner.  Corner ``(i, j)`` is at
    ``(i * s, j * s, 0)``, listed with ``i`` fastest (OpenCV's object-point
    order).

    Parameters
    ----------
    pattern : Pattern or ((cols, rows), square_size), optional
        Default :data:`DEFAULT_PATTERN` (9 x 6 inner corners, 20 mm).

    Returns
    -------
    (cols * rows, 3) float64, mm, board frame
    """
    p = _as_pattern(pattern)
    nx, ny = p.inner_corners
    j, i = np.mgrid[0:ny, 0:nx]
    return np.stack([i.ravel(), j.ravel(), np.zeros(nx * ny)], axis=1) * p.square_size


def board_outline(pattern=None, *, margin=BOARD_MARGIN):
    """The four corners of the printed sheet (squares + white margin), board frame, ``(4, 3)`` mm."""
    p = _as_pattern(pattern)
    nx, ny = p.inner_corners
    s = p.square_size
    lo_x, hi_x = -s - margin, nx * s + margin
    lo_y, hi_y = -s - margin, ny * s + margin
    return np.array([[lo_x, lo_y, 0], [hi_x, lo_y, 0], [hi_x, hi_y, 0], [lo_x, hi_y, 0]], dtype=np.float64)


def _board_center(pattern):
    p = _as_pattern(pattern)
    nx, ny = p.inner_corners
    return np.array([(nx - 1) / 2 * p.square_size, (ny - 1) / 2 * p.square_size, 0.0])


def turntable_board_pose(pattern=None, *, center_xy=BOARD_CENTER_XY):
    """Board-to-world pose of the board lying on the table at angle 0.

    The board lies printed side up on the table top (``z = 0``), its long
    side along +X (black-corner end toward -X, as the session format's world
    frame requires), its centre at ``center_xy``, off the table axis so that
    a turntable fit has to find the axis.

    Returns
    -------
    R_board : (3, 3) float64
        Identity (board axes = world axes).
    t_board : (3,) float64, mm
        ``X_world = R_board @ X_board + t_board``.
    """
    c = _board_center(pattern)
    return np.eye(3), np.array([center_xy[0] - c[0], center_xy[1] - c[1], 0.0])


def turntable_board_points(angle_deg, pattern=None, *, center_xy=BOARD_CENTER_XY):
    """World positions (table frame at angle 0 = world) of the inner corners at table angle ``angle_deg``.

    The board is fixed on the table, so at angle ``a`` its points are
    ``Rz(a) @ X`` with ``X`` their positions at angle 0.

    Returns
    -------
    (N, 3) float64, mm, world frame, OpenCV object-point order
    """
    R, t = turntable_board_pose(pattern, center_xy=center_xy)
    X = board_object_points(pattern) @ R.T + t
    return X @ rot_z(angle_deg).T


def intrinsic_board_poses(camera, n, *, pattern=None, seed=0, max_tilt_deg=45.0):
    """Board poses in front of the camera for intrinsic calibration images.

    Random but deterministic from ``seed``: tilts up to ``max_tilt_deg``,
    in-plane rotations up to 25 deg, the squares covering 16-45 % of the
    image (the sheet about 1/4 to 2/3), every other pose pushed toward an
    image corner (cycling through the four) where the distortion is strong.
    Every pose keeps all the squares inside the image (the white margin may
    be cut by the image border) and the sheet's normal within 55 deg of the
    line of sight.

    Parameters
    ----------
    camera : Camera
        Only the intrinsics are used.
    n : int
        Number of poses.
    pattern : Pattern or ((cols, rows), square_size), optional
    seed : int
    max_tilt_deg : float
        Largest angle between the sheet and the image plane.

    Returns
    -------
    list of ((3, 3) float64, (3,) float64)
        Board-to-camera poses ``X_cam = R @ X_board + t``, mm.
    """
    if n < 0:
        raise ValueError(f"n must be >= 0, got {n}")
    p = _as_pattern(pattern)
    cam0 = camera.with_pose(np.eye(3), np.zeros(3))
    w, h = cam0.image_size
    rng = np.random.default_rng([int(seed), 7919])
    corners = board_object_points(p)
    squares = board_outline(p, margin=0.0)
    centre = _board_center(p)
    R_face = np.diag([1.0, -1.0, -1.0])  # printed side toward the camera, board +x to the right
    poses = []
    tries = 0
    while len(poses) < n:
        tries += 1
        if tries > 20000:
            raise RuntimeError("could not place the intrinsic boards; is the camera's field of view sensible?")
        k = len(poses)
        roll = np.deg2rad(rng.uniform(-25, 25))
        tilt = np.deg2rad(rng.uniform(10, max_tilt_deg) if k % 4 else rng.uniform(0, 20))
        axis_angle = rng.uniform(0, 2 * np.pi)
        axis = np.array([np.cos(axis_angle), np.sin(axis_angle), 0.0])
        R = _axis_angle(axis, tilt) @ R_face @ _axis_angle([0, 0, 1.0], roll)
        if k % 2 == 1:  # toward an image corner (strong distortion), cycling through the four
            qx, qy = ((1, 1), (-1, 1), (-1, -1), (1, -1))[(k // 2) % 4]
            target = np.array([w / 2 + qx * w * rng.uniform(0.2, 0.3), h / 2 + qy * h * rng.uniform(0.2, 0.3)])
        else:
            target = np.array([w / 2 + w * rng.uniform(-0.12, 0.12), h / 2 + h * rng.uniform(-0.12, 0.12)])
        dist = rng.uniform(380, 680) * (cam0.K[0, 0] / 812.4) / (w / 640.0)
        ray = cam0.rays(target[None])[1][0]
        t = dist * ray - R @ centre
        cam_pts = corners @ R.T + t
        out_pts = squares @ R.T + t
        if np.any(cam_pts[:, 2] <= 50) or np.any(out_pts[:, 2] <= 50):
            continue
        uvo = cam0.project(out_pts)
        # every square inside the image (the white margin may be cut by the border)
        if not (np.all(uvo[:, 0] >= 2) and np.all(uvo[:, 0] <= w - 3) and np.all(uvo[:, 1] >= 2) and np.all(uvo[:, 1] <= h - 3)):
            continue
        # squares cover 16-45 % of the image (the sheet about 1/4 to 2/3)
        area = 0.5 * abs(np.dot(uvo[:, 0], np.roll(uvo[:, 1], 1)) - np.dot(uvo[:, 1], np.roll(uvo[:, 0], 1)))
        if not 0.16 <= area / (w * h) <= 0.45:
            continue
        normal = R[:, 2]
        c = R @ centre + t
        if abs(normal @ c) / np.linalg.norm(c) < np.cos(np.deg2rad(55)):
            continue
        poses.append((R, t))
    return poses


def _axis_angle(axis, angle):
    axis = np.asarray(axis, float)
    axis = axis / np.linalg.norm(axis)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


def render_board(
    camera,
    R_board,
    t_board,
    pattern=None,
    *,
    margin=BOARD_MARGIN,
    supersample=4,
    table=True,
    noise_sigma=0.0,
    seed=None,
    grey=True,
):
    """Render the printed checkerboard seen by ``camera``.

    Parameters
    ----------
    camera : Camera
        Full camera; its pose maps the world frame to the camera.
    R_board, t_board : (3, 3), (3,) float64
        Board-to-world pose, mm: ``X_world = R_board @ X_board + t_board``
        (board frame of :func:`board_object_points`).  For a board held in
        front of the camera, pass ``camera.with_pose(np.eye(3), np.zeros(3))``
        and the board-to-camera pose.
    pattern : Pattern or ((cols, rows), square_size), optional
    margin : float, mm
        White margin around the squares.
    supersample : int
        Sub-pixel samples per axis (box filter).
    table : bool
        Show the turntable plate (world frame) behind the board; the dark
        backdrop is always there.
    noise_sigma : float
        Gaussian pixel noise, grey levels.
    seed : int or sequence of int, optional
        Seed of the noise.
    grey : bool
        Return a grey ``(H, W)`` image, else RGB ``(H, W, 3)``.

    Returns
    -------
    image : (H, W) or (H, W, 3) uint8
    """
    p = _as_pattern(pattern)
    R_board = np.asarray(R_board, dtype=np.float64)
    t_board = np.asarray(t_board, dtype=np.float64).ravel()
    if R_board.shape != (3, 3) or t_board.shape != (3,):
        raise ValueError("R_board must be (3, 3) and t_board (3,)")
    if int(supersample) < 1:
        raise ValueError(f"supersample must be >= 1, got {supersample}")
    board = (R_board, t_board, p.inner_corners, p.square_size, float(margin))
    img = _render.render(camera, supersample=int(supersample), board=board, plate=table)
    if grey:
        img = np.einsum("ijk,k->ij", img, np.array([0.299, 0.587, 0.114]))
    return _render.quantize(img, noise_sigma, np.random.default_rng(seed))


# --------------------------------------------------------------- specimens
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
        p = _as_points(points)
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
        o = _as_points(origins, "origins")
        d = _as_points(directions, "directions")
        if o.shape != d.shape:
            o = np.broadcast_to(o, d.shape)
        return self._intersect(o, d, t_max=None)

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

    def _intersect(self, o, d, t_max=None):
        n = len(d)
        o = np.ascontiguousarray(o, dtype=np.float64)
        d = np.ascontiguousarray(d, dtype=np.float64)
        t, kind = _render.star_trace(
            o, d, _tmax(t_max, n), self.terms, self.z_lo, self.z_hi, self.r_max, self.lip, 0.02, 1e-5
        )
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

    def __init__(self, *, name="aaa"):
        z_b, z_top = 32.0, 172.0
        r_aorta = 12.6
        terms = [
            [r_aorta, 0, 0, 0, 0, 0, 0],
            [1.6, 2, z_b, z_b + 22.0, 0, 0, 0],  # flare toward the bifurcation
            [-0.8, 1, z_b + 90.0, z_top + 60.0, 0, 0, 0],  # gentle taper toward the top
            [13.4, 1, 42.0, 158.0, 0, 0, 0],  # fusiform aneurysm
            [2.4, 1, 42.0, 158.0, 1, 1, 0.6],  # anterior asymmetry
            [2.0, 1, 70.0, 130.0, 2, 3.0, 0.9],  # a bleb, left-anterior
            [0.5, 1, 42.0, 158.0, 1, 2, 0.3],  # slight ovality
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


def make_specimen(name):
    """The specimen called ``name``: ``"aaa"`` (:class:`AAAPhantom`) or ``"grooved"`` (:class:`GroovedSpecimen`)."""
    if isinstance(name, Specimen):
        return name
    if name == "aaa":
        return AAAPhantom()
    if name == "grooved":
        return GroovedSpecimen()
    raise ValueError(f"unknown specimen {name!r}; choose 'aaa' or 'grooved'")


# --------------------------------------------------------------- rendering
def render_view(specimen, camera, *, supersample=3, noise_sigma=0.0, seed=None, table=True):
    """Render the specimen on the turntable seen by ``camera``.

    Parameters
    ----------
    specimen : Specimen or str or None
        ``None`` renders the empty scene (a background frame).
    camera : Camera
        Pose world (table frame) to camera, e.g. ``default_camera().at_table_angle(a)``.
    supersample : int
        Sub-pixel samples per axis (box filter).
    noise_sigma : float
        Gaussian pixel noise, grey levels.
    seed : int or sequence of int, optional
        Seed of the noise.
    table : bool
        Show the turntable plate.

    Returns
    -------
    image : (H, W, 3) uint8
        RGB.
    """
    if int(supersample) < 1:
        raise ValueError(f"supersample must be >= 1, got {supersample}")
    spec = None if specimen is None else make_specimen(specimen)
    img = _render.render(camera, supersample=int(supersample), specimen=spec, plate=table)
    return _render.quantize(img, noise_sigma, np.random.default_rng(seed))


def render_masks(specimen, cameras, *, supersample=4):
    """Anti-aliased silhouettes: the fraction of each pixel covered by the specimen.

    Parameters
    ----------
    specimen : Specimen or str
    cameras : Camera or sequence of Camera
    supersample : int
        Sub-pixel samples per axis; coverage is a multiple of ``1 / supersample**2``.

    Returns
    -------
    masks : (V, H, W) float32 in [0, 1]
        One per camera (``(H, W)`` for a single camera).
    """
    spec = make_specimen(specimen)
    single = isinstance(cameras, Camera)
    cams = [cameras] if single else list(cameras)
    if int(supersample) < 1:
        raise ValueError(f"supersample must be >= 1, got {supersample}")
    out = np.stack([_render.coverage(c, spec, supersample=int(supersample)) for c in cams])
    return out[0] if single else out


# ----------------------------------------------------------------- session
DEFAULT_ROI = {"min": [-70.0, -70.0, 0.0], "max": [70.0, 70.0, 200.0]}


def _write_image(path, image, *, fmt="png", quality=95):
    import cv2

    path.parent.mkdir(parents=True, exist_ok=True)
    img = image if image.ndim == 2 else image[:, :, ::-1]
    if fmt == "png":
        # noisy images: Huffman-only deflate is often smaller; keep the smaller
        bufs = [
            cv2.imencode(".png", img, [cv2.IMWRITE_PNG_COMPRESSION, 9, cv2.IMWRITE_PNG_STRATEGY, strategy])[1]
            for strategy in (cv2.IMWRITE_PNG_STRATEGY_DEFAULT, cv2.IMWRITE_PNG_STRATEGY_HUFFMAN_ONLY)
        ]
        buf = min(bufs, key=len)
    else:
        params = [cv2.IMWRITE_JPEG_QUALITY, int(quality), cv2.IMWRITE_JPEG_SAMPLING_FACTOR, cv2.IMWRITE_JPEG_SAMPLING_FACTOR_444]
        buf = cv2.imencode(".jpg", img, params)[1]
    path.write_bytes(buf.tobytes())


def _remove_previous_images(out):
    """Delete the images of a session this generator wrote before in ``out`` (and only those)."""
    sj = out / "session.json"
    if not sj.is_file():
        return
    try:
        old = json.loads(sj.read_text(encoding="utf-8"))
    except (ValueError, UnicodeDecodeError):
        return
    if not isinstance(old, dict) or not isinstance(old.get("synthetic"), dict):
        return  # not ours: leave it alone
    cal = old.get("calibration") or {}
    names = list(cal.get("intrinsic_images", [])) + [e.get("image") for e in cal.get("turntable_images", [])]
    names += list(old.get("background_images", [])) + [v.get("image") for v in old.get("views", [])]
    root = out.resolve()
    for name in names:
        if isinstance(name, str):
            p = (out / name).resolve()
            if p.is_file() and root in p.parents and p.suffix.lower() in (".png", ".jpg", ".jpeg"):
                p.unlink()


def make_session(
    out_dir,
    *,
    seed=0,
    specimen="aaa",
    image_size=(640, 480),
    n_views=36,
    n_intrinsic=15,
    n_turntable=10,
    n_background=20,
    turntable_step_deg=20.0,
    supersample=3,
    board_supersample=4,
    noise_sigma=1.5,
    include_camera=True,
    include_poses=True,
    views_only=False,
    view_format="png",
    background_format="png",
    jpeg_quality=95,
    roi=None,
    name=None,
):
    """Write a complete synthetic session folder (``organlab.session/1``) and its ``truth.json``.

    Deterministic from ``seed`` (board poses and pixel noise; the scene is fixed).

    Parameters
    ----------
    out_dir : str or Path
        The session folder (created).  Images that a previous run of this
        generator listed in its ``session.json`` there are deleted first;
        other files are left alone.
    seed : int
    specimen : {"aaa", "grooved"} or Specimen
    image_size : (2,) int
        ``(width, height)``; the intrinsics scale with it (:func:`default_camera`).
    n_views : int
        Views of the specimen, every ``360 / n_views`` degrees from 0.
    n_intrinsic, n_turntable, n_background : int
        Numbers of intrinsic board images, turntable board images (at
        ``0, turntable_step_deg, ...``) and empty-scene frames.
    supersample, board_supersample : int
        Sub-pixel samples per axis for the views/backgrounds and the board images.
    noise_sigma : float
        Gaussian pixel noise, grey levels, independent per image.
    include_camera, include_poses : bool
        Write the true intrinsics (``camera``) and the true per-view poses in ``session.json``.
    views_only : bool
        No calibration images (needs ``include_camera`` and ``include_poses``).
    view_format, background_format : {"png", "jpg"}
        File format of the colour images (calibration images are grey PNG).
    jpeg_quality : int
    roi : dict, optional
        ``{"min": [...], "max": [...]}``, mm; default ``[-70, 70] x [-70, 70] x [0, 200]``.
    name : str, optional

    Returns
    -------
    dict
        The truth (also written to ``truth.json``): ``camera`` (``K``,
        ``dist``, ``image_size``, ``R_cam``, ``t_cam``, ``center``),
        ``specimen``, ``volume_mm3``, ``views`` (``angle_deg``, ``R``, ``t``),
        ``board`` poses, ``seed``, ``noise_sigma``, ``session_json`` (the
        dict written).
    """
    out = Path(out_dir)
    for label, value in (("n_views", n_views), ("n_intrinsic", n_intrinsic), ("n_turntable", n_turntable), ("n_background", n_background)):
        if int(value) < 0:
            raise ValueError(f"{label} must be >= 0, got {value}")
    if views_only:
        if not (include_camera and include_poses):
            raise ValueError("views_only=True needs include_camera=True and include_poses=True (nothing to calibrate from)")
        n_intrinsic = n_turntable = 0
    if not include_camera and n_intrinsic < 3:
        raise ValueError("without include_camera the session needs n_intrinsic >= 3 board images to calibrate from")
    if not include_poses and n_views and n_turntable < 2:
        raise ValueError("without include_poses the session needs n_turntable >= 2 board images to fit the turntable")
    for label, fmt in (("view_format", view_format), ("background_format", background_format)):
        if fmt not in ("png", "jpg"):
            raise ValueError(f"{label} must be 'png' or 'jpg', got {fmt!r}")
    spec = make_specimen(specimen)
    pattern = DEFAULT_PATTERN
    cam = default_camera(image_size)
    size = cam.image_size
    out.mkdir(parents=True, exist_ok=True)
    _remove_previous_images(out)

    def rng(kind, i):
        return np.random.default_rng([int(seed), kind, i])

    # intrinsic calibration images: board held in front of the camera
    cam0 = cam.with_pose(np.eye(3), np.zeros(3))
    intrinsic = []
    poses_in = intrinsic_board_poses(cam, n_intrinsic, pattern=pattern, seed=seed) if n_intrinsic else []
    for i, (Rb, tb) in enumerate(poses_in):
        img = render_board(cam0, Rb, tb, pattern, supersample=board_supersample, table=False, noise_sigma=0.0)
        rel = f"calibration/intrinsics/{i:02d}.png"
        _write_image(out / rel, _render.quantize(img, noise_sigma, rng(1, i)))
        intrinsic.append(rel)

    # turntable images: board lying on the table
    Rb0, tb0 = turntable_board_pose(pattern)
    turntable = []
    for i in range(int(n_turntable)):
        a = float(i * turntable_step_deg)
        img = render_board(cam.at_table_angle(a), Rb0, tb0, pattern, supersample=board_supersample, table=True)
        rel = f"calibration/turntable/{int(round(a)):03d}.png"
        _write_image(out / rel, _render.quantize(img, noise_sigma, rng(2, i)))
        turntable.append({"image": rel, "angle_deg": a})

    # background frames: the empty scene
    background = []
    if n_background:
        empty = _render.render(cam, supersample=int(supersample))
        for i in range(int(n_background)):
            rel = f"background/{i:02d}.{background_format}"
            _write_image(out / rel, _render.quantize(empty, noise_sigma, rng(3, i)), fmt=background_format, quality=jpeg_quality)
            background.append(rel)

    # views of the specimen
    views = []
    views_truth = []
    for i in range(int(n_views)):
        a = float(360.0 * i / n_views)
        cam_a = cam.at_table_angle(a)
        img = _render.render(cam_a, supersample=int(supersample), specimen=spec)
        rel = f"views/{int(round(a * 10)):04d}.{view_format}" if a != int(a) else f"views/{int(a):03d}.{view_format}"
        _write_image(out / rel, _render.quantize(img, noise_sigma, rng(4, i)), fmt=view_format, quality=jpeg_quality)
        entry = {"image": rel, "angle_deg": a}
        if include_poses:
            entry["pose"] = {"R": cam_a.R.tolist(), "t": cam_a.t.tolist()}
        views.append(entry)
        views_truth.append({"angle_deg": a, "R": cam_a.R.tolist(), "t": cam_a.t.tolist()})

    roi = DEFAULT_ROI if roi is None else roi
    session = {
        "format": FORMAT,
        "name": name or out.resolve().name,
        "units": "mm",
        "image_size": list(size),
        "pattern": {"type": "checkerboard", "inner_corners": list(pattern.inner_corners), "square_size": pattern.square_size},
        "calibration": {"intrinsic_images": intrinsic, "turntable_images": turntable},
        "background_images": background,
        "views": views,
        "roi": {"min": [float(v) for v in roi["min"]], "max": [float(v) for v in roi["max"]]},
        "reference": {"volume_mm3": spec.volume},
        "synthetic": {"generator": "organlab.synthetic", "seed": int(seed), "truth": "truth.json"},
    }
    if include_camera:
        session["camera"] = {"K": cam.K.tolist(), "dist": cam.dist.tolist()}
    truth = {
        "camera": {
            "K": cam.K.tolist(),
            "dist": cam.dist.tolist(),
            "image_size": list(size),
            "R_cam": cam.R.tolist(),
            "t_cam": cam.t.tolist(),
            "center": cam.center.tolist(),
        },
        "specimen": spec.name,
        "volume_mm3": spec.volume,
        "views": views_truth,
        "board": {
            "inner_corners": list(pattern.inner_corners),
            "square_size": pattern.square_size,
            "margin": BOARD_MARGIN,
            "turntable_R_board": Rb0.tolist(),
            "turntable_t_board": tb0.tolist(),
            "intrinsic_poses": [{"R": R.tolist(), "t": t.tolist()} for R, t in poses_in],
            "note": "X_world = R_board @ X_board + t_board (turntable, angle 0); intrinsic poses are board to camera",
        },
        "seed": int(seed),
        "noise_sigma": float(noise_sigma),
        "supersample": int(supersample),
        "board_supersample": int(board_supersample),
        "formats": {"views": view_format, "background": background_format, "jpeg_quality": int(jpeg_quality), "calibration": "png (grey)"},
    }
    write_json(out / "session.json", session)
    write_json(out / "truth.json", truth)
    truth["session_json"] = session
    return truth


def with_true_cameras(session_dir, dest):
    """Copy a synthetic session, giving the true camera and view poses in ``session.json``.

    The copy skips any calibration (``calibration.json``, check figures): it
    reconstructs with the cameras that rendered the images, from ``truth.json``,
    so a result with calibrated cameras can be compared with it.

    Parameters
    ----------
    session_dir : str or Path
        A session written by :func:`make_session` (has ``truth.json``).
    dest : str or Path
        The new session folder (must not exist).

    Returns
    -------
    Path
        ``dest``.
    """
    import shutil

    src, dest = Path(session_dir), Path(dest)
    if not (src / "truth.json").is_file():
        raise ValueError(f"{src}: no truth.json; only sessions made by organlab.synthetic have true cameras")
    shutil.copytree(src, dest, ignore=shutil.ignore_patterns("calibration.json", "calibration_check"))
    truth = json.loads((dest / "truth.json").read_text())
    doc = json.loads((dest / "session.json").read_text())
    doc["camera"] = {"K": truth["camera"]["K"], "dist": truth["camera"]["dist"]}
    for view, true_view in zip(doc["views"], truth["views"]):
        view["pose"] = {"R": true_view["R"], "t": true_view["t"]}
    write_json(dest / "session.json", doc)
    return dest


def main(argv=None):
    """``python -m organlab.synthetic OUT [--seed N] [--specimen aaa|grooved] [--small]``."""
    import argparse
    import time

    ap = argparse.ArgumentParser(prog="organlab synth", description="Write a synthetic organlab session folder.")
    ap.add_argument("out", help="session folder to write")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--specimen", choices=["aaa", "grooved"], default="aaa")
    ap.add_argument("--small", action="store_true", help="320x240, 12 views, few calibration images (fast)")
    ap.add_argument("--noise", type=float, default=None, help="pixel noise sigma, grey levels")
    ap.add_argument(
        "--png",
        action="store_true",
        help="write views and background frames as PNG (default for full-size sessions: JPEG quality 98, 4:4:4, "
        "to keep the folder under 15 MB; calibration images are always grey PNG)",
    )
    ap.add_argument("--no-camera", action="store_true", help="do not put the true intrinsics in session.json")
    ap.add_argument("--no-poses", action="store_true", help="do not put the true view poses in session.json")
    ap.add_argument("--preview", default=None, help="also write a half-size PNG of view 0 here")
    ap.add_argument("--force", action="store_true", help="write into a folder that is not empty (overwrites its session)")
    args = ap.parse_args(argv)
    target = Path(args.out)
    if target.exists() and (not target.is_dir() or any(target.iterdir())) and not args.force:
        what = "is a file" if not target.is_dir() else "is not empty"
        ap.exit(2, f"organlab synth: error: {target}: {what}; give a new folder, or --force to overwrite its session\n")
    kw = {}
    if args.small:
        kw = dict(image_size=(320, 240), n_views=12, n_intrinsic=8, n_turntable=6, n_background=5)
    if args.noise is not None:
        kw["noise_sigma"] = args.noise
    elif not args.small:
        kw["noise_sigma"] = 1.0
    if not args.png and not args.small:
        kw.update(view_format="jpg", background_format="jpg", jpeg_quality=98)
    t0 = time.perf_counter()
    truth = make_session(
        args.out, seed=args.seed, specimen=args.specimen, include_camera=not args.no_camera, include_poses=not args.no_poses, **kw
    )
    out = Path(args.out)
    size = sum(p.stat().st_size for p in out.rglob("*") if p.is_file())
    print(
        f"wrote {out}: {len(truth['views'])} views, {truth['specimen']} volume {truth['volume_mm3']:.1f} mm^3, "
        f"{size / 1e6:.2f} MB, {time.perf_counter() - t0:.1f} s"
    )
    if args.preview:
        import cv2

        from .session import load_session

        s = load_session(out, check_images=False)
        img = s.read(s.views[0].image)
        small = cv2.resize(img, (img.shape[1] // 2, img.shape[0] // 2), interpolation=cv2.INTER_AREA)
        Path(args.preview).parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(args.preview), small[:, :, ::-1], [cv2.IMWRITE_PNG_COMPRESSION, 9])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
