"""Intrinsic calibration: Bouguet's camera model fitted to board images held at varied poses."""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from ..camera import Camera
from ..errors import CalibrationError
from ..session import Pattern
from ._board import _check_pattern, _detect_all, board_points
from ._common import (
    REJECT_FACTOR,
    REJECT_FLOOR_PX,
    _check_image_size,
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
class IntrinsicCalibration:
    """Result of :func:`calibrate_intrinsics`.

    Attributes
    ----------
    camera : Camera
        Intrinsics, identity pose.
    rms_px : float
        Reprojection RMS over every corner of the images used, px
        (``sqrt(mean(|detected - reprojected|^2))``).
    per_image_rms : dict of str to float
        The same per image used, px.
    std : dict
        One standard deviation: ``fc`` (2,), ``cc`` (2,) px; ``alpha_c``;
        ``kc`` (5,).  A parameter held fixed has std 0.
    rejected : dict of str to str
        Images left out and why (no board found, or RMS far above the others).
    extrinsics : dict of str to ((3,) float64, (3,) float64)
        Board-to-camera ``(rvec, tvec)`` per image used, mm.
    corners : dict of str to (N, 2) float64
        Detected corners per image (board order), px.
    fixed : tuple of str
        Parameters held fixed: ``"alpha_c"`` unless ``estimate_skew``,
        ``"k3"`` with ``fix_k3``.
    image_size : (2,) int
        ``(width, height)``, px (the camera's).
    """

    camera: Camera
    rms_px: float
    per_image_rms: dict
    std: dict
    rejected: dict
    extrinsics: dict
    corners: dict = field(repr=False, default_factory=dict)
    fixed: tuple = ()

    @property
    def image_size(self) -> tuple[int, int]:
        return self.camera.image_size

    @property
    def uncertainty(self) -> dict[str, np.ndarray]:
        """Three standard deviations (Bouguet's toolbox's "+/-" convention), same keys as ``std``."""
        return {k: 3.0 * np.asarray(v) for k, v in self.std.items()}

    def to_dict(self) -> dict:
        """JSON-ready: the ``camera`` entry of ``calibration.json``."""
        d = self.camera.intrinsics_dict()
        d.update(
            rms_px=self.rms_px,
            source="calibrated",
            n_images=len(self.per_image_rms),
            std={k: np.asarray(v).tolist() for k, v in self.std.items()},
            uncertainty_3sigma={k: np.asarray(v).tolist() for k, v in self.uncertainty.items()},
            uncertainty_note="std: one standard deviation; uncertainty_3sigma: three (Bouguet's +/-)",
            fixed=list(self.fixed),
            images={
                n: {
                    "rms_px": self.per_image_rms[n],
                    "rvec": self.extrinsics[n][0].tolist(),
                    "tvec": self.extrinsics[n][1].tolist(),
                    **_corners_entry(self.corners, n),
                }
                for n in self.per_image_rms
            },
            rejected=dict(self.rejected),
        )
        return d

    def summary(self) -> str:
        """Bouguet-style text: every parameter with its 3-sigma uncertainty."""
        K, u = self.camera.K, self.uncertainty
        kc = ", ".join(f"{a:.5f}" for a in self.camera.dist)
        kce = ", ".join(f"{a:.5f}" for a in u["kc"])
        return "\n".join(
            [
                f"Focal length:    fc = [{K[0, 0]:.3f}, {K[1, 1]:.3f}] +/- [{u['fc'][0]:.3f}, {u['fc'][1]:.3f}] px",
                f"Principal point: cc = [{K[0, 2]:.3f}, {K[1, 2]:.3f}] +/- [{u['cc'][0]:.3f}, {u['cc'][1]:.3f}] px",
                f"Skew:       alpha_c = {self.camera.skew:.5f} +/- {float(u['alpha_c']):.5f}",
                f"Distortion:      kc = [{kc}] +/- [{kce}]",
                f"Reprojection RMS: {self.rms_px:.4f} px over {len(self.per_image_rms)} images"
                + (f" ({len(self.rejected)} rejected)" if self.rejected else ""),
                "(+/- are three standard deviations, as in Bouguet's toolbox)",
            ]
        )


def _opencv_calibrate(obj, pts, image_size, fix_k3):
    import cv2

    flags = cv2.CALIB_FIX_K3 if fix_k3 else 0
    # on OpenCV's threads the fit's sums come out in another order from run to run: the same corners gave six
    # different calibrations in six calls (differing about 1e-10 relative), and so every later stage's bits;
    # on one thread it is the same calibration every time (a few ms for a few dozen boards)
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        out = cv2.calibrateCameraExtended(
            [obj.astype(np.float32)] * len(pts),
            [p.astype(np.float32).reshape(-1, 1, 2) for p in pts],
            tuple(int(s) for s in image_size),
            None,
            None,
            flags=flags,
            criteria=(cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-12),
        )
    finally:
        cv2.setNumThreads(threads)
    _, K, dist, rvecs, tvecs, std_int = out[:6]
    std_int = np.asarray(std_int, np.float64).ravel()
    dist = np.asarray(dist, np.float64).ravel()[:5]
    rv = np.array([np.ravel(r) for r in rvecs], np.float64)
    tv = np.array([np.ravel(t) for t in tvecs], np.float64)
    std = {
        "fc": std_int[0:2].copy(),
        "cc": std_int[2:4].copy(),
        "alpha_c": 0.0,
        "kc": std_int[4:9].copy(),
    }
    return np.asarray(K, np.float64), dist, rv, tv, std


def _residuals_intr(params, obj, pts, n_img, fixed, base):
    n_int = int((~fixed).sum())
    full = base.copy()
    full[~fixed] = params[:n_int]
    fx, fy, cx, cy, alpha = full[:5]
    poses = params[n_int:].reshape(n_img, 6)
    pc = np.einsum("kab,nb->kna", _rodrigues(poses[:, :3]), obj) + poses[:, None, 3:]
    K = np.array([[fx, alpha * fx, cx], [0, fy, cy], [0, 0, 1.0]])
    return (_project(K, full[5:10], pc) - pts).ravel()


def _refine_with_skew(obj, pts, K, dist, rv, tv, fix_k3):
    """Joint least squares over fc, cc, alpha_c, kc and every board pose; std from the Jacobian."""
    from scipy.optimize import least_squares

    n_img = pts.shape[0]
    base = np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2], K[0, 1] / K[0, 0], *dist])
    fixed = np.zeros(10, bool)
    if fix_k3:
        fixed[9] = True
    n_int = int((~fixed).sum())
    x0 = np.concatenate([base[~fixed], np.concatenate([rv, tv], axis=1).ravel()])
    res = least_squares(
        _residuals_intr, x0, method="lm", x_scale="jac", args=(obj, pts, n_img, fixed, base), xtol=1e-10, ftol=1e-10
    )
    full = base.copy()
    full[~fixed] = res.x[:n_int]
    fx, fy, cx, cy, alpha = full[:5]
    K = np.array([[fx, alpha * fx, cx], [0, fy, cy], [0, 0, 1.0]])
    poses = res.x[n_int:].reshape(n_img, 6)
    J = res.jac.toarray() if hasattr(res.jac, "toarray") else np.asarray(res.jac)
    dof = max(J.shape[0] - J.shape[1], 1)
    s2 = float(np.sum(res.fun**2)) / dof
    cov = np.linalg.pinv(J.T @ J) * s2
    sd = np.zeros(10)
    sd[~fixed] = np.sqrt(np.clip(np.diag(cov)[:n_int], 0, None))
    std = {"fc": sd[0:2], "cc": sd[2:4], "alpha_c": float(sd[4]), "kc": sd[5:10]}
    return K, full[5:10], poses[:, :3], poses[:, 3:], std


def calibrate_intrinsics(
    images: Sequence[np.ndarray],
    pattern: Pattern,
    *,
    image_size: tuple[int, int],
    names: Sequence[str] | None = None,
    estimate_skew: bool = False,
    fix_k3: bool = True,
    reject_factor: float = REJECT_FACTOR,
    reject_floor_px: float = REJECT_FLOOR_PX,
    min_images: int = 3,
    progress: Callable[[int, int], object] | None = None,
) -> IntrinsicCalibration:
    """Intrinsic calibration (Bouguet's model) from images of a checkerboard.

    Parameters
    ----------
    images : sequence of (H, W) or (H, W, 3) uint8, or paths
        The board held at varied poses (tilted, filling the image, in the
        corners where distortion is strong).
    pattern : Pattern
        ``inner_corners`` and ``square_size`` (mm).
    image_size : (2,) int
        ``(width, height)``, px; every image must have it.
    names : sequence of str, optional
        One name per image, used in the results and messages.
    estimate_skew : bool
        Also fit ``alpha_c`` (Bouguet's ``est_alpha``); default held at 0.
    fix_k3 : bool
        Hold ``k3`` (``kc(5)``, the 6th-order radial term) at 0, as Bouguet's
        toolbox does by default (``est_dist = [1 1 1 1 0]``); pass False for
        strongly distorting (wide-angle) lenses.
    reject_factor, reject_floor_px : float
        An image whose RMS exceeds ``max(reject_factor * median, reject_floor_px)``
        is rejected and the fit is run again without it.
    min_images : int
        Fewest images with a detected board.
    progress : callable, optional
        Called as ``progress(done, total)`` after each image's detection.

    Returns
    -------
    IntrinsicCalibration

    Raises
    ------
    CalibrationError
        No board in any image, too few boards, or images of different sizes.
    """
    p = _check_pattern(pattern)
    images = list(images)
    names = _names(images, names)
    image_size = _check_image_size(image_size)
    if not images:
        raise CalibrationError("no intrinsic calibration images given")
    images = _load_images(images, names, image_size, "intrinsic")
    corners, rejected = _detect_all(images, names, p, need_orientation=False, progress=progress)
    if not corners:
        raise CalibrationError(_no_board_message("intrinsic", p, len(images)))
    if len(corners) < min_images:
        failed = ", ".join(f"{n} ({r})" for n, r in rejected.items())
        raise CalibrationError(
            f"only {len(corners)} of {len(images)} intrinsic images show the board (need {min_images}); failed: {failed}"
        )

    res = fit_intrinsics(
        corners,
        p,
        image_size=image_size,
        estimate_skew=estimate_skew,
        fix_k3=fix_k3,
        reject_factor=reject_factor,
        reject_floor_px=reject_floor_px,
        min_images=min_images,
    )
    res.rejected = {**rejected, **res.rejected}
    return res


def fit_intrinsics(
    corners: Mapping[str, np.ndarray | None],
    pattern: Pattern,
    *,
    image_size: tuple[int, int],
    estimate_skew: bool = False,
    fix_k3: bool = True,
    reject_factor: float = REJECT_FACTOR,
    reject_floor_px: float = REJECT_FLOOR_PX,
    min_images: int = 3,
) -> IntrinsicCalibration:
    """The intrinsic fit of :func:`calibrate_intrinsics` on detected corners.

    Parameters
    ----------
    corners : dict of str to (N, 2) float64
        Inner corners per image, px, in board order.
    pattern : Pattern
    image_size : (2,) int
    estimate_skew, fix_k3, reject_factor, reject_floor_px, min_images
        As in :func:`calibrate_intrinsics`.

    Returns
    -------
    IntrinsicCalibration
    """
    p = _check_pattern(pattern)
    obj = board_points(p)
    image_size = _check_image_size(image_size)
    corners = {str(n): np.asarray(c, np.float64).reshape(-1, 2) for n, c in corners.items()}
    for n, c in corners.items():
        if c.shape[0] != obj.shape[0]:
            raise CalibrationError(f"image '{n}': {c.shape[0]} corners but the pattern has {obj.shape[0]}")
    if len(corners) < min_images:
        raise CalibrationError(f"{len(corners)} images with a board; the intrinsic fit needs {min_images} or more")
    rejected = {}
    used = list(corners)
    for _pass in range(2):
        pts = np.stack([corners[n] for n in used])
        K, dist, rv, tv, std = _opencv_calibrate(obj, pts, image_size, fix_k3)
        if estimate_skew:
            K, dist, rv, tv, std = _refine_with_skew(obj, pts, K, dist, rv, tv, fix_k3)
        pc = np.einsum("kab,nb->kna", _rodrigues(rv), obj) + tv[:, None]
        res = _project(K, dist, pc) - pts
        per = np.sqrt(np.mean(np.sum(res**2, axis=2), axis=1))
        if _pass == 1:
            break
        thr = _threshold(per, reject_factor, reject_floor_px)
        bad = per > thr
        if not bad.any() or len(used) - bad.sum() < min_images:
            break
        for n, r in zip(np.array(used)[bad], per[bad]):
            rejected[str(n)] = f"reprojection RMS {r:.3f} px > {thr:.3f} px (max({reject_factor:g} x median, {reject_floor_px:g} px))"
        used = [n for n, b in zip(used, bad) if not b]

    camera = Camera(K, dist, image_size=image_size)
    fixed = tuple(n for n, f in (("alpha_c", not estimate_skew), ("k3", fix_k3)) if f)
    return IntrinsicCalibration(
        camera=camera,
        rms_px=_rms(res),
        per_image_rms={n: float(r) for n, r in zip(used, per)},
        std={k: (np.asarray(v, float) if np.ndim(v) else float(v)) for k, v in std.items()},
        rejected=rejected,
        extrinsics={n: (rv[k].copy(), tv[k].copy()) for k, n in enumerate(used)},
        corners=corners,
        fixed=fixed,
    )


