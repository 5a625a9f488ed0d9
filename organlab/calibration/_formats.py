"""Cameras made by other tools, in and out: Middlebury, COLMAP, Bouguet, OpenCV, Meshroom.

Published data sets and rigs calibrated elsewhere come with their cameras.
:func:`read_cameras` reads them into organlab's :class:`~organlab.camera.Camera`
(intrinsics shared by every view, one world-to-camera pose per image where the
file has them, translations in mm); :func:`write_cameras` writes them back so
another multi-view-stereo program can run on organlab's cameras.

=============  ===========================  ======================================  =========
format         file                         poses                                   units
=============  ===========================  ======================================  =========
``middlebury`` ``*_par.txt``                ``name K R t`` per line, x = K [R|t] X  metres
``colmap``     ``cameras.txt`` +            quaternion ``qw qx qy qz`` and ``t``,   the model's
               ``images.txt`` (a folder     world to camera; models SIMPLE_PINHOLE,  (SfM scale)
               or either file)              PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV,
                                            FULL_OPENCV (k4-k6 = 0)
``bouguet``    ``Calib_Results.m``          ``Rc_i``/``Tc_i`` (or ``omc_i``), in     the board's
                                            image order                             (mm)
``opencv``     ``.yml``/``.yaml``/``.xml``  ``views`` (``image``, ``rvec``,         mm
                                            ``tvec``) or ``extrinsic_parameters``
                                            (N x 6, image order)
``meshroom``   ``cameras.sfm`` (write only) AliceVision SfMData JSON 1.2.5
=============  ===========================  ======================================  =========

Conventions converted on the way: COLMAP puts the centre of the upper left pixel at
(0.5, 0.5), organlab (like OpenCV, Bouguet, Middlebury) at (0, 0), so
``cx = cx_colmap - 0.5``; COLMAP quaternions are Hamilton ``(w, x, y, z)`` of
``R_cam_world``.  AliceVision stores ``R_cam_world`` column by column and the
camera centre, and its principal point relative to the image centre.

Every reader checks what it reads (numbers finite, integers where integers,
focal lengths > 0, rotations orthonormal to :data:`~organlab.camera.ROTATION_TOLERANCE`,
then snapped to the nearest rotation) and stops at the first problem with one line
naming the file and the line (:class:`~organlab.errors.CalibrationError`).
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from . import _files as calibio
from .. import validate
from ..camera import Camera, nearest_rotation
from ..errors import CalibrationError
from ._storage import read_storage

__all__ = ["CAMERA_FORMATS", "CameraFile", "camera_format", "export_cameras", "read_cameras", "write_cameras"]

#: Formats :func:`read_cameras` reads (all but ``meshroom``) and :func:`write_cameras` writes.
CAMERA_FORMATS = ("middlebury", "colmap", "bouguet", "opencv", "meshroom")

#: mm per file unit of the translations, by format (Middlebury's files are in metres).
_DEFAULT_SCALE = {"middlebury": 1000.0, "colmap": 1.0, "bouguet": 1.0, "opencv": 1.0}


def camera_format(path: str | Path) -> str:
    """The format of a camera file, from its name (see the module docstring).

    Parameters
    ----------
    path : str or Path

    Returns
    -------
    str
        One of ``middlebury``, ``colmap``, ``bouguet``, ``opencv``.

    Raises
    ------
    CalibrationError
        A name none of them uses.
    """
    p = Path(path)
    name = p.name.lower()
    if p.is_dir() or name in ("cameras.txt", "images.txt"):
        return "colmap"
    if name.endswith("_par.txt"):
        return "middlebury"
    if p.suffix.lower() == ".m":
        return "bouguet"
    if p.suffix.lower() in (".yml", ".yaml", ".xml"):
        return "opencv"
    raise CalibrationError(
        f"{p}: unknown camera file; give a Middlebury *_par.txt, a COLMAP model (folder with cameras.txt and "
        "images.txt), Bouguet's Calib_Results.m or an OpenCV .yml/.yaml/.xml"
    )


def read_cameras(path: str | Path, *, image_size: tuple[int, int] | None = None,
                 scale: float | None = None) -> CameraFile:
    """Read the cameras of another tool's file.

    Parameters
    ----------
    path : str or Path
        A Middlebury ``*_par.txt``, a COLMAP text model (its folder, or its
        ``cameras.txt`` or ``images.txt``), a Bouguet ``Calib_Results.m``, or
        an OpenCV YAML/XML file.
    image_size : (2,) int, optional
        ``(width, height)`` in px of the images; required for a Middlebury
        file (it does not store it), checked against files that do.
    scale : float, optional
        mm per unit of the file's translations.  Default: 1000 for
        Middlebury (metres), 1 otherwise (mm; a COLMAP model made by
        structure from motion has an arbitrary scale: give it here).

    Returns
    -------
    CameraFile

    Raises
    ------
    CalibrationError
        One line naming the file (and the line) at fault.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> from organlab.synthetic import default_camera
    >>> cam = default_camera((320, 240))
    >>> folder = pathlib.Path(tempfile.mkdtemp())
    >>> _ = write_cameras(folder / "colmap", [cam.at_table_angle(a) for a in (0, 90)], ["000.png", "090.png"],
    ...                   format="colmap")
    >>> back = read_cameras(folder / "colmap")
    >>> back.format, list(back.poses), bool(np.allclose(back.camera.K, cam.K))
    ('colmap', ['000.png', '090.png'], True)
    """
    fmt = camera_format(path)
    path = Path(path)
    if scale is None:
        scale = _DEFAULT_SCALE[fmt]
    if not (isinstance(scale, (int, float)) and math.isfinite(scale) and scale > 0):
        raise CalibrationError(f"{path}: the scale (mm per file unit) must be a finite number > 0, got {scale!r}")
    reader = {"middlebury": _read_middlebury, "colmap": _read_colmap, "bouguet": _read_bouguet, "opencv": _read_opencv}[fmt]
    camera, poses, notes, src = reader(path, image_size)
    poses = {name: (R, np.asarray(t, np.float64) * float(scale)) for name, (R, t) in poses.items()}
    if scale != 1.0:
        notes.append(f"translations x {float(scale):g} (mm per file unit)")
    return CameraFile(src, fmt, camera, poses, tuple(notes))


def write_cameras(path: str | Path, cameras: Sequence[Camera], names: Sequence[str], *, format: str) -> list[Path]:
    """Write posed cameras for another tool.

    Parameters
    ----------
    path : str or Path
        ``colmap``: a folder (``cameras.txt``, ``images.txt``, an empty
        ``points3D.txt``); ``meshroom``: the ``.sfm`` file; ``middlebury``: the
        ``*_par.txt``; ``bouguet``: the ``Calib_Results.m``; ``opencv``: a
        ``.yml``/``.yaml``/``.xml`` file.
    cameras : sequence of Camera
        World to camera, mm, one per image; all with the same intrinsics.
    names : sequence of str
        The images' names (``meshroom``: their paths, made absolute).
    format : {'colmap', 'meshroom', 'middlebury', 'bouguet', 'opencv'}

    Returns
    -------
    list of Path
        The files written.

    Raises
    ------
    CalibrationError
        Cameras with different intrinsics, a distortion the format cannot
        hold, or a skewed camera for COLMAP / Meshroom.
    """
    cameras, names = list(cameras), [str(n) for n in names]
    if format not in CAMERA_FORMATS:
        raise CalibrationError(f"format must be one of {', '.join(CAMERA_FORMATS)}, got {format!r}")
    if not cameras or len(cameras) != len(names):
        raise CalibrationError(f"{path}: give one name per camera (got {len(cameras)} cameras, {len(names)} names)")
    first = cameras[0]
    for n, c in zip(names, cameras):
        if not (np.array_equal(c.K, first.K) and np.array_equal(c.dist, first.dist) and c.image_size == first.image_size):
            raise CalibrationError(f"{path}: {n}'s intrinsics differ from {names[0]}'s; organlab writes one shared camera")
    writer = {"colmap": _write_colmap, "meshroom": _write_meshroom, "middlebury": _write_middlebury,
              "bouguet": _write_bouguet, "opencv": _write_opencv}[format]
    return writer(Path(path), cameras, names)


def export_cameras(result: str | Path, out: str | Path | None = None, *, format: str,
                   images: str | Path | None = None) -> list[Path]:
    """Write the cameras a reconstruction used, for another multi-view-stereo program.

    They are read from ``result/report.json`` (``camera`` and every view's
    ``R``, ``t``: the cameras the carving used, refined ones when the run
    refined them).

    Parameters
    ----------
    result : str or Path
        A folder written by ``organlab reconstruct``.
    out : str or Path, optional
        Default ``result/colmap/`` (COLMAP: a folder) or ``result/cameras.sfm``
        (Meshroom).
    format : {'colmap', 'meshroom'}
        Or any of :data:`CAMERA_FORMATS`.
    images : str or Path, optional
        The folder the views' names are relative to (the session folder);
        Meshroom's paths are made absolute against it (default: the current
        folder).  COLMAP keeps the names (``views/000.png``): give the session
        folder as COLMAP's ``--image_path``.

    Returns
    -------
    list of Path

    Raises
    ------
    CalibrationError
        No ``report.json``, or one without cameras.
    """
    result = Path(result)
    rj = result / "report.json"
    if not rj.is_file():
        raise CalibrationError(f"{rj}: missing; give a folder written by 'organlab reconstruct'")
    report = validate.read_json(rj, error=CalibrationError, fix="run 'organlab reconstruct' again")  # strict, bounded
    try:
        cam = report["camera"]
        base = Camera(cam["K"], cam["dist"], image_size=tuple(cam["image_size"]))
        cams = [base.with_pose(v["R"], v["t"]) for v in report["views"]]
        names = [str(v["image"]) for v in report["views"]]
    except (json.JSONDecodeError, UnicodeDecodeError, KeyError, TypeError, ValueError) as e:
        raise CalibrationError(f"{rj}: has no usable cameras ({type(e).__name__}: {e}); run 'organlab reconstruct' again") from None
    if format == "meshroom":
        root = Path(images if images is not None else ".").absolute()
        names = [str(root / n) for n in names]
    if out is None:
        out = result / ("cameras.sfm" if format == "meshroom" else "colmap" if format == "colmap" else
                        {"middlebury": "cameras_par.txt", "bouguet": "Calib_Results.m", "opencv": "cameras.yml"}.get(format, "cameras"))
    return write_cameras(out, cams, names, format=format)


# --------------------------------------------------------------------------- checks
def _fail(path, line, message):
    where = f"{path}, line {line}" if line else f"{path}"
    raise CalibrationError(f"{where}: {message}")


def _floats(tokens, path, line, what):
    try:
        a = np.array([float(t) for t in tokens], dtype=np.float64)
    except ValueError:
        _fail(path, line, f"{what}: not numbers ({' '.join(tokens)[:60]})")
    if not np.all(np.isfinite(a)):
        _fail(path, line, f"{what}: not finite ({' '.join(tokens)[:60]})")
    return a


def _int(token, path, line, what):
    if not re.fullmatch(r"[+-]?\d+", token):
        _fail(path, line, f"{what} must be an integer, got {token!r}")
    return int(token)


def _rotation(R, path, line, what="R"):
    try:
        return nearest_rotation(R)[0]
    except ValueError as e:
        _fail(path, line, f"{what} {e}")


def _intrinsics(K, dist, size, path, line):
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        _fail(path, line, f"focal length must be > 0, got fx={K[0, 0]:g}, fy={K[1, 1]:g}")
    try:
        return Camera(K, dist, image_size=size)
    except ValueError as e:
        _fail(path, line, str(e))


def _check_size(path, line, size, image_size):
    if image_size is not None and tuple(int(s) for s in image_size) != tuple(size):
        _fail(path, line, f"the cameras are for {size[0]}x{size[1]} images, the images are "
                          f"{image_size[0]}x{image_size[1]}; give the cameras of these images")


def _text_lines(path):
    if not path.is_file():
        raise CalibrationError(f"{path}: no such file")
    try:
        return path.read_text(encoding="utf-8").splitlines()
    except UnicodeDecodeError:
        raise CalibrationError(f"{path}: not a text file") from None


# --------------------------------------------------------------------------- Middlebury
def _read_middlebury(path, image_size):
    lines = _text_lines(path)
    rows = [(i, ln.split()) for i, ln in enumerate(lines, start=1) if ln.strip()]
    if not rows:
        _fail(path, None, "empty; a Middlebury *_par.txt starts with the number of images")
    n = _int(rows[0][1][0], path, rows[0][0], "the first line (the number of images)")
    if len(rows) - 1 != n:
        _fail(path, rows[0][0], f"announces {n} images but has {len(rows) - 1} camera lines")
    if image_size is None:
        _fail(path, None, "a Middlebury file does not store the image size; give image_size=(width, height)")
    camera, poses = None, {}
    for lineno, f in rows[1:]:
        if len(f) != 22:
            _fail(path, lineno, f"expected 'name.png' and 21 numbers (K, R, t), got {len(f)} fields")
        v = _floats(f[1:], path, lineno, "K, R, t")
        K, R, t = v[:9].reshape(3, 3), v[9:18].reshape(3, 3), v[18:]
        cam = _intrinsics(K, None, tuple(image_size), path, lineno)
        if camera is None:
            camera = cam
        elif not np.array_equal(cam.K, camera.K):
            _fail(path, lineno, f"{f[0]}'s K differs from the first image's; organlab sessions have one camera")
        if f[0] in poses:
            _fail(path, lineno, f"{f[0]} is listed twice")
        poses[f[0]] = (_rotation(R, path, lineno), t)
    return camera, poses, [], path


def _write_middlebury(path, cameras, names):
    lines = [str(len(cameras))]
    for n, c in zip(names, cameras):
        if c.dist.any():
            raise CalibrationError(f"{path}: a Middlebury file has no lens distortion; {n}'s camera has {c.dist.tolist()}")
        vals = list(c.K.ravel()) + list(c.R.ravel()) + list(c.t / 1000.0)
        lines.append(" ".join([n] + [repr(float(x)) for x in vals]))
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return [path]


# --------------------------------------------------------------------------- COLMAP
#: COLMAP camera model -> (parameter names); organlab's model holds these (k4-k6 of FULL_OPENCV must be 0).
_COLMAP_MODELS = {
    "SIMPLE_PINHOLE": ("f", "cx", "cy"),
    "PINHOLE": ("fx", "fy", "cx", "cy"),
    "SIMPLE_RADIAL": ("f", "cx", "cy", "k1"),
    "RADIAL": ("f", "cx", "cy", "k1", "k2"),
    "OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"),
    "FULL_OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"),
}


def _quat_to_R(q):
    w, x, y, z = q
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def _R_to_quat(R):
    """Unit quaternion ``(w, x, y, z)``, ``w >= 0``, of a rotation (Shepperd's method, stable for every angle)."""
    m = np.asarray(R, np.float64)
    tr = np.trace(m)
    if tr > max(m[0, 0], m[1, 1], m[2, 2]):
        s = 2.0 * math.sqrt(1.0 + tr)
        q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    else:
        i = int(np.argmax(np.diag(m)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * math.sqrt(1.0 + m[i, i] - m[j, j] - m[k, k])
        q = [0.0, 0.0, 0.0, 0.0]
        q[0] = (m[k, j] - m[j, k]) / s
        q[1 + i] = 0.25 * s
        q[1 + j] = (m[j, i] + m[i, j]) / s
        q[1 + k] = (m[k, i] + m[i, k]) / s
    q = np.array(q)
    return q if q[0] >= 0 else -q


def _colmap_files(path):
    folder = path if path.is_dir() else path.parent
    cams, imgs = folder / "cameras.txt", folder / "images.txt"
    for p in (cams, imgs):
        if not p.is_file():
            raise CalibrationError(f"{p}: missing; a COLMAP text model is cameras.txt and images.txt in one folder "
                                   "(colmap model_converter --output_type TXT writes them)")
    return cams, imgs


def _colmap_camera(fields, path, lineno, image_size):
    if len(fields) < 4:
        _fail(path, lineno, "expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]")
    model = fields[1]
    if model not in _COLMAP_MODELS:
        _fail(path, lineno, f"camera model {model} is not supported (use {', '.join(_COLMAP_MODELS)}; "
                            "or undistort the images with colmap image_undistorter, which writes PINHOLE)")
    size = (_int(fields[2], path, lineno, "WIDTH"), _int(fields[3], path, lineno, "HEIGHT"))
    if min(size) <= 0:
        _fail(path, lineno, f"image size must be > 0, got {size}")
    names = _COLMAP_MODELS[model]
    if len(fields) - 4 != len(names):
        _fail(path, lineno, f"{model} has {len(names)} parameters ({' '.join(names)}), got {len(fields) - 4}")
    p = dict(zip(names, _floats(fields[4:], path, lineno, f"{model} parameters")))
    fx, fy = (p["f"], p["f"]) if "f" in p else (p["fx"], p["fy"])
    if any(p.get(k, 0.0) != 0.0 for k in ("k4", "k5", "k6")):
        _fail(path, lineno, "FULL_OPENCV with k4-k6 (rational model) is not supported; only k1, k2, p1, p2, k3")
    dist = [p.get("k1", 0.0), p.get("k2", 0.0), p.get("p1", 0.0), p.get("p2", 0.0), p.get("k3", 0.0)]
    K = np.array([[fx, 0.0, p["cx"] - 0.5], [0.0, fy, p["cy"] - 0.5], [0.0, 0.0, 1.0]])
    _check_size(path, lineno, size, image_size)
    return _intrinsics(K, dist, size, path, lineno)


def _read_colmap(path, image_size):
    cams_txt, imgs_txt = _colmap_files(path)
    cameras = {}
    for lineno, ln in enumerate(_text_lines(cams_txt), start=1):
        if not ln.strip() or ln.lstrip().startswith("#"):
            continue
        f = ln.split()
        cid = _int(f[0], cams_txt, lineno, "CAMERA_ID")
        cameras[cid] = (_colmap_camera(f, cams_txt, lineno, image_size), lineno)
    if not cameras:
        _fail(cams_txt, None, "no camera")
    poses, used = {}, {}
    lines = [(i, ln) for i, ln in enumerate(_text_lines(imgs_txt), start=1) if not ln.lstrip().startswith("#")]
    k = 0
    while k < len(lines):
        lineno, ln = lines[k]
        if not ln.strip():  # an image's empty POINTS2D line, or a blank line
            k += 1
            continue
        f = ln.split()
        if len(f) < 10:
            _fail(imgs_txt, lineno, "expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME")
        _int(f[0], imgs_txt, lineno, "IMAGE_ID")
        q = _floats(f[1:5], imgs_txt, lineno, "QW QX QY QZ")
        t = _floats(f[5:8], imgs_txt, lineno, "TX TY TZ")
        cid = _int(f[8], imgs_txt, lineno, "CAMERA_ID")
        name = " ".join(f[9:])
        norm = float(np.linalg.norm(q))
        if abs(norm - 1.0) > 1e-3:
            _fail(imgs_txt, lineno, f"the quaternion QW QX QY QZ must have norm 1, got {norm:.6g}")
        if cid not in cameras:
            _fail(imgs_txt, lineno, f"CAMERA_ID {cid} is not in {cams_txt.name}")
        if name in poses:
            _fail(imgs_txt, lineno, f"{name} is listed twice")
        used.setdefault(cid, lineno)
        poses[name] = (_rotation(_quat_to_R(q / norm), imgs_txt, lineno), t)
        k += 2  # the next line lists the image's 2D points
    if not poses:
        _fail(imgs_txt, None, "no image")
    ids = list(used)
    camera = cameras[ids[0]][0]
    for cid in ids[1:]:
        c, lineno = cameras[cid]
        if not (np.array_equal(c.K, camera.K) and np.array_equal(c.dist, camera.dist) and c.image_size == camera.image_size):
            _fail(cams_txt, lineno, f"camera {cid} differs from camera {ids[0]}; organlab sessions have one camera: "
                                    "refine the model with shared intrinsics (colmap mapper --Mapper.single_camera 1)")
    return camera, poses, [], cams_txt.parent


def _colmap_params(camera, where):
    if camera.K[0, 1] != 0:
        raise CalibrationError(f"{where}: COLMAP has no skew; this camera's alpha_c is {camera.skew:g}")
    k1, k2, p1, p2, k3 = camera.dist
    fx, fy, cx, cy = camera.K[0, 0], camera.K[1, 1], camera.K[0, 2] + 0.5, camera.K[1, 2] + 0.5
    if k3 != 0:
        return "FULL_OPENCV", [fx, fy, cx, cy, k1, k2, p1, p2, k3, 0.0, 0.0, 0.0]
    if p1 != 0 or p2 != 0 or k1 != 0 or k2 != 0:
        return "OPENCV", [fx, fy, cx, cy, k1, k2, p1, p2]
    return "PINHOLE", [fx, fy, cx, cy]


def _write_colmap(folder, cameras, names):
    folder.mkdir(parents=True, exist_ok=True)
    model, params = _colmap_params(cameras[0], folder)
    w, h = cameras[0].image_size
    cams = ["# Camera list with one line of data per camera:", "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]",
            "# Number of cameras: 1", f"1 {model} {w} {h} " + " ".join(repr(float(v)) for v in params)]
    imgs = ["# Image list with two lines of data per image:",
            "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME", "#   POINTS2D[] as (X, Y, POINT3D_ID)",
            f"# Number of images: {len(cameras)}, mean observations per image: 0"]
    for i, (n, c) in enumerate(zip(names, cameras), start=1):
        q = _R_to_quat(c.R)
        imgs += [f"{i} " + " ".join(repr(float(v)) for v in (*q, *c.t)) + f" 1 {n}", ""]
    out = [folder / "cameras.txt", folder / "images.txt", folder / "points3D.txt"]
    out[0].write_text("\n".join(cams) + "\n", encoding="utf-8")
    out[1].write_text("\n".join(imgs) + "\n", encoding="utf-8")
    out[2].write_text("# 3D point list (empty: organlab exports cameras only)\n", encoding="utf-8")
    return out


# --------------------------------------------------------------------------- Bouguet
_M_ASSIGN = re.compile(r"^\s*(Rc|Tc|omc)_(\d+)\s*=\s*\[(.*)\]\s*;?\s*$")


_M_INTRINSIC = re.compile(r"^\s*(fc|cc|kc|alpha_c|nx|ny)\s*=\s*(.*?)\s*;?\s*$")


def _check_bouguet_intrinsics(path):
    """Finite numbers, fc > 0 and integer nx, ny, checked line by line (the toolbox's reader takes NaN)."""
    for lineno, ln in enumerate(_text_lines(path), start=1):
        m = _M_INTRINSIC.match(ln.split("%", 1)[0])
        if not m:
            continue
        key, body = m.group(1), m.group(2).strip("[] ")
        vals = _floats(body.replace(";", " ").replace(",", " ").split(), path, lineno, key)
        if key == "fc" and not np.all(vals > 0):
            _fail(path, lineno, f"focal length fc must be > 0, got {vals.tolist()}")
        if key in ("nx", "ny") and not (vals.size == 1 and vals[0] == int(vals[0]) and vals[0] > 0):
            _fail(path, lineno, f"{key} (image size) must be a positive integer, got {body}")


def _read_bouguet(path, image_size):
    if not path.is_file():
        raise CalibrationError(f"{path}: no such file; give the Calib_Results.m saved by Bouguet's toolbox")
    _check_bouguet_intrinsics(path)
    camera = calibio.read_bouguet(path, image_size=image_size)[0]
    if image_size is not None:
        _check_size(path, None, camera.image_size, image_size)
    found = {}
    for lineno, ln in enumerate(_text_lines(path), start=1):
        m = _M_ASSIGN.match(ln.split("%", 1)[0])
        if m:
            vals = _floats(m.group(3).replace(";", " ").replace(",", " ").split(), path, lineno, m.group(1))
            found.setdefault(int(m.group(2)), {})[m.group(1)] = (vals, lineno)
    poses, notes = {}, []
    for i in sorted(found):
        d = found[i]
        if "Tc" not in d:
            continue
        t, lineno = d["Tc"]
        if t.size != 3:
            _fail(path, lineno, f"Tc_{i} must have 3 numbers, got {t.size}")
        if "Rc" in d:
            R, rl = d["Rc"]
            if R.size != 9:
                _fail(path, rl, f"Rc_{i} must be 3x3, got {R.size} numbers")
            R = _rotation(R.reshape(3, 3), path, rl, f"Rc_{i}")
        elif "omc" in d and d["omc"][0].size == 3:
            import cv2

            R = cv2.Rodrigues(d["omc"][0])[0]
        else:
            _fail(path, lineno, f"Tc_{i} has no Rc_{i} or omc_{i}")
        poses[f"#{i}"] = (R, t)  # the toolbox numbers its images; matched to the views in their order
    if poses:
        notes.append(f"{len(poses)} poses Rc_i/Tc_i, numbered (the file has no image names): matched to the views in name order")
    return camera, poses, notes, path


def _write_bouguet(path, cameras, names):
    calibio.write_bouguet(path, cameras[0])
    lines = ["", "%-- Extrinsic parameters, one per image (world to camera, mm):"]
    for i, (n, c) in enumerate(zip(names, cameras), start=1):
        lines += [f"% image {i}: {n}",
                  f"Rc_{i} = [ " + " ; ".join(" , ".join(repr(float(v)) for v in row) for row in c.R) + " ];",
                  f"Tc_{i} = [ " + " ; ".join(repr(float(v)) for v in c.t) + " ];"]
    with path.open("a", encoding="utf-8") as fh:
        fh.write("\n".join(lines) + "\n")
    return [path]


# --------------------------------------------------------------------------- OpenCV
def _line_of(path, key):
    try:
        for i, ln in enumerate(path.read_text(encoding="utf-8", errors="replace").splitlines(), start=1):
            if re.search(rf"(^|[\s<]){re.escape(key)}\b", ln):
                return i
    except OSError:
        pass
    return None


def _read_opencv(path, image_size):
    camera = calibio.read_opencv(path)[0]
    if not (np.all(np.isfinite(camera.K)) and np.all(np.isfinite(camera.dist))):
        key = "camera_matrix" if not np.all(np.isfinite(camera.K)) else "distortion_coefficients"
        _fail(path, _line_of(path, key), f"{key} must be finite numbers")
    if not (camera.K[0, 0] > 0 and camera.K[1, 1] > 0):
        _fail(path, _line_of(path, "camera_matrix"), "camera_matrix must have positive focal lengths")
    _check_size(path, _line_of(path, "image_width"), camera.image_size, image_size)
    poses, notes = {}, []
    doc = read_storage(path)  # not cv2.FileStorage: it aborts the process on some damaged files
    views, ext = doc.get("views"), doc.get("extrinsic_parameters")
    if views is not None:
        line = _line_of(path, "views")
        if not isinstance(views, list):
            _fail(path, line, "views must be a sequence of {image, rvec, tvec}")
        for k, v in enumerate(views):
            name = v.get("image") if isinstance(v, dict) else None
            rvec, tvec = (v.get("rvec"), v.get("tvec")) if isinstance(v, dict) else (None, None)
            if not isinstance(name, str) or not isinstance(rvec, np.ndarray) or not isinstance(tvec, np.ndarray):
                _fail(path, line, f"views[{k}] needs image (a string), rvec and tvec (3x1)")
            poses[name] = _opencv_pose(rvec, tvec, path, line, f"views[{k}]")
    elif ext is not None:
        line = _line_of(path, "extrinsic_parameters")
        if not isinstance(ext, np.ndarray) or ext.ndim != 2 or ext.shape[1] != 6:
            _fail(path, line, "extrinsic_parameters must be an N x 6 matrix [rvec | tvec]")
        for k, row in enumerate(np.asarray(ext, np.float64)):
            poses[f"#{k + 1}"] = _opencv_pose(row[:3], row[3:], path, line, f"extrinsic_parameters row {k}")
        notes.append(f"{len(poses)} poses (extrinsic_parameters, no image names): matched to the views in name order")
    return camera, poses, notes, path


def _opencv_pose(rvec, tvec, path, line, what):
    import cv2

    r = np.asarray(rvec, np.float64).ravel()
    t = np.asarray(tvec, np.float64).ravel()
    if r.size != 3 or t.size != 3 or not (np.all(np.isfinite(r)) and np.all(np.isfinite(t))):
        _fail(path, line, f"{what}: rvec and tvec must be 3 finite numbers each")
    return cv2.Rodrigues(r)[0], t


def _write_opencv(path, cameras, names):
    import cv2

    if path.suffix.lower() not in (".yml", ".yaml", ".xml"):
        raise CalibrationError(f"{path}: use a .yml, .yaml or .xml file name for an OpenCV file")
    calibio.write_opencv(path, cameras[0])
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_APPEND)
    try:
        fs.startWriteStruct("views", cv2.FileNode_SEQ)
        for n, c in zip(names, cameras):
            fs.startWriteStruct("", cv2.FileNode_MAP)
            fs.write("image", n)
            fs.write("rvec", np.asarray(c.rvec, np.float64).reshape(3, 1))
            fs.write("tvec", np.asarray(c.t, np.float64).reshape(3, 1))
            fs.endWriteStruct()
        fs.endWriteStruct()
    finally:
        fs.release()
    return [path]


# --------------------------------------------------------------------------- Meshroom (AliceVision)
def _write_meshroom(path, cameras, names):
    cam = cameras[0]
    if cam.K[0, 1] != 0:
        raise CalibrationError(f"{path}: AliceVision has no skew; this camera's alpha_c is {cam.skew:g}")
    w, h = cam.image_size
    k1, k2, p1, p2, k3 = (float(v) for v in cam.dist)
    if p1 == p2 == 0.0:
        kind, params = ("pinhole", []) if k1 == k2 == k3 == 0.0 else ("radial3", [k1, k2, k3])
    else:
        kind, params = "brown", [k1, k2, k3, p1, p2]
    s = lambda v: repr(float(v))  # noqa: E731  (AliceVision writes every number as a string)
    # sensorWidth = width px, so that focalLength "mm" = fx px (AliceVision: fx = focalLength / sensorWidth * width)
    intrinsic = {
        "intrinsicId": "1", "width": str(w), "height": str(h), "sensorWidth": s(w), "sensorHeight": s(h),
        "serialNumber": "organlab", "type": kind, "initializationMode": "calibrated",
        "initialFocalLength": s(cam.K[0, 0]), "focalLength": s(cam.K[0, 0]),
        "pixelRatio": s(cam.K[1, 1] / cam.K[0, 0]), "pixelRatioLocked": "true",
        "principalPoint": [s(cam.K[0, 2] - w / 2.0), s(cam.K[1, 2] - h / 2.0)],
        "distortionInitializationMode": "calibrated", "distortionParams": [s(v) for v in params],
        "undistortionOffset": ["0", "0"], "undistortionParams": [], "locked": "true",
    }
    views, poses = [], []
    for i, (n, c) in enumerate(zip(names, cameras), start=1):
        views.append({"viewId": str(i), "poseId": str(i), "frameId": str(i), "intrinsicId": "1",
                      "path": str(Path(n).absolute()), "width": str(w), "height": str(h), "metadata": ""})
        poses.append({"poseId": str(i), "pose": {"transform": {"rotation": [s(v) for v in c.R.T.ravel()],
                                                               "center": [s(v) for v in c.center]}, "locked": "1"}})
    doc = {"version": ["1", "2", "5"], "views": views, "intrinsics": [intrinsic], "poses": poses}
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(doc, indent=2) + "\n", encoding="utf-8")
    return [path]


# --------------------------------------------------------------------------- the type
@dataclass(frozen=True)
class CameraFile:
    """Cameras read from another tool's file (:func:`read_cameras`).

    Attributes
    ----------
    path : Path
        The file (a COLMAP model: its folder).
    format : str
        ``middlebury``, ``colmap``, ``bouguet`` or ``opencv``.
    camera : Camera
        The intrinsics every image shares (identity pose), OpenCV pixel convention.
    poses : dict of str -> ((3, 3) float64, (3,) float64)
        World-to-camera ``(R_cam_world, t)`` per image, ``t`` in mm, in file
        order; keyed by the image's name as the file gives it, or ``'#1'``,
        ``'#2'``, ... when the file numbers its poses without names (Bouguet's
        ``Rc_i``, OpenCV's ``extrinsic_parameters``).  Empty when the file
        holds intrinsics only.
    notes : tuple of str
        What was assumed on the way (unit conversion, poses matched by order).
    """

    path: Path
    format: str
    camera: Camera
    poses: dict
    notes: tuple = ()

    @property
    def named(self) -> bool:
        """Whether the poses are keyed by image names (not numbered)."""
        return bool(self.poses) and not next(iter(self.poses)).startswith("#")

    def cameras(self) -> dict[str, Camera]:
        """The posed cameras, in file order: ``{name: Camera}``."""
        return {n: self.camera.with_pose(R, t) for n, (R, t) in self.poses.items()}
