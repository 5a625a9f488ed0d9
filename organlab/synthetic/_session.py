"""Writing a synthetic session folder (``organlab.session/1``) and its ``truth.json``."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..session import FORMAT, save_session, write_json
from . import _hard, _render
from ._boards import BOARD_MARGIN, DEFAULT_PATTERN, default_camera, intrinsic_board_poses, render_board, turntable_board_pose
from ._specimens import make_specimen

DEFAULT_ROI = {"min": [-70.0, -70.0, 0.0], "max": [70.0, 70.0, 200.0]}


def _write_image(path, image, *, fmt="png", quality=95, chroma="444"):
    """Write a PNG, or a JPEG with full (``'444'``) or 2 x 2 subsampled (``'420'``, most cameras) chroma."""
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
        factor = {"444": cv2.IMWRITE_JPEG_SAMPLING_FACTOR_444, "420": cv2.IMWRITE_JPEG_SAMPLING_FACTOR_420}[chroma]
        params = [cv2.IMWRITE_JPEG_QUALITY, int(quality), cv2.IMWRITE_JPEG_SAMPLING_FACTOR, factor]
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
    hard=False,
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
    hard : bool
        Hard lighting for the views and background frames (:mod:`organlab.synthetic._hard`):
        a directional lamp with cast shadows on the plate, specular highlights,
        a per-view exposure gain within +-10 %; views and frames are written as
        JPEG (quality at most 90, chroma subsampled 4:2:0 as most cameras
        write it) over the pixel noise.

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
    n_intrinsic, n_turntable = _check_session_options(
        n_views, n_intrinsic, n_turntable, n_background, include_camera, include_poses, views_only, view_format, background_format
    )
    spec = make_specimen(specimen)
    pattern = DEFAULT_PATTERN
    cam = default_camera(image_size)
    out.mkdir(parents=True, exist_ok=True)
    _remove_previous_images(out)
    noise = _Noise(seed, noise_sigma)
    poses_in = intrinsic_board_poses(cam, n_intrinsic, pattern=pattern, seed=seed) if n_intrinsic else []
    intrinsic = _write_intrinsic_images(out, cam, poses_in, pattern, board_supersample, noise)
    turntable = _write_turntable_images(out, cam, pattern, n_turntable, turntable_step_deg, board_supersample, noise)
    if hard:
        view_format = background_format = "jpg"
        jpeg_quality = min(int(jpeg_quality), 90)
    image_kw = dict(supersample=int(supersample), quality=jpeg_quality, hard=hard, chroma="420" if hard else "444")
    background = _write_background_frames(out, cam, n_background, noise, fmt=background_format, **image_kw)
    views, views_truth = _write_views(out, cam, spec, n_views, noise, include_poses, fmt=view_format, **image_kw)
    roi = DEFAULT_ROI if roi is None else roi
    session = {
        "format": FORMAT,
        "name": name or out.resolve().name,
        "units": "mm",
        "image_size": list(cam.image_size),
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
    if hard:  # key the views in Lab against the frames: exposure divided out, cast shadows not specimen
        session["backdrop"] = {"color": "frames", "shadows": True}
    truth = _truth(cam, spec, views_truth, pattern, poses_in, seed=seed, noise_sigma=noise_sigma, supersample=supersample,
                   board_supersample=board_supersample, formats=(view_format, background_format, jpeg_quality))
    if hard:
        truth["hard"] = {"exposure_gains": [v["exposure_gain"] for v in views_truth], "jpeg_chroma": "4:2:0"}
    save_session(out, session)
    write_json(out / "truth.json", truth)
    truth["session_json"] = session
    return truth


def _check_session_options(
    n_views, n_intrinsic, n_turntable, n_background, include_camera, include_poses, views_only, view_format, background_format
):
    """Validate make_session's options; returns the numbers of intrinsic and turntable images to write."""
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
    return n_intrinsic, n_turntable


class _Noise:
    """Pixel noise of a session: independent per image, deterministic from the seed and the image's kind and index."""

    def __init__(self, seed, sigma):
        self.seed, self.sigma = int(seed), sigma

    def __call__(self, image, kind, i):
        return _render.quantize(image, self.sigma, np.random.default_rng([self.seed, kind, i]))


def _write_intrinsic_images(out, cam, poses, pattern, board_supersample, noise):
    """Intrinsic calibration images: the board held in front of the camera."""
    cam0 = cam.with_pose(np.eye(3), np.zeros(3))
    names = []
    for i, (Rb, tb) in enumerate(poses):
        img = render_board(cam0, Rb, tb, pattern, supersample=board_supersample, table=False, noise_sigma=0.0)
        rel = f"calibration/intrinsics/{i:02d}.png"
        _write_image(out / rel, noise(img, 1, i))
        names.append(rel)
    return names


def _write_turntable_images(out, cam, pattern, n, step_deg, board_supersample, noise):
    """Turntable images: the board lying on the table, at ``0, step_deg, ...``."""
    Rb0, tb0 = turntable_board_pose(pattern)
    entries = []
    for i in range(int(n)):
        a = float(i * step_deg)
        img = render_board(cam.at_table_angle(a), Rb0, tb0, pattern, supersample=board_supersample, table=True)
        rel = f"calibration/turntable/{int(round(a)):03d}.png"
        _write_image(out / rel, noise(img, 2, i))
        entries.append({"image": rel, "angle_deg": a})
    return entries


def _write_background_frames(out, cam, n, noise, *, supersample, fmt, quality, hard=False, chroma="444"):
    """Background frames: the empty scene."""
    names = []
    if n:
        empty = _hard.render_hard(cam, supersample=supersample) if hard else _render.render(cam, supersample=supersample)
        for i in range(int(n)):
            rel = f"background/{i:02d}.{fmt}"
            _write_image(out / rel, noise(empty, 3, i), fmt=fmt, quality=quality, chroma=chroma)
            names.append(rel)
    return names


def _write_views(out, cam, spec, n_views, noise, include_poses, *, supersample, fmt, quality, hard=False, chroma="444"):
    """Views of the specimen every ``360 / n_views`` degrees; returns the session's and the truth's view entries."""
    views, views_truth = [], []
    for i in range(int(n_views)):
        a = float(360.0 * i / n_views)
        cam_a = cam.at_table_angle(a)
        if hard:
            gain = _hard.exposure_gain(np.random.default_rng([noise.seed, 5, i]))
            img = gain * _hard.render_hard(cam_a, supersample=supersample, specimen=spec)
        else:
            img = _render.render(cam_a, supersample=supersample, specimen=spec)
        rel = f"views/{int(round(a * 10)):04d}.{fmt}" if a != int(a) else f"views/{int(a):03d}.{fmt}"
        _write_image(out / rel, noise(img, 4, i), fmt=fmt, quality=quality, chroma=chroma)
        entry = {"image": rel, "angle_deg": a}
        if include_poses:
            entry["pose"] = {"R": cam_a.R.tolist(), "t": cam_a.t.tolist()}
        views.append(entry)
        views_truth.append({"angle_deg": a, "R": cam_a.R.tolist(), "t": cam_a.t.tolist()})
        if hard:
            views_truth[-1]["exposure_gain"] = float(gain)
    return views, views_truth


def _truth(cam, spec, views_truth, pattern, poses_in, *, seed, noise_sigma, supersample, board_supersample, formats):
    """The contents of ``truth.json``."""
    Rb0, tb0 = turntable_board_pose(pattern)
    view_format, background_format, jpeg_quality = formats
    return {
        "camera": {
            "K": cam.K.tolist(),
            "dist": cam.dist.tolist(),
            "image_size": list(cam.image_size),
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
    save_session(dest, doc)
    return dest
