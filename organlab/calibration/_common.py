"""Shared pieces of the calibration fits: thresholds, geometry, input checks, file entries."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..camera import distort
from ..errors import CalibrationError
from ..session import read_image

#: Factor on the median per-image RMS above which an image is rejected/flagged.
REJECT_FACTOR = 3.0
#: Floor of the rejection threshold, px (intrinsic images).
REJECT_FLOOR_PX = 0.5
#: Floor of the "board moved" threshold, px (turntable images).
FLAG_FLOOR_PX = 1.0
_HALF_CAP = 8
#: Upsampling factor of the final corner measurement (:func:`_refine_upsampled`).
_UPSAMPLE = 2


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


def _corners_entry(corners, name):
    """``{"corners_px": [[u, v], ...]}`` for calibration.json, or ``{}``."""
    c = corners.get(name)
    return {} if c is None else {"corners_px": np.round(np.asarray(c, float).reshape(-1, 2), 4).tolist()}


def _stored_corners(entry):
    """The detected corners kept in calibration.json for one image, or None."""
    if not entry or "corners_px" not in entry:
        return None
    return np.asarray(entry["corners_px"], dtype=np.float64).reshape(-1, 2)

