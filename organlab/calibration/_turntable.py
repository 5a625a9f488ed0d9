"""Turntable calibration: the camera's pose and the table axis, fitted jointly over board images on the table."""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from ..camera import Camera, rot_z
from ..errors import CalibrationError
from ..session import Pattern
from ._board import _check_pattern, _detect_all, _orientable, board_points
from ._common import (
    FLAG_FLOOR_PX,
    REJECT_FACTOR,
    _corners_entry,
    _load_images,
    _names,
    _no_board_message,
    _project,
    _rms,
    _rodrigues,
    _threshold,
)

@dataclass
class TurntableCalibration:
    """Result of :func:`calibrate_turntable`.

    Attributes
    ----------
    camera : Camera
        The camera at table angle 0: intrinsics and ``R = R_cam``, ``t = t_cam``
        (world to camera, mm).  A view at angle ``a`` is
        ``camera.at_table_angle(a)``.
    rms_px : float
        Reprojection RMS of the joint fit over every corner of the images
        used, px.
    per_image_rms : dict of str to float
        Each detected image's RMS under the final fit (flagged ones too), px.
    flagged : list of str
        Images whose RMS was far above the others (the board moved, a wrong
        angle); they are left out of the final fit.
    rejected : dict of str to str
        Images with no usable board and why.
    angles_deg : dict of str to float
    board_offset_mm : (2,) float64
        World ``(x, y)`` of the board's first corner (black end), mm.
    std : dict
        One standard deviation of ``rvec_cam`` (3,) rad, ``t_cam`` (3,) mm,
        ``board_offset_mm`` (2,) mm and ``camera_center_mm`` (3,) mm.
    corners : dict of str to (N, 2) float64
        Detected corners, board order, px.
    """

    camera: Camera
    rms_px: float
    per_image_rms: dict
    flagged: list
    rejected: dict
    angles_deg: dict
    board_offset_mm: np.ndarray
    std: dict
    corners: dict = field(repr=False, default_factory=dict)

    @property
    def R_cam(self) -> np.ndarray:
        """World to camera rotation at table angle 0, (3, 3)."""
        return self.camera.R

    @property
    def t_cam(self) -> np.ndarray:
        """World to camera translation at table angle 0, (3,) mm."""
        return self.camera.t

    @property
    def axis_direction_cam(self) -> np.ndarray:
        """The table axis (+Z, up) in the camera frame at angle 0, unit (3,)."""
        return self.camera.R[:, 2].copy()

    @property
    def axis_point_cam(self) -> np.ndarray:
        """Where the axis meets the board's top surface, camera frame, mm (3,)."""
        return self.camera.t.copy()

    @property
    def camera_center_mm(self) -> np.ndarray:
        """Camera centre at angle 0, world frame, mm (3,)."""
        return self.camera.center

    def view_camera(self, angle_deg: float) -> Camera:
        """The camera of a view at table angle ``angle_deg``."""
        return self.camera.at_table_angle(angle_deg)

    def to_dict(self) -> dict:
        """JSON-ready: the ``turntable`` entry of ``calibration.json``."""
        c = self.camera.center
        dist_axis = float(np.hypot(c[0], c[1]))
        return {
            "R_cam": self.camera.R.tolist(),
            "t_cam": self.camera.t.tolist(),
            "rms_px": self.rms_px,
            "n_images": len(self.per_image_rms) - len(self.flagged),
            "images": {
                n: {"angle_deg": self.angles_deg[n], "rms_px": r, "flagged": n in self.flagged, **_corners_entry(self.corners, n)}
                for n, r in self.per_image_rms.items()
            },
            "flagged": list(self.flagged),
            "rejected": dict(self.rejected),
            "axis": {
                "direction_cam": self.axis_direction_cam.tolist(),
                "point_cam_mm": self.axis_point_cam.tolist(),
                "camera_center_mm": c.tolist(),
                "camera_distance_to_axis_mm": dist_axis,
                "camera_height_mm": float(c[2]),
                "camera_elevation_deg": float(np.degrees(np.arctan2(c[2], dist_axis))),
                "board_offset_mm": np.asarray(self.board_offset_mm).tolist(),
            },
            "std": {k: np.asarray(v).tolist() for k, v in self.std.items()},
            "uncertainty_note": "std: one standard deviation from the fit's Jacobian",
        }


def _tt_points(params, obj, angles):
    """Camera-frame points (n_img, N, 3) of the turntable model."""
    R_cam = _rodrigues(params[:3])[0]
    t_cam = params[3:6]
    off = np.array([params[6], params[7], 0.0])
    X0 = obj + off
    Rz = np.stack([rot_z(a) for a in angles])
    Xw = np.einsum("kab,nb->kna", Rz, X0)
    return Xw @ R_cam.T + t_cam


def _tt_residuals(params, K, dist, obj, angles, pts):
    return (_project(K, dist, _tt_points(params, obj, angles)) - pts).ravel()


def _tt_init(K, dist, obj, pts, angles):
    """Initial camera pose at angle 0 and board offset from per-image solvePnP."""
    import cv2

    Rs, ts = [], []
    for c in pts:
        ok, rv, tv = cv2.solvePnP(obj, c.reshape(-1, 1, 2), K, dist, flags=cv2.SOLVEPNP_ITERATIVE)
        if not ok:
            raise CalibrationError("solvePnP failed on a turntable image; check the intrinsics")
        Rs.append(cv2.Rodrigues(rv)[0])
        ts.append(tv.ravel())
    # R_k = R_cam Rz(a_k): chordal mean of R_k Rz(-a_k)
    M = sum(R @ rot_z(-a) for R, a in zip(Rs, angles))
    U, _, Vt = np.linalg.svd(M)
    R_cam = U @ np.diag([1, 1, np.linalg.det(U @ Vt)]) @ Vt
    # t_k = R_cam Rz(a_k) [ox, oy, 0] + t_cam: linear in (ox, oy, t_cam)
    A = np.zeros((3 * len(ts), 5))
    b = np.concatenate(ts)
    for k, a in enumerate(angles):
        M = R_cam @ rot_z(a)
        A[3 * k : 3 * k + 3, 0:2] = M[:, :2]
        A[3 * k : 3 * k + 3, 2:5] = np.eye(3)
    sol = np.linalg.lstsq(A, b, rcond=None)[0]
    return np.concatenate([cv2.Rodrigues(R_cam)[0].ravel(), sol[2:5], sol[0:2]])


def _tt_fit(K, dist, obj, pts, angles, x0=None):
    from scipy.optimize import least_squares

    if x0 is None:
        x0 = _tt_init(K, dist, obj, pts, angles)
    # soft-L1 with a 0.5 px scale: quadratic for normal residuals, but a
    # single mislocated corner cannot drag the pose
    res = least_squares(
        _tt_residuals, x0, x_scale="jac", loss="soft_l1", f_scale=0.5, args=(K, dist, obj, angles, pts), xtol=1e-12, ftol=1e-12
    )
    J = res.jac
    dof = max(J.shape[0] - J.shape[1], 1)
    cov = np.linalg.pinv(J.T @ J) * (float(np.sum(res.fun**2)) / dof)
    return res.x, cov


def _per_image_rms(x, K, dist, obj, angles, pts):
    res = _tt_residuals(x, K, dist, obj, angles, pts).reshape(len(pts), -1, 2)
    return np.sqrt(np.mean(np.sum(res**2, axis=2), axis=1))


def _tt_fit_robust(K, dist, obj, pts, angles):
    """Turntable parameters that a minority of moved boards cannot drag, (8,).

    The joint fit's soft-L1 loss stops a mislocated corner, not a board moved
    between stops: that moves all the corners of an image, and 3 such images
    of 10 drag the pose (the sample with 3 turntable images shifted by
    (6, 3) px: RMS 1.79 px, a model 22 % too small).  Here the fit starts from
    several poses (``solvePnP`` of all the images, and of windows of half of
    them) with a redescending loss (``arctan``, 0.5 px: an image 6 px off weighs
    almost nothing); the start whose fit has the smallest *median* per-image
    RMS wins.  On that sample the moved images then stand at 6.7 px, the
    others at 0.03-0.05 px (0.2-1 s).
    """
    from scipy.optimize import least_squares

    n = len(pts)
    subsets = [list(range(n))]
    if n >= 4:
        h = (n + 1) // 2
        step = max(1, (n - h) // 3)
        subsets += [list(range(s, s + h)) for s in range(0, n - h + 1, step)]
    best = None
    for idx in subsets:
        if _distinct_angles([angles[i] for i in idx]) < 2:
            continue
        try:
            x0 = _tt_init(K, dist, obj, pts[idx], [angles[i] for i in idx])
        except CalibrationError:  # solvePnP failed on this subset: another start will do
            continue
        r = least_squares(_tt_residuals, x0, x_scale="jac", loss="arctan", f_scale=0.5,
                          args=(K, dist, obj, angles, pts), xtol=1e-10, ftol=1e-10)
        score = float(np.median(_per_image_rms(r.x, K, dist, obj, angles, pts)))
        if best is None or score < best[0]:
            best = (score, r.x)
    return best[1] if best is not None else _tt_init(K, dist, obj, pts, angles)


def _distinct_angles(angles):
    a = np.mod(np.asarray(angles, float), 360.0)
    return len(np.unique(np.round(a, 6)))


def calibrate_turntable(
    images: Sequence[np.ndarray],
    angles_deg: Sequence[float],
    camera: Camera,
    pattern: Pattern,
    *,
    names: Sequence[str] | None = None,
    flag_factor: float = REJECT_FACTOR,
    flag_floor_px: float = FLAG_FLOOR_PX,
    progress: Callable[[int, int], object] | None = None,
) -> TurntableCalibration:
    """Camera pose at table angle 0 and the table axis, one joint fit.

    The board lies on the table, printed side up; one image per table angle.
    Unknowns: the camera's pose at angle 0 (``R_cam``, ``t_cam``: world to
    camera; they hold the axis's direction ``R_cam[:, 2]`` and position
    ``t_cam`` in the camera frame) and the board's in-plane offset from the
    axis (2).  The world frame is the board's at angle 0 (X black end to
    white end, Z up the axis, origin on the axis in the board's surface), so
    the board's in-plane rotation is zero by definition.  Every corner of
    every image enters one least-squares problem with the angles held fixed
    (``scipy.optimize.least_squares``), initialised from per-image
    ``solvePnP``.  A view at angle ``a`` then has ``R = R_cam @ Rz(a)``,
    ``t = t_cam``.

    Parameters
    ----------
    images : sequence of (H, W) or (H, W, 3) uint8, or paths
        The board lying on the table at each angle; all of the camera's
        ``image_size``.
    angles_deg : sequence of float
        Table angle of each image, degrees, right-handed about +Z.
    camera : Camera
        Intrinsics (its pose is ignored).
    pattern : Pattern
        Must have an odd number of inner corners along ``inner_corners[0]``
        and an even number along the other side, so that the board's X
        direction is defined (e.g. 9 x 6).
    names : sequence of str, optional
    flag_factor, flag_floor_px : float
        An image whose RMS, under a fit that a minority of moved boards cannot
        drag, exceeds ``max(flag_factor * median, flag_floor_px)`` is flagged and
        the fit is run again without it, when more than half the images remain.
    progress : callable, optional
        ``progress(done, total)`` after each image's detection.

    Returns
    -------
    TurntableCalibration

    Raises
    ------
    CalibrationError
        Angles missing or not finite, no board in any image, fewer than two
        usable images at distinct angles, a pattern whose X direction is
        ambiguous, or images of the wrong size.
    """
    p = _check_pattern(pattern)
    if not isinstance(camera, Camera):
        raise CalibrationError(f"camera must be an organlab Camera (the intrinsics), got {type(camera).__name__}")
    if not _orientable(p.inner_corners):
        nx, ny = p.inner_corners
        raise CalibrationError(
            f"pattern.inner_corners is {nx}x{ny}: the turntable calibration needs an odd number of inner corners along "
            "the first (long) side and an even number along the other (e.g. 9x6) to tell the board's X direction"
        )
    images = list(images)
    names = _names(images, names)
    if angles_deg is None:
        raise CalibrationError("angles_deg is missing; give the table angle of every turntable image")
    angles_arr = np.asarray(list(angles_deg), dtype=object)
    if len(angles_arr) != len(images):
        raise CalibrationError(f"{len(images)} turntable images but {len(angles_arr)} angles; give one angle per image")
    bad = [n for n, a in zip(names, angles_arr) if not isinstance(a, (int, float, np.number)) or isinstance(a, bool) or not np.isfinite(a)]
    if bad:
        raise CalibrationError(f"turntable angle missing or not a number for {', '.join(bad)}; give angle_deg for every image")
    angles = [float(a) for a in angles_arr]
    if not images:
        raise CalibrationError("no turntable calibration images given")
    images = _load_images(images, names, camera.image_size, "turntable")
    corners, rejected = _detect_all(images, names, p, need_orientation=True, progress=progress)
    if not corners and all(r.startswith("no ") for r in rejected.values()):
        raise CalibrationError(_no_board_message("turntable", p, len(images)))
    ang = dict(zip(names, angles))
    n_angles = _distinct_angles([ang[n] for n in corners])
    if len(corners) < 2 or n_angles < 2:
        failed = ", ".join(f"{n} ({r})" for n, r in rejected.items()) or "none"
        raise CalibrationError(
            f"only {len(corners)} turntable images with a usable board at {n_angles} "
            f"distinct angles (need 2 angles, better 6+); failed: {failed}"
        )

    tt = fit_turntable(corners, {n: ang[n] for n in corners}, camera, p, flag_factor=flag_factor, flag_floor_px=flag_floor_px)
    tt.rejected = rejected
    tt.angles_deg = ang
    return tt


def fit_turntable(corners: Mapping[str, np.ndarray | None], angles_deg: Sequence[float], camera: Camera, pattern: Pattern,
                  *, flag_factor: float = REJECT_FACTOR, flag_floor_px: float = FLAG_FLOOR_PX) -> TurntableCalibration:
    """The joint turntable fit of :func:`calibrate_turntable` on detected corners.

    Parameters
    ----------
    corners : dict of str to (N, 2) float64
        Detected inner corners per image, px, in board order
        (:func:`detect_board`).
    angles_deg : dict of str to float
        Table angle of each image, degrees.
    camera : Camera
        Intrinsics.
    pattern : Pattern
    flag_factor, flag_floor_px : float
        As in :func:`calibrate_turntable`.

    Returns
    -------
    TurntableCalibration
    """
    p = _check_pattern(pattern)
    K, dist = camera.K, camera.dist
    obj = board_points(p)
    missing = [str(n) for n in corners if n not in angles_deg]
    if missing:
        raise CalibrationError(f"angles_deg has no table angle for {', '.join(missing)}; give one angle per image")
    ang = {n: float(angles_deg[n]) for n in corners}
    corners = {n: np.asarray(c, np.float64).reshape(-1, 2) for n, c in corners.items()}
    for n, c in corners.items():
        if c.shape[0] != obj.shape[0]:
            raise CalibrationError(f"image '{n}': {c.shape[0]} corners but the pattern has {obj.shape[0]}")
    if len(corners) < 2 or _distinct_angles(list(ang.values())) < 2:
        raise CalibrationError("the turntable fit needs boards at 2 or more distinct table angles")
    det = list(corners)
    pts_all = np.stack([corners[n] for n in det])
    angles_all = [ang[n] for n in det]
    # each image judged by its residuals under a fit the others agree on: a minority
    # of moved boards cannot drag it (see _tt_fit_robust)
    x = _tt_fit_robust(K, dist, obj, pts_all, angles_all)
    per = _per_image_rms(x, K, dist, obj, angles_all, pts_all)
    bad = per > _threshold(per, flag_factor, flag_floor_px)
    keep = [n for n, b in zip(det, bad) if not b]
    flagged = []
    # set them aside only when most images remain (else the RMS says the fit is poor)
    if bad.any() and len(keep) >= max(2, len(det) // 2 + 1) and _distinct_angles([ang[n] for n in keep]) >= 2:
        flagged = [n for n, b in zip(det, bad) if b]
    used = [n for n in det if n not in flagged]
    x, cov = _tt_fit(K, dist, obj, np.stack([corners[n] for n in used]), [ang[n] for n in used], x0=x)
    res = _tt_residuals(x, K, dist, obj, angles_all, pts_all).reshape(len(det), -1, 2)
    per = np.sqrt(np.mean(np.sum(res**2, axis=2), axis=1))
    per_image = {n: float(r) for n, r in zip(det, per)}
    used_res = np.stack([res[det.index(n)] for n in used])

    R_cam = _rodrigues(x[:3])[0]
    cam0 = camera.with_pose(R_cam, x[3:6])
    # camera centre std by linear propagation
    eps = 1e-6
    Jc = np.zeros((3, 8))
    for i in range(8):
        dx = np.zeros(8)
        dx[i] = eps
        c1 = -_rodrigues((x + dx)[:3])[0].T @ (x + dx)[3:6]
        c0 = -_rodrigues((x - dx)[:3])[0].T @ (x - dx)[3:6]
        Jc[:, i] = (c1 - c0) / (2 * eps)
    sd = np.sqrt(np.clip(np.diag(cov), 0, None))
    std = {
        "rvec_cam": sd[:3],
        "t_cam": sd[3:6],
        "board_offset_mm": sd[6:8],
        "camera_center_mm": np.sqrt(np.clip(np.diag(Jc @ cov @ Jc.T), 0, None)),
    }
    return TurntableCalibration(
        camera=cam0,
        rms_px=_rms(used_res),
        per_image_rms=per_image,
        flagged=flagged,
        rejected={},
        angles_deg=dict(ang),
        board_offset_mm=x[6:8].copy(),
        std=std,
        corners=corners,
    )


