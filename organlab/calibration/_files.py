"""Reading and writing camera calibrations made by other tools.

Labs keep calibrations made with Bouguet's *Camera Calibration Toolbox for
Matlab* (``Calib_Results.m``) or with OpenCV's calibration sample (a YAML or
XML file with ``camera_matrix`` and ``distortion_coefficients``).  Both use
the same camera model as organlab (:class:`~organlab.camera.Camera`):

* Bouguet: ``fc`` (2), ``cc`` (2), ``alpha_c``, ``kc = [k1, k2, p1, p2, k3]``,
  image size ``nx`` x ``ny``; the pixel ``[0, 0]`` is the centre of the upper
  left pixel, as in OpenCV and organlab, so no half-pixel shift is applied.
  The toolbox's ``fc_error``, ``cc_error``, ``alpha_c_error`` and ``kc_error``
  are about three standard deviations; they are returned unchanged.
* OpenCV: ``camera_matrix`` (3x3), ``distortion_coefficients`` (4, 5 or more;
  coefficients beyond ``k3`` must be zero), ``image_width``,
  ``image_height``, read and written with :class:`cv2.FileStorage`.
"""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np

from ..validate import read_json
from ..camera import Camera
from ..errors import CalibrationError
from ._storage import read_storage

__all__ = [
    "read_bouguet",
    "write_bouguet",
    "read_opencv",
    "write_opencv",
    "read_camera",
]

_ASSIGN = re.compile(r"^\s*([A-Za-z_]\w*)\s*=\s*(.+?)\s*;?\s*$")  # on a line stripped of its % comment
_NUMBER = r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?|[-+]?(?:Inf|NaN)"


def _parse_matlab_value(text):
    """A number or a ``[a ; b ; ...]`` / ``[a b c]`` vector, else None."""
    text = text.strip().rstrip(";").strip()
    if text.startswith("[") and text.endswith("]"):
        body = text[1:-1].replace(";", " ").replace(",", " ")
        toks = body.split()
        if not toks or not all(re.fullmatch(_NUMBER, t) for t in toks):
            return None
        return np.array([float(t) for t in toks])
    if re.fullmatch(_NUMBER, text):
        return float(text)
    return None


def _bouguet_values(path):
    out = {}
    for line in Path(path).read_text(encoding="utf-8", errors="replace").splitlines():
        s = line.split("%", 1)[0].strip()
        if not s:
            continue
        m = _ASSIGN.match(s)
        if m is None:
            continue
        v = _parse_matlab_value(m.group(2))
        if v is not None:
            out[m.group(1)] = v
    return out


def read_bouguet(path: str | Path, *, image_size: tuple[int, int] | None = None) -> tuple[Camera, dict]:
    """Read Bouguet's toolbox ``Calib_Results.m``.

    Parameters
    ----------
    path : str or Path
        The ``Calib_Results.m`` file written by the toolbox's *Save*.
    image_size : (2,) int, optional
        ``(width, height)`` in px; needed only when the file has no ``nx``,
        ``ny``.

    Returns
    -------
    camera : Camera
        Intrinsics (identity pose).
    errors : dict
        The toolbox's uncertainties when present: any of ``fc_error`` (2,),
        ``cc_error`` (2,), ``alpha_c_error`` float, ``kc_error`` (5,); px for
        ``fc``/``cc``, unitless otherwise.  The toolbox states them as about
        three times the standard deviations.

    Raises
    ------
    CalibrationError
        When the file is missing or lacks ``fc``, ``cc`` or the image size.
    """
    path = Path(path)
    if not path.is_file():
        raise CalibrationError(f"{path}: no such file; give the Calib_Results.m saved by Bouguet's toolbox")
    v = _bouguet_values(path)
    for key in ("fc", "cc"):
        if key not in v or np.size(v[key]) != 2:
            raise CalibrationError(f"{path}: {key} is missing or not a 2-vector; is it a Calib_Results.m file?")
    try:
        fc, cc = np.asarray(v["fc"], float).ravel(), np.asarray(v["cc"], float).ravel()
        alpha = float(np.asarray(v.get("alpha_c", 0.0), float).ravel()[0])
        kc = np.zeros(5)
        k = np.atleast_1d(np.asarray(v.get("kc", []), float)).ravel()
        size = (int(np.asarray(v["nx"]).ravel()[0]), int(np.asarray(v["ny"]).ravel()[0])) if "nx" in v and "ny" in v else None
    except (TypeError, ValueError, IndexError, OverflowError) as e:
        raise CalibrationError(f"{path}: fc, cc, alpha_c, kc, nx, ny must be numbers ({e}); is it a Calib_Results.m file?") from None
    if not (np.all(np.isfinite(fc)) and np.all(np.isfinite(cc)) and np.isfinite(alpha) and np.all(np.isfinite(k))):
        raise CalibrationError(f"{path}: fc, cc, alpha_c and kc must be finite numbers; is it a Calib_Results.m file?")
    if k.size > 5:
        raise CalibrationError(f"{path}: kc has {k.size} coefficients; at most 5 [k1, k2, p1, p2, k3] are supported")
    kc[: k.size] = k
    if size is not None:
        pass
    elif image_size is not None:
        size = tuple(int(s) for s in image_size)
    else:
        raise CalibrationError(f"{path}: nx, ny (image size) are missing; pass image_size=(width, height)")
    K = np.array([[fc[0], alpha * fc[0], cc[0]], [0.0, fc[1], cc[1]], [0.0, 0.0, 1.0]])
    try:
        camera = Camera(K, kc, image_size=size)
    except ValueError as e:
        raise CalibrationError(f"{path}: {e}") from None
    errors = {}
    for key, n in (("fc_error", 2), ("cc_error", 2), ("alpha_c_error", 1), ("kc_error", 5)):
        if key in v:
            try:
                e = np.atleast_1d(np.asarray(v[key], float)).ravel()
            except (TypeError, ValueError):
                continue  # an uncertainty that is not numbers: left out
            if e.size == 0 or not np.all(np.isfinite(e)):
                continue
            if key == "alpha_c_error":
                errors[key] = float(e[0])
            else:
                full = np.zeros(n)
                full[: min(n, e.size)] = e[:n]
                errors[key] = full
    return camera, errors


def _fmt_vec(a):
    return "[ " + " ; ".join(f"{x:.15f}" for x in np.ravel(a)) + " ]"


def write_bouguet(path: str | Path, camera: Camera, *, errors: dict | None = None) -> Path:
    """Write intrinsics as Bouguet's toolbox ``Calib_Results.m``.

    Parameters
    ----------
    path : str or Path
    camera : Camera
        Its intrinsics and ``image_size`` are written.
    errors : dict, optional
        ``fc_error``, ``cc_error``, ``alpha_c_error``, ``kc_error`` (the
        toolbox's convention: about three standard deviations).

    Returns
    -------
    Path
    """
    K = camera.K
    fc = [K[0, 0], K[1, 1]]
    cc = [K[0, 2], K[1, 2]]
    lines = [
        "% Intrinsic camera parameters (written by organlab, Bouguet's Calib_Results.m layout)",
        "",
        "%-- Focal length:",
        f"fc = {_fmt_vec(fc)};",
        "",
        "%-- Principal point:",
        f"cc = {_fmt_vec(cc)};",
        "",
        "%-- Skew coefficient:",
        f"alpha_c = {camera.skew:.15f};",
        "",
        "%-- Distortion coefficients:",
        f"kc = {_fmt_vec(camera.dist)};",
        "",
    ]
    errors = errors or {}
    titles = {
        "fc_error": "Focal length uncertainty",
        "cc_error": "Principal point uncertainty",
        "alpha_c_error": "Skew coefficient uncertainty",
        "kc_error": "Distortion coefficients uncertainty",
    }
    for key, title in titles.items():
        if key in errors:
            val = errors[key]
            txt = f"{float(val):.15f}" if np.ndim(val) == 0 else _fmt_vec(val)
            lines += [f"%-- {title}:", f"{key} = {txt};", ""]
    lines += ["%-- Image size:", f"nx = {camera.width};", f"ny = {camera.height};", ""]
    path = Path(path)
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


def read_opencv(path: str | Path) -> tuple[Camera, dict]:
    """Read an OpenCV calibration file (YAML or XML).

    Parameters
    ----------
    path : str or Path
        A file as written by OpenCV's calibration sample: ``camera_matrix``,
        ``distortion_coefficients``, ``image_width``, ``image_height``.

    Returns
    -------
    camera : Camera
        Intrinsics (identity pose).
    extra : dict
        ``avg_reprojection_error`` (px) and ``per_view_reprojection_errors``
        ((N,) float64, px) when present.

    Raises
    ------
    CalibrationError
        When a key is missing or the distortion model is not the 5-coefficient
        one.
    """
    path = Path(path)
    if not path.is_file():
        raise CalibrationError(f"{path}: no such file; give an OpenCV calibration YAML/XML file")
    doc = read_storage(path)  # not cv2.FileStorage: it aborts the process on some damaged files
    K = doc.get("camera_matrix")
    if not isinstance(K, np.ndarray) or K.shape != (3, 3):
        raise CalibrationError(f"{path}: camera_matrix is missing or not 3x3")
    d = doc.get("distortion_coefficients")
    if d is not None and not isinstance(d, np.ndarray):
        raise CalibrationError(f"{path}: distortion_coefficients must be an opencv-matrix")
    d = np.zeros(5) if d is None else d.ravel()
    if d.size > 5 and np.any(d[5:] != 0):
        raise CalibrationError(
            f"{path}: distortion_coefficients has non-zero terms beyond k3 (rational/thin-prism model); "
            "only [k1, k2, p1, p2, k3] is supported"
        )
    dist = np.zeros(5)
    dist[: min(5, d.size)] = d[:5]
    w, h = doc.get("image_width"), doc.get("image_height")
    if w is None or h is None:
        raise CalibrationError(f"{path}: image_width / image_height are missing")
    if not all(_is_number(v) and math.isfinite(v) and 0 < v < 2**31 for v in (w, h)):
        raise CalibrationError(f"{path}: image_width / image_height must be positive finite numbers")
    size = (int(w), int(h))
    extra = {}
    rms = doc.get("avg_reprojection_error")
    if rms is not None:
        if not _is_number(rms):
            raise CalibrationError(f"{path}: avg_reprojection_error must be a number")
        extra["avg_reprojection_error"] = float(rms)
    per_view = doc.get("per_view_reprojection_errors")
    if per_view is not None:
        if not isinstance(per_view, np.ndarray):
            raise CalibrationError(f"{path}: per_view_reprojection_errors must be an opencv-matrix")
        extra["per_view_reprojection_errors"] = per_view.ravel()
    try:
        camera = Camera(np.asarray(K, float), dist, image_size=size)
    except ValueError as e:
        raise CalibrationError(f"{path}: {e}") from None
    return camera, extra


def _is_number(v):
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def write_opencv(path: str | Path, camera: Camera, *, rms_px: float | None = None) -> Path:
    """Write intrinsics as OpenCV's calibration sample does (YAML or XML by extension).

    Parameters
    ----------
    path : str or Path
        ``.yml``/``.yaml`` or ``.xml``.
    camera : Camera
    rms_px : float, optional
        Written as ``avg_reprojection_error``.

    Returns
    -------
    Path
    """
    import cv2

    path = Path(path)
    if path.suffix.lower() not in (".yml", ".yaml", ".xml"):
        raise CalibrationError(f"{path}: use a .yml, .yaml or .xml file name for an OpenCV calibration file")
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    try:
        fs.write("image_width", int(camera.width))
        fs.write("image_height", int(camera.height))
        fs.write("camera_matrix", np.asarray(camera.K, float))
        fs.write("distortion_coefficients", np.asarray(camera.dist, float).reshape(5, 1))
        if rms_px is not None:
            fs.write("avg_reprojection_error", float(rms_px))
    finally:
        fs.release()
    return path


def read_camera(path: str | Path, *, image_size: tuple[int, int] | None = None) -> Camera:
    """Read intrinsics from a ``Calib_Results.m``, OpenCV YAML/XML or organlab JSON file.

    Parameters
    ----------
    path : str or Path
    image_size : (2,) int, optional
        ``(width, height)``, for files that do not store it.

    Returns
    -------
    Camera
        Intrinsics, identity pose.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".m":
        return read_bouguet(path, image_size=image_size)[0]
    if suffix in (".yml", ".yaml", ".xml"):
        return read_opencv(path)[0]
    if suffix == ".json":
        d = read_json(path, error=CalibrationError, fix="give a calibration.json or a JSON file with 'camera'")
        d = d.get("camera", d) if isinstance(d, dict) else d
        try:
            return Camera.from_dict(d, image_size=image_size)
        except (KeyError, TypeError, ValueError, AttributeError, IndexError, OverflowError) as e:
            raise CalibrationError(f"{path}: not a camera ({e}); it needs K, dist and image_size") from None
    raise CalibrationError(f"{path}: unknown calibration format; use Calib_Results.m, .yml/.yaml/.xml or .json")
