"""Writing a synthetic session folder (``organlab.session/1``) and its ``truth.json``."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..camera import rot_z
from ..session import DEFAULT_PATTERN, DEFAULT_ROI, FORMAT, save_session, write_json
from . import _hard, _render
from ._boards import BOARD_MARGIN, default_camera, intrinsic_board_poses, render_board, turntable_board_pose
from ._specimens import Moved, make_specimen

def _write_image(path, image, *, fmt="png", quality=95, chroma="444"):
    """Write a PNG, or a JPEG with full (``'444'``) or 2 x 2 subsampled (``'420'``, most cameras) chroma."""
    import cv2

    path.parent.mkdir(parents=True, exist_ok=True)
    img = image if image.ndim == 2 else image[:, :, ::-1]
    if fmt == "png":
        # noisy images: Huffman-only deflate is often smaller; keep the smaller.  Level 1, not 9: the same
        # pixels (lossless); on noisy images Huffman-only wins at any level (the same bytes: a 12-view
        # 320 x 240 session wrote 3 914 788 bytes at both), and level 9's default strategy cost 0.94 s CPU per
        # 640 x 480 image against 0.02 s (encoding 2.3 -> 0.6 s of that session's 20 s)
        bufs = [
            cv2.imencode(".png", img, [cv2.IMWRITE_PNG_COMPRESSION, 1, cv2.IMWRITE_PNG_STRATEGY, strategy])[1]
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
    true_angles_deg=None,
    camera_bump=None,
    slip=None,
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
    true_angles_deg : sequence of float, optional
        The table angle each view was really taken at (a table that lost
        steps, a mislabelled view); ``session.json`` keeps the commanded
        ``360 * i / n_views``.  ``truth.json`` has both.
    camera_bump : dict, optional
        The camera bumped after the board images, before the background
        frames and the views: ``{"rotation_deg": (3,), "translation_mm": (3,)}``,
        a rotation vector in the camera frame (degrees) about the camera's
        centre, and the centre's move, world frame, mm.
    slip : dict, optional
        The specimen slid on the plate from a view on:
        ``{"view": k, "translation_mm": (dx, dy), "rotation_deg": psi}``;
        views ``k, k+1, ...`` see it at ``Rz(psi) X + (dx, dy, 0)``.  The
        truth's view poses are in the specimen's frame of the first views
        (the cameras that see the unmoved specimen at the same place).

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
    commanded = [float(360.0 * i / n_views) for i in range(int(n_views))]
    perturb = _Perturbation(commanded, true_angles_deg, camera_bump, slip)
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
    cam_views = perturb.camera(cam)  # after the board images
    background = _write_background_frames(out, cam_views, n_background, noise, fmt=background_format, **image_kw)
    views, views_truth = _write_views(out, cam_views, spec, n_views, noise, include_poses, fmt=view_format, perturb=perturb,
                                      camera_nominal=cam, **image_kw)
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
        # the plate a user measures with a ruler (its top is where the zero-thickness board lies)
        "turntable_plate": {"diameter_mm": 2.0 * _render.PLATE_RADIUS, "top_z_mm": 0.0},
        "synthetic": {"generator": "organlab.synthetic", "seed": int(seed), "truth": "truth.json"},
    }
    if include_camera:
        session["camera"] = {"K": cam.K.tolist(), "dist": cam.dist.tolist()}
    if hard:  # key the views in Lab against the frames: exposure divided out, cast shadows not specimen
        session["backdrop"] = {"color": "frames", "shadows": True}
    truth = _truth(cam, spec, views_truth, pattern, poses_in, seed=seed, noise_sigma=noise_sigma, supersample=supersample,
                   board_supersample=board_supersample, formats=(view_format, background_format, jpeg_quality))
    if perturb.any:
        truth["perturbation"] = perturb.to_dict()
        truth["perturbation"]["camera_views"] = {"R_cam": cam_views.R.tolist(), "t_cam": cam_views.t.tolist(),
                                                 "center": cam_views.center.tolist()}
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


class _Perturbation:
    """What went wrong at the simulated rig (none by default): true angles, a bumped camera, a slip."""

    def __init__(self, commanded, true_angles_deg, camera_bump, slip):
        n = len(commanded)
        self.commanded = commanded
        if true_angles_deg is None:
            self.angles = list(commanded)
        else:
            a = np.asarray(true_angles_deg, dtype=np.float64).ravel()
            if a.shape != (n,) or not np.all(np.isfinite(a)):
                raise ValueError(f"true_angles_deg must hold {n} finite angles (one per view), got shape {a.shape}")
            self.angles = [float(x) for x in a]
        self.bump = None
        if camera_bump is not None:
            rot = np.asarray(camera_bump.get("rotation_deg", (0, 0, 0)), np.float64)
            tr = np.asarray(camera_bump.get("translation_mm", (0, 0, 0)), np.float64)
            if rot.shape != (3,) or tr.shape != (3,):
                raise ValueError("camera_bump needs rotation_deg (3,) and translation_mm (3,)")
            self.bump = (rot, tr)
        self.slip = None
        if slip is not None:
            k = int(slip["view"])
            if not 0 < k < n:
                raise ValueError(f"slip['view'] must be a view index in 1..{n - 1}, got {k}")
            tr = np.asarray(slip.get("translation_mm", (0, 0)), np.float64)
            if tr.shape != (2,):
                raise ValueError("slip['translation_mm'] must be (dx, dy), mm")
            self.slip = (k, tr, float(slip.get("rotation_deg", 0.0)))
        self.any = true_angles_deg is not None or self.bump is not None or self.slip is not None

    def camera(self, cam):
        """The camera after the board images (bumped or not)."""
        if self.bump is None:
            return cam
        import cv2

        rot, tr = self.bump
        Rb = cv2.Rodrigues(np.deg2rad(rot).reshape(3, 1))[0]
        R = Rb @ cam.R
        c = cam.center + tr
        return cam.with_pose(R, -R @ c)

    def specimen(self, spec, i):
        if self.slip is None or i < self.slip[0]:
            return spec
        return Moved(spec, self.slip[1], self.slip[2])

    def true_camera(self, cam, i):
        """The camera of view ``i`` in the frame of the unmoved specimen."""
        c = cam.at_table_angle(self.angles[i])
        if self.slip is None or i < self.slip[0]:
            return c
        Rs, s = rot_z(self.slip[2]), np.array([*self.slip[1], 0.0])
        # x_cam = R (Rs X + s) + t
        return c.with_pose(c.R @ Rs, c.R @ s + c.t)

    def to_dict(self):
        d = {"commanded_angles_deg": list(self.commanded), "true_angles_deg": list(self.angles)}
        if self.bump is not None:
            d["camera_bump"] = {"rotation_deg": self.bump[0].tolist(), "translation_mm": self.bump[1].tolist()}
        if self.slip is not None:
            d["slip"] = {"view": self.slip[0], "translation_mm": self.slip[1].tolist(), "rotation_deg": self.slip[2]}
        return d


def _write_views(out, cam, spec, n_views, noise, include_poses, *, supersample, fmt, quality, hard=False, chroma="444",
                 perturb=None, camera_nominal=None):
    """Views of the specimen every ``360 / n_views`` degrees; returns the session's and the truth's view entries."""
    views, views_truth = [], []
    if perturb is None:
        perturb = _Perturbation([float(360.0 * i / n_views) for i in range(int(n_views))], None, None, None)
    nominal = cam if camera_nominal is None else camera_nominal
    for i in range(int(n_views)):
        a = perturb.commanded[i]
        cam_a = cam.at_table_angle(perturb.angles[i])
        spec_i = perturb.specimen(spec, i)
        if hard:
            gain = _hard.exposure_gain(np.random.default_rng([noise.seed, 5, i]))
            img = gain * _hard.render_hard(cam_a, supersample=supersample, specimen=spec_i)
        else:
            img = _render.render(cam_a, supersample=supersample, specimen=spec_i)
        rel = f"views/{int(round(a * 10)):04d}.{fmt}" if a != int(a) else f"views/{int(a):03d}.{fmt}"
        _write_image(out / rel, noise(img, 4, i), fmt=fmt, quality=quality, chroma=chroma)
        entry = {"image": rel, "angle_deg": a}
        if include_poses:  # what the rig believes: the board-calibrated camera at the commanded angle
            cam_n = nominal.at_table_angle(a)
            entry["pose"] = {"R": cam_n.R.tolist(), "t": cam_n.t.tolist()}
        views.append(entry)
        true_cam = perturb.true_camera(cam, i)
        views_truth.append({"angle_deg": a, "R": true_cam.R.tolist(), "t": true_cam.t.tolist()})
        if perturb.any:
            views_truth[-1]["true_angle_deg"] = perturb.angles[i]
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


def with_true_cameras(session_dir: str | Path, dest: str | Path, *, step: int = 1) -> Path:
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
    step : int
        Keep every ``step``-th view (1: all; 6 on the 36-view sample: 6 views
        60 degrees apart, for quick examples and tests).

    Returns
    -------
    Path
        ``dest``.
    """
    if int(step) != step or step < 1:
        raise ValueError(f"step must be an integer >= 1, got {step!r}")
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
    doc["views"] = doc["views"][:: int(step)]
    save_session(dest, doc)
    return dest
