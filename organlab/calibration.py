"""Camera and turntable calibration from images of a checkerboard.

Two fits, each reported with the errors a user needs to judge it before
carving (:func:`check_figures` draws them over every image):

* **Intrinsics** (:func:`calibrate_intrinsics`): the board held at varied
  poses.  Bouguet's camera model (``fc``, ``cc``, ``alpha_c``,
  ``kc = [k1, k2, p1, p2, k3]``) fitted with OpenCV's
  ``calibrateCameraExtended`` (or, with ``estimate_skew=True``, a joint
  least-squares fit that also frees ``alpha_c``), per-image reprojection RMS,
  automatic rejection of images whose RMS is far above the others and a
  second pass without them, and the standard deviation of every parameter.
  Like Bouguet's toolbox, :attr:`IntrinsicCalibration.uncertainty` gives
  **three** standard deviations.
* **Turntable** (:func:`calibrate_turntable`): the board lying on the table,
  one image per known table angle.  One least-squares problem over every
  corner of every image (8 unknowns: the camera pose at angle 0 (6) and the
  board's in-plane position relative to the table axis (2)), the angles held
  at their given values, initialised from per-image ``solvePnP``.  Images
  whose residual is far above the others (the board moved) are flagged and
  left out of a second pass.

World frame (``session-format.md``): defined by the board at table angle 0:
X along the board's long side (``inner_corners[0]``) from the end whose
corner squares are black toward the end whose corner squares are white,
Z the table axis toward the camera's side (up), Y = Z x X, origin where the
axis meets the board's top surface.  :func:`detect_board` returns corners in
that board order whatever order the corner detector found them in.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .camera import Camera, distort, rot_z
from .errors import CalibrationError
from .session import Pattern, read_image, write_json

__all__ = [
    "board_points",
    "detect_board",
    "IntrinsicCalibration",
    "TurntableCalibration",
    "calibrate_intrinsics",
    "fit_intrinsics",
    "calibrate_turntable",
    "fit_turntable",
    "calibrate_session",
    "write_calibration",
    "check_figures",
]

#: Factor on the median per-image RMS above which an image is rejected/flagged.
REJECT_FACTOR = 3.0
#: Floor of the rejection threshold, px (intrinsic images).
REJECT_FLOOR_PX = 0.5
#: Floor of the "board moved" threshold, px (turntable images).
FLAG_FLOOR_PX = 1.0
_HALF_CAP = 8
#: Upsampling factor of the final corner measurement (:func:`_refine_upsampled`).
_UPSAMPLE = 2


# ===================================================================== board
def _check_pattern(pattern):
    if not isinstance(pattern, Pattern):
        try:
            pattern = Pattern(tuple(pattern["inner_corners"]), float(pattern["square_size"]))
        except (TypeError, KeyError, ValueError):
            raise CalibrationError(
                f"pattern must be an organlab.session.Pattern (inner_corners, square_size), got {pattern!r}"
            ) from None
    ic = tuple(int(v) for v in pattern.inner_corners)
    if len(ic) != 2 or min(ic) < 2:
        raise CalibrationError(f"pattern.inner_corners must be [columns, rows] >= 2, got {pattern.inner_corners}")
    if not pattern.square_size > 0:
        raise CalibrationError(f"pattern.square_size must be > 0 mm, got {pattern.square_size}")
    return Pattern(ic, float(pattern.square_size), pattern.type)


def _orientable(size):
    """True when the board's X direction is defined by its corner colours (odd x even inner corners)."""
    nx, ny = size
    return nx % 2 == 1 and ny % 2 == 0


def board_points(pattern):
    """Inner corners of the board in the board frame.

    Corner ``(i, j)`` (``i`` along ``inner_corners[0]``, black end to white
    end; ``j`` along the other side, Y = Z x X with Z the printed side's
    normal) is at ``(i * s, j * s, 0)``; corners are listed with ``i``
    fastest, the order :func:`detect_board` returns.

    Parameters
    ----------
    pattern : Pattern

    Returns
    -------
    (nx * ny, 3) float64, mm, board frame
    """
    p = _check_pattern(pattern)
    nx, ny = p.inner_corners
    j, i = np.mgrid[0:ny, 0:nx]
    return np.stack([i.ravel(), j.ravel(), np.zeros(nx * ny)], axis=1).astype(np.float64) * p.square_size


def _as_grey(image):
    import cv2

    img = np.asarray(image)
    if img.ndim == 3 and img.shape[2] in (3, 4):
        img = cv2.cvtColor(np.ascontiguousarray(img[:, :, :3]), cv2.COLOR_RGB2GRAY)
    if img.ndim != 2:
        raise ValueError(f"image must be (H, W) or (H, W, 3), got shape {img.shape}")
    if img.dtype != np.uint8:
        img = np.clip(img, 0, 255).astype(np.uint8)
    return np.ascontiguousarray(img)


def _find_corners(grey, size):
    """Raw corners in the detector's order, refined to sub-pixel, or None."""
    import cv2

    nx, ny = size
    corners = None
    # Classic detector first: on real photographs (OpenCV's left01..14) it
    # finds every board where the sector-based one misses some; then the
    # sector-based detector as a fall-back (blur, low contrast).  The final
    # corners come from _refine_upsampled when it finds the board (it did on
    # every synthetic and real image we tried); cornerSubPix's otherwise.
    found, c = cv2.findChessboardCorners(grey, (nx, ny), flags=cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE)
    if found:
        corners = c
    else:
        for flags in (
            cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY,
            cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY,
        ):
            found, c = cv2.findChessboardCornersSB(grey, (nx, ny), flags=flags)
            if found:
                corners = c
                break
    if corners is None:
        return None
    corners = np.asarray(corners, np.float32).reshape(-1, 1, 2)
    spacing = _spacing(corners.reshape(ny, nx, 2).astype(np.float64))
    half = int(np.clip(np.floor(0.4 * spacing), 2, _HALF_CAP))
    term = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 50, 1e-3)
    corners = cv2.cornerSubPix(grey, corners, (half, half), (-1, -1), term).reshape(-1, 2).astype(np.float64)
    fine = _refine_upsampled(grey, corners, size, spacing)
    return corners if fine is None else fine


def _spacing(g):
    """Smallest distance between neighbouring corners of a (ny, nx, 2) grid, px."""
    return float(
        min(
            np.linalg.norm(np.diff(g, axis=1), axis=2).min(),
            np.linalg.norm(np.diff(g, axis=0), axis=2).min(),
        )
    )


def _refine_upsampled(grey, corners, size, spacing):
    """Corners re-measured by the sector-based detector on the board's crop upsampled x2, or None.

    ``findChessboardCornersSB`` with ``CALIB_CB_ACCURACY`` on the (bicubic)
    x2 upsampled board region gives the most accurate corners we measured on
    rendered boards with known truth (0.02-0.05 px RMS against 0.05-0.10 px
    for ``cornerSubPix``, whose window sees the grid lines curved by the lens
    and the squares foreshortened; ``CALIB_CB_ACCURACY`` at the native
    resolution: 0.04 px but a focal-length bias of 0.1-0.16 %).  Accepted
    only when every corner lands within a quarter square of the coarse one;
    returned in the coarse corners' order.
    """
    import cv2

    nx, ny = size
    h, w = grey.shape
    pad = max(spacing, 4.0)  # one square: measured to find the most boards (OpenCV's left01..14, both ways up)
    lo = np.floor(corners.min(axis=0) - pad).astype(int)
    hi = np.ceil(corners.max(axis=0) + pad).astype(int) + 1
    x0, y0 = max(lo[0], 0), max(lo[1], 0)
    x1, y1 = min(hi[0], w), min(hi[1], h)
    crop = np.ascontiguousarray(grey[y0:y1, x0:x1])
    big = cv2.resize(crop, None, fx=_UPSAMPLE, fy=_UPSAMPLE, interpolation=cv2.INTER_CUBIC)
    for flags in (cv2.CALIB_CB_ACCURACY, cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_ACCURACY):
        found, c = cv2.findChessboardCornersSB(big, (nx, ny), flags=flags)
        if found:
            break
    else:
        return None
    # pixel centres: big pixel U covers crop pixels (U + 0.5) / f - 0.5
    fine = (np.asarray(c, np.float64).reshape(-1, 2) + 0.5) / _UPSAMPLE - 0.5 + [x0, y0]
    d = np.linalg.norm(corners[:, None] - fine[None], axis=2)
    nearest = d.argmin(axis=1)
    if len(set(nearest.tolist())) != len(corners) or d[np.arange(len(corners)), nearest].max() > 0.25 * spacing:
        return None
    return fine[nearest]


def _sample(grey, point, radius):
    """Mean grey level in a square window around ``point`` (u, v), or NaN when outside."""
    h, w = grey.shape
    u, v = point
    r = max(1, int(round(radius)))
    u0, u1 = int(round(u)) - r, int(round(u)) + r + 1
    v0, v1 = int(round(v)) - r, int(round(v)) + r + 1
    if u0 < 0 or v0 < 0 or u1 > w or v1 > h:
        return np.nan
    return float(grey[v0:v1, u0:u1].mean())


def _corner_squares(grey, g):
    """Grey levels of the four outer corner squares and of their neighbours along i.

    ``g`` is the (ny, nx, 2) corner grid.  Returns two dicts keyed by
    ``(j_end, i_end)`` in {0, -1}^2: the corner square's level and the level
    of the square next to it along i (opposite colour).
    """
    ny, nx = g.shape[:2]
    corner, neighbour = {}, {}
    for je in (0, -1):
        for ie in (0, -1):
            j0 = 0 if je == 0 else ny - 1
            i0 = 0 if ie == 0 else nx - 1
            sj = 1 if je == 0 else -1
            si = 1 if ie == 0 else -1
            p = g[j0, i0]
            a_i = g[j0, i0 + si] - p  # one square inward along i
            a_j = g[j0 + sj, i0] - p
            r = 0.15 * min(np.linalg.norm(a_i), np.linalg.norm(a_j))
            corner[je, ie] = _sample(grey, p - 0.5 * a_i - 0.5 * a_j, r)
            neighbour[je, ie] = _sample(grey, p + 0.5 * a_i - 0.5 * a_j, r)
    return corner, neighbour


def _orient(grey, corners, size):
    """Re-order detected corners to the board order; returns (corners, oriented).

    ``oriented`` is False when the X direction could not be told from the
    corner-square colours (board not odd x even, squares outside the image,
    or too little contrast); X then keeps the detector's direction.
    """
    nx, ny = size
    g = corners.reshape(ny, nx, 2)
    oriented = False
    if _orientable(size):
        corner, neighbour = _corner_squares(grey, g)
        diffs = {k: corner[k] - neighbour[k] for k in corner}
        finite = [abs(d) for d in diffs.values() if np.isfinite(d)]
        contrast = float(np.median(finite)) if finite else 0.0
        # each outer corner square votes dark / bright against its neighbour
        # (opposite colour); a square cut by the border or blurred abstains
        dark = {k: (d < -0.5 * contrast) if np.isfinite(d) and abs(d) > 0.5 * contrast else None for k, d in diffs.items()}
        forward = sum(1 for k, v in dark.items() if v is not None and v == (k[1] == 0))
        backward = sum(1 for k, v in dark.items() if v is not None and v != (k[1] == 0))
        if contrast > 10 and max(forward, backward) >= 2 and min(forward, backward) == 0:
            oriented = True
            if backward > forward:  # black squares at the detector's last column
                g = g[:, ::-1]
    # Y = Z x X with Z toward the camera: seen from the front, Y points "up"
    # in the image when X points right, i.e. the 2-D cross product is < 0.
    dx = (g[:, -1] - g[:, 0]).mean(axis=0)
    dy = (g[-1, :] - g[0, :]).mean(axis=0)
    if dx[0] * dy[1] - dx[1] * dy[0] > 0:
        g = g[::-1, :]
    return np.ascontiguousarray(g.reshape(-1, 2)), oriented


def _detect(image, pattern):
    grey = _as_grey(image)
    raw = _find_corners(grey, pattern.inner_corners)
    if raw is None:
        return None, False
    return _orient(grey, raw, pattern.inner_corners)


def _detect_all(images, names, pattern, *, need_orientation, progress):
    """Board corners of every image that shows one, and why the others were left out.

    Returns ``(corners, rejected)``: dicts keyed by image name, of
    ``(N, 2)`` float64 corners in board order and of the reason; a reason
    starting with ``"no "`` means no board at all.
    """
    nx, ny = pattern.inner_corners
    corners, rejected = {}, {}
    for k, (img, name) in enumerate(zip(images, names)):
        c, oriented = _detect(img, pattern)
        if c is None:
            rejected[name] = f"no {nx}x{ny} board found"
        elif need_orientation and not oriented:
            rejected[name] = "board found but its black/white ends cannot be told (corner squares cut off or low contrast)"
        else:
            corners[name] = c
        if progress is not None:
            progress(k + 1, len(images))
    return corners, rejected


def detect_board(image, pattern, *, require_orientation=False):
    """Find the checkerboard's inner corners, sub-pixel, in board order.

    Detection: OpenCV's ``findChessboardCorners`` (adaptive threshold), with
    ``findChessboardCornersSB`` as fall-back, refined by ``cornerSubPix``;
    then every corner is measured again by ``findChessboardCornersSB``
    (``CALIB_CB_ACCURACY``) on the board's region upsampled x2 (bicubic),
    kept when it agrees with the first detection to a quarter square
    (rendered boards with known truth: 0.02-0.05 px RMS, against 0.05-0.10 px
    for ``cornerSubPix`` alone).
    The corners are then re-ordered so that X runs from the end whose outer
    corner squares are black to the end whose corner squares are white
    (grey levels sampled in the outer squares, extrapolated from the grid)
    and Y = Z x X with Z toward the camera, so a detector's 180-degree flip
    cannot change the board frame.

    Parameters
    ----------
    image : (H, W) or (H, W, 3) uint8
        Grey or RGB image.
    pattern : Pattern
        ``inner_corners`` (columns, rows) and ``square_size`` (mm).
    require_orientation : bool
        Return None when the black/white end cannot be told (the board has
        not an odd number of inner corners along ``inner_corners[0]`` and an
        even number along the other side, its corner squares are cut off by
        the image border, or the contrast is too low).

    Returns
    -------
    corners : (nx * ny, 2) float64 or None
        Pixels ``(u, v)``, listed as :func:`board_points`; None when no board
        is found.
    """
    p = _check_pattern(pattern)
    corners, oriented = _detect(image, p)
    if corners is None or (require_orientation and not oriented):
        return None
    return corners


# ================================================================ geometry
def _rodrigues(rvecs):
    """(n, 3) rotation vectors to (n, 3, 3) matrices."""
    rv = np.atleast_2d(np.asarray(rvecs, np.float64))
    theta = np.linalg.norm(rv, axis=1)
    small = theta < 1e-12
    k = rv / np.where(small, 1.0, theta)[:, None]
    K = np.zeros((rv.shape[0], 3, 3))
    K[:, 0, 1], K[:, 0, 2] = -k[:, 2], k[:, 1]
    K[:, 1, 0], K[:, 1, 2] = k[:, 2], -k[:, 0]
    K[:, 2, 0], K[:, 2, 1] = -k[:, 1], k[:, 0]
    s, c = np.sin(theta)[:, None, None], np.cos(theta)[:, None, None]
    R = np.eye(3)[None] + s * K + (1 - c) * (K @ K)
    R[small] = np.eye(3)
    return R


def _project(K, dist, pc):
    """Camera-frame points (..., 3) to pixels (..., 2) with the Bouguet model.

    ``Camera.project`` without building a :class:`Camera` (whose checks cost
    more than the projection) in the fits' residuals, where ``K`` changes
    every call and the points are batched over many poses.
    """
    shape = pc.shape[:-1]
    pc = pc.reshape(-1, 3)
    xn = pc[:, :2] / pc[:, 2:3]
    xd = distort(xn, dist)
    u = K[0, 0] * xd[:, 0] + K[0, 1] * xd[:, 1] + K[0, 2]
    v = K[1, 1] * xd[:, 1] + K[1, 2]
    return np.stack([u, v], axis=1).reshape(*shape, 2)


def _rms(res):
    res = np.asarray(res).reshape(-1, 2)
    return float(np.sqrt(np.mean(np.sum(res * res, axis=1))))


def _threshold(values, factor, floor):
    return max(factor * float(np.median(values)), floor)


# ============================================================== intrinsics
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
    def image_size(self):
        return self.camera.image_size

    @property
    def uncertainty(self):
        """Three standard deviations (Bouguet's toolbox's "+/-" convention), same keys as ``std``."""
        return {k: 3.0 * np.asarray(v) for k, v in self.std.items()}

    def to_dict(self):
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

    def summary(self):
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
    out = cv2.calibrateCameraExtended(
        [obj.astype(np.float32)] * len(pts),
        [p.astype(np.float32).reshape(-1, 1, 2) for p in pts],
        tuple(int(s) for s in image_size),
        None,
        None,
        flags=flags,
        criteria=(cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-12),
    )
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


def _load_images(images, names, image_size, what):
    """Images (arrays or paths) to a list of arrays (paths read grey); checks shapes and sizes."""
    out = []
    for img, name in zip(images, names):
        if isinstance(img, (str, Path)):
            img = read_image(img, grey=True, key=what)
        img = np.asarray(img)
        if img.ndim not in (2, 3) or (img.ndim == 3 and img.shape[2] not in (3, 4)):
            raise CalibrationError(f"{what} image '{name}' has shape {img.shape}; expected (H, W) or (H, W, 3)")
        size = (img.shape[1], img.shape[0])
        if size != tuple(image_size):
            raise CalibrationError(
                f"{what} image '{name}' is {size[0]}x{size[1]} px but image_size is {image_size[0]}x{image_size[1]}; "
                "every calibration image must have the same size"
            )
        out.append(img)
    return out


def _check_image_size(image_size):
    try:
        size = tuple(int(s) for s in image_size)
    except (TypeError, ValueError):
        raise CalibrationError(f"image_size must be (width, height), got {image_size!r}") from None
    if len(size) != 2 or min(size) <= 0:
        raise CalibrationError(f"image_size must be (width, height) > 0, got {size}")
    return size


def _names(images, names):
    if names is None:
        names = [Path(i).name if isinstance(i, (str, Path)) else f"image {k}" for k, i in enumerate(images)]
    names = [str(n) for n in names]
    if len(names) != len(images):
        raise CalibrationError(f"names has {len(names)} entries but there are {len(images)} images")
    if len(set(names)) != len(names):
        raise CalibrationError("names must be unique")
    return names


def _no_board_message(what, pattern, n):
    nx, ny = pattern.inner_corners
    return (
        f"no {nx}x{ny} board found in any of the {n} {what} images; check pattern.inner_corners "
        f"(inner corners, not squares: a board of {nx + 1}x{ny + 1} squares has {nx}x{ny}) and that the whole board is in view"
    )


def calibrate_intrinsics(
    images,
    pattern,
    *,
    image_size,
    names=None,
    estimate_skew=False,
    fix_k3=True,
    reject_factor=REJECT_FACTOR,
    reject_floor_px=REJECT_FLOOR_PX,
    min_images=3,
    progress=None,
):
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
    corners,
    pattern,
    *,
    image_size,
    estimate_skew=False,
    fix_k3=True,
    reject_factor=REJECT_FACTOR,
    reject_floor_px=REJECT_FLOOR_PX,
    min_images=3,
):
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


# =============================================================== turntable
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
    def R_cam(self):
        """World to camera rotation at table angle 0, (3, 3)."""
        return self.camera.R

    @property
    def t_cam(self):
        """World to camera translation at table angle 0, (3,) mm."""
        return self.camera.t

    @property
    def axis_direction_cam(self):
        """The table axis (+Z, up) in the camera frame at angle 0, unit (3,)."""
        return self.camera.R[:, 2].copy()

    @property
    def axis_point_cam(self):
        """Where the axis meets the board's top surface, camera frame, mm (3,)."""
        return self.camera.t.copy()

    @property
    def camera_center_mm(self):
        """Camera centre at angle 0, world frame, mm (3,)."""
        return self.camera.center

    def view_camera(self, angle_deg):
        """The camera of a view at table angle ``angle_deg``."""
        return self.camera.at_table_angle(angle_deg)

    def to_dict(self):
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


def _distinct_angles(angles):
    a = np.mod(np.asarray(angles, float), 360.0)
    return len(np.unique(np.round(a, 6)))


def calibrate_turntable(
    images,
    angles_deg,
    camera,
    pattern,
    *,
    names=None,
    flag_factor=REJECT_FACTOR,
    flag_floor_px=FLAG_FLOOR_PX,
    progress=None,
):
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
        An image whose RMS exceeds ``max(flag_factor * median, flag_floor_px)``
        is flagged and the fit is run again without it.
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


def fit_turntable(corners, angles_deg, camera, pattern, *, flag_factor=REJECT_FACTOR, flag_floor_px=FLAG_FLOOR_PX):
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
    used = det
    x, cov = _tt_fit(K, dist, obj, pts_all, [ang[n] for n in used])
    flagged = []
    for _pass in range(2):
        res = _tt_residuals(x, K, dist, obj, [ang[n] for n in det], pts_all).reshape(len(det), -1, 2)
        per = np.sqrt(np.mean(np.sum(res**2, axis=2), axis=1))
        if _pass == 1:
            break
        thr = _threshold(per, flag_factor, flag_floor_px)
        bad = per > thr
        keep = [n for n, b in zip(det, bad) if not b]
        if not bad.any() or len(keep) < 2 or _distinct_angles([ang[n] for n in keep]) < 2:
            break
        flagged = [n for n, b in zip(det, bad) if b]
        used = keep
        x, cov = _tt_fit(K, dist, obj, np.stack([corners[n] for n in used]), [ang[n] for n in used], x0=x)
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


# ================================================================= session
def calibrate_session(session, *, progress=None):
    """Calibrate a session from its board images: the content of ``calibration.json``.

    Intrinsics come from ``session.json``'s ``camera`` when given (no fit),
    otherwise from ``calibration.intrinsic_images``; the turntable fit runs
    when ``calibration.turntable_images`` are given.

    Parameters
    ----------
    session : Session
    progress : callable, optional
        ``progress(done, total)`` over all calibration images.

    Returns
    -------
    dict
        ``camera``: ``K``, ``dist``, ``image_size``, ``rms_px`` (None when the
        intrinsics were given), ``source``, and for a fit ``std``,
        ``uncertainty_3sigma``, per-image ``images`` (RMS, board pose,
        detected corners ``corners_px``) and
        ``rejected``; ``turntable`` (when turntable images are given):
        ``R_cam``, ``t_cam``, ``rms_px``, per-image ``images``, ``flagged``,
        ``rejected``, ``axis``, ``std``; ``pattern``.

    Raises
    ------
    CalibrationError
    """
    where = session.json_path
    need_intr = session.camera is None
    n_intr = len(session.intrinsic_images) if need_intr else 0
    n_tt = len(session.turntable_images)
    if need_intr and n_intr == 0:
        raise CalibrationError(f"{where}: no intrinsics: give 'camera' or 'calibration.intrinsic_images'")
    if (n_intr or n_tt) and session.pattern is None:
        raise CalibrationError(f"{where}: pattern is required to calibrate from board images: {{'inner_corners': [cols, rows], 'square_size': mm}}")
    total = n_intr + n_tt

    def sub(offset):
        if progress is None:
            return None
        return lambda done, _n: progress(offset + done, total)

    out = {"format": "organlab.calibration/1"}
    if session.pattern is not None:
        out["pattern"] = {"inner_corners": list(session.pattern.inner_corners), "square_size": session.pattern.square_size}
    if need_intr:
        imgs = [session.read(pth, key=f"calibration.intrinsic_images[{i}]", grey=True) for i, pth in enumerate(session.intrinsic_images)]
        names = [session.relpath(pth) for pth in session.intrinsic_images]
        try:
            intr = calibrate_intrinsics(imgs, session.pattern, image_size=session.image_size, names=names, progress=sub(0))
        except CalibrationError as e:
            raise CalibrationError(f"{where}: calibration.intrinsic_images: {e}") from None
        camera = intr.camera
        out["camera"] = intr.to_dict()
    else:
        camera = session.given_camera()
        d = camera.intrinsics_dict()
        d.update(rms_px=None, source="session.json")
        out["camera"] = d
    if n_tt:
        imgs = [session.read(pth, key=f"calibration.turntable_images[{i}].image", grey=True) for i, (pth, _) in enumerate(session.turntable_images)]
        names = [session.relpath(pth) for pth, _ in session.turntable_images]
        angles = [a for _, a in session.turntable_images]
        try:
            tt = calibrate_turntable(imgs, angles, camera, session.pattern, names=names, progress=sub(n_intr))
        except CalibrationError as e:
            raise CalibrationError(f"{where}: calibration.turntable_images: {e}") from None
        out["turntable"] = tt.to_dict()
    return out


def write_calibration(session, calib):
    """Write ``calib`` (from :func:`calibrate_session`) to ``session/calibration.json``.

    Returns
    -------
    Path
    """
    if not isinstance(calib, dict) or "camera" not in calib:
        raise CalibrationError("calibration to write must be the dict returned by calibrate_session (with 'camera')")
    path = session.calibration_path
    write_json(path, calib)
    return path


# ================================================================= figures
_GREEN = (40, 220, 40)
_RED = (255, 60, 60)
_YELLOW = (255, 220, 0)
_CYAN = (0, 220, 255)


def _pts(uv, scale):
    return [(int(round(u * scale * 16)), int(round(v * scale * 16))) for u, v in uv if np.isfinite(u) and np.isfinite(v)]


def _draw(img, detected, reprojected, scale, lines, extra=None):
    import cv2

    out = cv2.resize(img, None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST) if scale != 1 else img.copy()
    if out.ndim == 2:
        out = cv2.cvtColor(out, cv2.COLOR_GRAY2RGB)
    if extra is not None:
        extra(out)
    if reprojected is not None:
        for p in _pts(reprojected, scale):
            cv2.circle(out, p, 5 * 16, _RED, 1, cv2.LINE_AA, shift=4)
    if detected is not None:
        for (u, v) in _pts(detected, scale):
            cv2.drawMarker(out, (u // 16, v // 16), _GREEN, cv2.MARKER_CROSS, 9, 1, cv2.LINE_AA)
    y = 18
    for text in lines:
        (tw, th), base = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, 0.5, 1)
        cv2.rectangle(out, (4, y - th - 3), (12 + tw, y + base), (0, 0, 0), -1)
        cv2.putText(out, text, (8, y), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA)
        y += 20
    return out


def _save(path, rgb):
    import cv2

    ok, buf = cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    if not ok:
        raise CalibrationError(f"{path}: could not encode the figure")
    Path(path).write_bytes(buf.tobytes())
    return Path(path)


def _fig_name(name):
    stem = str(name).replace("\\", "/").rsplit(".", 1)[0]
    return stem.replace("/", "_") + ".png"


def _corners_entry(corners, name):
    """``{"corners_px": [[u, v], ...]}`` for calibration.json, or ``{}``."""
    c = corners.get(name)
    return {} if c is None else {"corners_px": np.round(np.asarray(c, float).reshape(-1, 2), 4).tolist()}


def _stored_corners(entry):
    """The detected corners kept in calibration.json for one image, or None."""
    if not entry or "corners_px" not in entry:
        return None
    return np.asarray(entry["corners_px"], dtype=np.float64).reshape(-1, 2)


def check_figures(session, calib, out_dir):
    """Draw detected (+, green) and reprojected (o, red) corners over every calibration image.

    As the thesis's Figure 1: a good calibration puts every circle on its
    cross.  Turntable images also show the table axis (yellow, from the
    board surface up) and the circle that the board's first corner sweeps as
    the table turns (cyan): every image's first corner must lie on it.

    Parameters
    ----------
    session : Session
    calib : dict
        From :func:`calibrate_session` (or ``calibration.json``).  The
        detected corners it keeps per image (``corners_px``) are drawn as
        they are; an image without them (rejected, or an older file) is
        detected again.
    out_dir : str or Path
        Created when missing; one PNG per calibration image.

    Returns
    -------
    list of Path
    """
    import cv2

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    cam_d = calib["camera"]
    camera = Camera(cam_d["K"], cam_d["dist"], image_size=tuple(cam_d.get("image_size", session.image_size)))
    pattern = session.pattern
    if pattern is None and ((cam_d.get("source") == "calibrated" and session.intrinsic_images) or calib.get("turntable")):
        raise CalibrationError(
            f"{session.json_path}: pattern is required to draw the calibration figures: "
            "{'inner_corners': [cols, rows], 'square_size': mm}"
        )
    obj = None if pattern is None else board_points(pattern)
    scale = 2 if camera.width < 1000 else 1
    paths = []

    if cam_d.get("source") == "calibrated":
        per = cam_d.get("images", {})
        rej = cam_d.get("rejected", {})
        for pth in session.intrinsic_images:
            name = session.relpath(pth)
            img = session.read(pth, key="calibration.intrinsic_images", grey=False)
            det = _stored_corners(per.get(name))
            if det is None:
                det = detect_board(img, pattern)
            rep = None
            lines = [f"intrinsic {name}"]
            if name in per:
                e = per[name]
                cam = camera.with_pose(cv2.Rodrigues(np.asarray(e["rvec"], float))[0], e["tvec"])
                rep = cam.project(obj)
                lines.append(f"RMS {e['rms_px']:.3f} px  (all images {cam_d['rms_px']:.3f} px)")
            if name in rej:
                lines.append(f"REJECTED: {rej[name]}")
            lines.append("+ detected   o reprojected")
            paths.append(_save(out_dir / ("intrinsic_" + _fig_name(name)), _draw(img, det, rep, scale, lines)))

    tt = calib.get("turntable")
    if tt:
        cam0 = camera.with_pose(tt["R_cam"], tt["t_cam"])
        off = np.array(tt["axis"]["board_offset_mm"] + [0.0])
        X0 = obj + off
        radius = float(np.hypot(*off[:2]))
        height = float(np.ptp(obj[:, 0]))
        ts = np.linspace(0, 2 * np.pi, 181)
        circle = np.stack([radius * np.cos(ts), radius * np.sin(ts), np.zeros_like(ts)], axis=1)
        axis_pts = np.array([[0.0, 0.0, z] for z in np.linspace(0.0, height, 11)])
        images = tt.get("images", {})
        for pth, angle in session.turntable_images:
            name = session.relpath(pth)
            img = session.read(pth, key="calibration.turntable_images", grey=False)
            cam = cam0.at_table_angle(angle)
            det = _stored_corners(images.get(name))
            if det is None:
                det = detect_board(img, pattern, require_orientation=True)
            rep = cam.project(X0)
            circ = cam.project(circle)
            ax = cam.project(axis_pts)

            def extra(out, circ=circ, ax=ax, rep=rep):
                poly = np.array(_pts(circ, scale), np.int32)
                if len(poly) > 1:
                    cv2.polylines(out, [poly], False, _CYAN, 1, cv2.LINE_AA, shift=4)
                axp = np.array(_pts(ax, scale), np.int32)
                if len(axp) > 1:
                    cv2.polylines(out, [axp], False, _YELLOW, 2, cv2.LINE_AA, shift=4)
                o = _pts(rep[:1], scale)
                if o:
                    cv2.circle(out, o[0], 9 * 16, _CYAN, 2, cv2.LINE_AA, shift=4)

            lines = [f"turntable {name}  angle {angle:g} deg"]
            if name in images:
                e = images[name]
                lines.append(f"RMS {e['rms_px']:.3f} px  (joint fit {tt['rms_px']:.3f} px)" + ("  FLAGGED: board moved?" if e.get("flagged") else ""))
            if name in tt.get("rejected", {}):
                lines.append(f"REJECTED: {tt['rejected'][name]}")
            lines.append("+ detected  o reprojected  | axis  O sweep of first corner")
            paths.append(_save(out_dir / ("turntable_" + _fig_name(name)), _draw(img, det, rep, scale, lines, extra)))
    return paths
