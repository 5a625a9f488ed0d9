"""The synthetic camera and calibration boards: poses and rendering."""

from __future__ import annotations

import numpy as np

from ..camera import Camera, rot_z
from ..session import DEFAULT_PATTERN, Pattern
from . import _render

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
