"""The checkerboard: its corners in the board frame, and their detection in an image, in board order."""

from __future__ import annotations

import hashlib
import os
import threading
from collections import OrderedDict
from pathlib import Path

import numpy as np

from ..errors import CalibrationError
from ..session import Pattern
from . import _common
from ._common import _HALF_CAP, _UPSAMPLE

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


def board_points(pattern: Pattern) -> np.ndarray:
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

    Its cost (~0.2 s CPU per 640x480 image, ~70 % of it ``CALIB_CB_ACCURACY``)
    was measured against cheaper variants on 2026-12-03 (corner RMS against
    truth, mean: sample intrinsic / sample turntable / 24 rendered boards of
    another seed; sample calibration's CPU): this one 0.022 / 0.042 / 0.055 px,
    4.05 s; x1.5 0.023 / 0.072 / 0.048 px, 2.60 s; x1.75 0.022 / 0.056 /
    0.052 px, 3.19 s; pad 0.6 square 0.023 / 0.048 / 0.058 px, 3.44 s; pad
    0.8 square 0.022 / 0.043 / 0.056 px, ~5 % less; without
    ``CALIB_CB_ACCURACY`` 0.029 / 0.068 / 0.060 px, 1.26 s; x3 without it
    0.029 / 0.049 / 0.073 px.  Each lost accuracy somewhere, so repeated
    detections are cached instead (:func:`_detect`).
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


# Detections of this process, keyed by the grey image's bytes and the board's
# inner corners (all that _find_corners and _orient read).  The accurate pass
# (_refine_upsampled) costs ~0.15-0.25 s per 640x480 image, ~4 s for the
# sample's 25 calibration images; the same images are detected again when a
# user calibrates again, the check figures and the capture audit look at them,
# and the test suite calibrates the sample ~25 times.  A hit returns the
# identical result, as copies.  ~1 KB per entry, at most _CACHE_SIZE entries.
_CACHE_SIZE = 512
_cache: OrderedDict = OrderedDict()
_cache_lock = threading.Lock()

#: Environment variable naming a folder where detections are also kept across processes (off when unset or
#: empty): a run of many fresh processes over the same board images (the test suite's notebook kernels and
#: command-line subprocesses, a class's notebooks) detects each image once.  One small ``.npz`` per image
#: (corners and orientation, no pickle), named by the key above and by a digest of the detector's code
#: (this module, ``_common``) and OpenCV's version, so that a changed detector never reads an old result.
#: Written to a temporary name and renamed (processes may share the folder); an unreadable file is
#: detected again.  Delete the folder to drop it.
DETECTION_CACHE_ENV = "ORGANLAB_DETECTION_CACHE"
_code_digest = None


def _disk_file(key):
    """The cache file of ``key`` under $ORGANLAB_DETECTION_CACHE, or None when that is unset."""
    global _code_digest
    folder = os.environ.get(DETECTION_CACHE_ENV)
    if not folder:
        return None
    if _code_digest is None:
        import cv2

        h = hashlib.blake2b(cv2.__version__.encode(), digest_size=8)
        for mod in (__file__, _common.__file__):
            h.update(Path(mod).read_bytes())
        _code_digest = h.hexdigest()
    (h, w), (nx, ny), digest = key
    return Path(folder) / f"{h}x{w}-{nx}x{ny}-{digest.hex()}-{_code_digest}.npz"


def _disk_read(path):
    import zipfile

    try:
        with open(path, "rb") as fh, np.load(fh, allow_pickle=False) as z:  # (np.load leaves a damaged file open)
            corners, oriented = np.array(z["corners"], np.float64), bool(z["oriented"])
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile):  # absent, or damaged: measured again
        return None
    if corners.ndim != 2 or corners.shape[1:] != (2,):
        return None
    return (None if corners.size == 0 else corners), oriented


def _disk_write(path, hit):
    corners, oriented = hit
    tmp = path.with_name(f".{path.stem}.{os.getpid()}.{threading.get_ident()}.tmp.npz")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        np.savez(tmp, corners=np.zeros((0, 2)) if corners is None else corners, oriented=np.bool_(oriented))
        os.replace(tmp, path)
    except OSError:  # a read-only or full disk: the cache is only an optimisation
        tmp.unlink(missing_ok=True)


def _detect(image, pattern):
    grey = _as_grey(image)
    key = (grey.shape, tuple(pattern.inner_corners), hashlib.blake2b(grey.data, digest_size=20).digest())
    with _cache_lock:
        hit = _cache.get(key)
        if hit is not None:
            _cache.move_to_end(key)
    if hit is None:
        disk = _disk_file(key)
        hit = None if disk is None else _disk_read(disk)
        if hit is None:
            raw = _find_corners(grey, pattern.inner_corners)
            hit = (None, False) if raw is None else _orient(grey, raw, pattern.inner_corners)
            if disk is not None:
                _disk_write(disk, hit)
        with _cache_lock:
            _cache[key] = hit
            while len(_cache) > _CACHE_SIZE:
                _cache.popitem(last=False)
    corners, oriented = hit
    return (None if corners is None else corners.copy()), oriented


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


def detect_board(image: np.ndarray, pattern: Pattern, *, require_orientation: bool = False) -> np.ndarray | None:
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
    cannot change the board frame.  The result is kept for the process
    (keyed by the grey pixels and ``inner_corners``): detecting the same
    image again returns the same corners without measuring them again;
    with the environment variable ``ORGANLAB_DETECTION_CACHE`` naming a
    folder, also for the processes started later that name the same folder.

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

