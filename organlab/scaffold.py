"""A first ``session.json`` for a folder of images (``organlab init``).

Writing ``session.json`` by hand is the first obstacle for a new user.
:func:`init_session` looks at a folder laid out as ``session-format.md``
describes (or a flat folder of view images), writes a ``session.json`` that
:func:`organlab.session.load_session` accepts, and lists what the user must
check (the board, the roi, angles guessed from file names).

Sub-folders found (first match):

- views: ``views/``, otherwise the images in the folder itself;
- background frames: ``background/``, ``backgrounds/``, ``bg/``;
- intrinsic board images: ``calibration/intrinsics/``, ``intrinsics/``;
- turntable board images: ``calibration/turntable/``, ``turntable/``; their
  angles are read from the file names when every name is a number
  (``040.png`` -> 40 degrees), otherwise taken as ``index * step``.

Views are sorted by name (numbers in names compared as numbers).  Their
angles are read from their names when every name is a number (``030.png`` ->
30 degrees), otherwise ``start + i * step``; names that contradict an explicit
``step`` are an error (``angles='step'`` uses the step and ignores the names).

Cameras known from elsewhere (``cameras=FILE``: a Middlebury ``*_par.txt``, a
COLMAP text model, Bouguet's ``Calib_Results.m``, an OpenCV YAML/XML file; see
:func:`organlab.calibration.read_cameras`) become the session's ``camera`` and,
where the file has them, every view's ``pose`` (matched by image name; numbered
poses in view order); no board images are then needed, and the roi defaults
to the box every camera sees.
"""

from __future__ import annotations

import re
from pathlib import Path

from .calibration import read_cameras
from .errors import SessionError
from .session import FORMAT, load_session, save_session

__all__ = ["IMAGE_SUFFIXES", "init_session"]

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp")

_FOLDERS = {
    "views": ("views",),
    "background": ("background", "backgrounds", "bg"),
    "intrinsics": ("calibration/intrinsics", "intrinsics"),
    "turntable": ("calibration/turntable", "turntable"),
}


def _natural(path):
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", path.name)]


def _images(folder):
    if not folder.is_dir():
        return []
    return sorted((p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES), key=_natural)


def _find(root, kind):
    for name in _FOLDERS[kind]:
        found = _images(root / name)
        if found:
            return found
    return []


def _image_size(path):
    from PIL import Image

    try:
        with Image.open(path) as im:
            return [int(im.width), int(im.height)]
    except OSError as e:
        raise SessionError(f"{path}: cannot read the image ({e}); remove it from the folder or replace it") from None


def init_session(folder, *, step_deg=None, start_deg=0.0, cameras=None, cameras_scale=None, angles="auto",
                 inner_corners=(9, 6), square_size=20.0, roi=None, name=None, backdrop=None, force=False):
    """Write ``folder/session.json`` for the images in ``folder``.

    Parameters
    ----------
    folder : str or Path
        The session folder (see the module docstring for the sub-folders).
    step_deg : float, optional
        Table rotation between consecutive views, degrees (negative for a
        table turning the other way).  Needed unless the views' names carry
        their angles or ``cameras`` gives every view's pose.
    start_deg : float
        Angle of the first view, degrees (with ``step_deg``).
    cameras : str or Path, optional
        Cameras known from another tool (see the module docstring): the
        session's ``camera`` and, where the file has them, the views' poses.
    cameras_scale : float, optional
        mm per unit of the camera file's translations (default: 1000 for a
        Middlebury file, in metres; 1 otherwise).
    angles : {'auto', 'names', 'step'}
        Where the views' angles come from: ``'auto'`` the names when every
        name is a number, else the step; ``'names'`` or ``'step'`` force one.
    inner_corners : (2,) int
        Board's inner corners ``(columns, rows)``.
    square_size : float, mm
        Board's square edge.
    roi : (6,) float, mm, optional
        ``xmin, ymin, zmin, xmax, ymax, zmax`` in the world frame (default: the
        box every given camera sees, else a 200 x 200 x 200 mm box standing on
        the table: check it).
    name : str, optional
        Session name (default: the folder's name).
    backdrop : {'border', 'frames'} or (3,) int, optional
        The session's ``backdrop`` (keying in CIE Lab, see
        ``docs/session-format.md``): the image border's colour, the
        background frames, or a declared RGB colour.  Default: none when
        there are background frames (background subtraction), ``'border'``
        when there are none.
    force : bool
        Overwrite an existing ``session.json``.

    Returns
    -------
    path : Path
        The written ``session.json``.
    notes : list of str
        What the user should check or edit.

    Raises
    ------
    SessionError
        No images, no cameras and no board images, an existing
        ``session.json`` without ``force``, bad numbers, names that contradict
        ``step_deg``, or a result that :func:`~organlab.session.load_session`
        rejects (then nothing is left written).
    CalibrationError
        A camera file that cannot be read (one line naming its line).

    Examples
    --------
    >>> import tempfile, pathlib
    >>> from PIL import Image
    >>> from organlab.synthetic import default_camera
    >>> from organlab.calibration import write_cameras
    >>> root = pathlib.Path(tempfile.mkdtemp())
    >>> for a in (0, 90, 180, 270):
    ...     Image.new("RGB", (320, 240)).save(root / f"{a:03d}.png")
    >>> cam = default_camera((320, 240))
    >>> _ = write_cameras(root / "sparse", [cam.at_table_angle(a) for a in (0, 90, 180, 270)],
    ...                   ["000.png", "090.png", "180.png", "270.png"], format="colmap")
    >>> path, notes = init_session(root, cameras=root / "sparse")
    >>> import json; [v["angle_deg"] for v in json.loads(path.read_text())["views"]]
    [0.0, 90.0, 180.0, 270.0]
    """
    import math

    root = Path(folder).absolute()
    sj = root / "session.json"
    if not root.is_dir():
        raise SessionError(f"{root}: not a folder; give the folder that holds the images")
    if sj.exists() and not force:
        raise SessionError(f"{sj}: exists; edit it, or give --force to write a new one")
    if step_deg is not None and not (isinstance(step_deg, (int, float)) and math.isfinite(step_deg) and step_deg != 0):
        raise SessionError(f"--step must be a finite, non-zero number of degrees, got {step_deg!r}")
    if not (math.isfinite(start_deg) and math.isfinite(square_size) and square_size > 0):
        raise SessionError(f"--start must be finite and --square a finite number of mm > 0, got {start_deg}, {square_size}")
    if angles not in ("auto", "names", "step"):
        raise SessionError(f"--angles must be 'names' or 'step', got {angles!r}")
    views = _find(root, "views") or _images(root)
    if not views:
        raise SessionError(f"{root}: no images ({', '.join(IMAGE_SUFFIXES)}) in views/ nor in the folder itself")
    rel = lambda p: p.relative_to(root).as_posix()  # noqa: E731
    notes = []
    size = _image_size(views[0])
    intrinsics, turntable = _find(root, "intrinsics"), _find(root, "turntable")
    given = None if cameras is None else read_cameras(cameras, image_size=size, scale=cameras_scale)
    poses = _view_poses(given, views, rel, notes) if given is not None else None
    if given is None and not (intrinsics or turntable):
        raise SessionError(
            f"{root}: no cameras: give --cameras FILE (a Middlebury *_par.txt, a COLMAP model, Calib_Results.m or an "
            "OpenCV .yml) or add board images (calibration/intrinsics/ and calibration/turntable/) to calibrate from")
    if given is not None and poses is None and not turntable:
        raise SessionError(
            f"{given.path}: holds intrinsics only, and the views need poses: give a camera file with poses "
            "(Middlebury, COLMAP) or add board images on the table (calibration/turntable/)")
    view_angles = _view_angles(views, step_deg, start_deg, angles, posed=poses is not None, notes=notes)
    if step_deg is not None and len(views) * abs(step_deg) > 360 + 1e-9:
        notes.append(f"{len(views)} views at {step_deg:g} degrees cover more than a turn: check --step")
    doc = {
        "format": FORMAT,
        "name": name or root.name,
        "units": "mm",
        "image_size": size,
        "views": [{"image": rel(p), "angle_deg": a} for p, a in zip(views, view_angles)],
    }
    if given is not None:
        doc["camera"] = {"K": given.camera.K.tolist(), "dist": given.camera.dist.tolist()}
        doc["cameras_from"] = {"file": str(Path(cameras).absolute()), "format": given.format}  # readers ignore it
        notes += [f"cameras from {given.path} ({given.format}): {n}" for n in given.notes]
        if poses is not None:
            for v, (R, t) in zip(doc["views"], poses):
                v["pose"] = {"R": R.tolist(), "t": t.tolist()}
        if intrinsics:
            notes.append(f"{len(intrinsics)} intrinsic board images not listed: the intrinsics come from {Path(cameras).name}")
    background = _find(root, "background")
    if background:
        doc["background_images"] = [rel(p) for p in background]
    if backdrop is None and not background:
        backdrop = "border"
        notes.append("no background frames (background/): views keyed against the colour of the image border "
                     "(backdrop 'border'); give --backdrop R,G,B for a known backdrop colour, or add frames of the empty scene")
    if backdrop is not None:
        doc["backdrop"] = {"color": backdrop if isinstance(backdrop, str) else [int(v) for v in backdrop]}
    board_int = intrinsics if given is None else []
    board_tt = turntable if poses is None else []
    if board_int or board_tt:
        doc["pattern"] = {"type": "checkerboard", "inner_corners": [int(v) for v in inner_corners], "square_size": float(square_size)}
        notes.append(f"pattern: {inner_corners[0]}x{inner_corners[1]} inner corners, {square_size:g} mm squares: "
                     "check them against your board (a wrong square size scales the whole model)")
        cal = {}
        if board_int:
            cal["intrinsic_images"] = [rel(p) for p in board_int]
        if board_tt:
            stems = [p.stem for p in board_tt]
            if all(_NUMBER.fullmatch(s) for s in stems):
                tt_angles = [float(s) for s in stems]
            else:
                tt_angles = [float(start_deg + i * (step_deg or 0.0)) for i in range(len(board_tt))]
                notes.append("turntable image angles taken as index x step (their names are not numbers): check them")
            cal["turntable_images"] = [{"image": rel(p), "angle_deg": a} for p, a in zip(board_tt, tt_angles)]
        doc["calibration"] = cal
    if roi is None and poses is not None:
        roi = _roi_seen_by_all(given.camera, [R for R, _ in poses], [t for _, t in poses])
        if roi is not None:
            ext = " x ".join(f"{hi - lo:.0f}" for lo, hi in zip(roi[:3], roi[3:]))
            notes.append(f"roi: the box every camera sees ({ext} mm, estimated from the cameras): "
                         "shrink it around the specimen for speed")
    if roi is None:
        roi = (-100.0, -100.0, 0.0, 100.0, 100.0, 200.0)
        notes.append("roi: a 200 mm box standing on the table (default): shrink it around the specimen for speed")
    roi = [float(v) for v in roi]
    if len(roi) != 6 or not all(math.isfinite(v) for v in roi):
        raise SessionError(f"--roi must be 6 finite numbers xmin,ymin,zmin,xmax,ymax,zmax in mm, got {roi}")
    doc["roi"] = {"min": roi[:3], "max": roi[3:]}
    doc["init_notes"] = notes  # readers ignore unknown keys; delete once checked
    backup = sj.read_bytes() if sj.exists() else None
    save_session(root, doc)
    try:
        load_session(root)
    except SessionError as e:
        if backup is None:
            sj.unlink()
        else:
            sj.write_bytes(backup)
        why = str(e).split(": ", 1)[1] if str(e).startswith(str(sj)) else str(e)
        raise SessionError(f"{root}: organlab init cannot write a valid session.json ({why}); nothing written") from None
    return sj, notes


_NUMBER = re.compile(r"[-+]?\d+(\.\d+)?")


def _view_angles(views, step_deg, start_deg, angles, *, posed, notes):
    """The views' angles: from their names, from the step, or 0 when their poses are given."""
    stems = [p.stem for p in views]
    named = all(_NUMBER.fullmatch(s) for s in stems)
    if angles == "names" and not named:
        bad = next(p for p in views if not _NUMBER.fullmatch(p.stem))
        raise SessionError(f"{bad}: --angles names, but this name is not a number of degrees")
    if angles == "step" and step_deg is None:
        raise SessionError("--angles step needs --step DEG")
    if named and angles != "step":
        from_names = [float(s) for s in stems]
        if step_deg is not None:
            for i, (p, a) in enumerate(zip(views, from_names)):
                b = float(start_deg + i * step_deg)
                if abs((a - b + 180.0) % 360.0 - 180.0) > 1e-6:
                    raise SessionError(
                        f"{p}: its name says {a:g} degrees but --step {step_deg:g} (--start {start_deg:g}) makes it "
                        f"{b:g}; drop --step to take the angles from the names, or give --angles step to ignore them")
        notes.append("view angles read from the file names (e.g. 030.png = 30 degrees)")
        return from_names
    if step_deg is not None:
        return [float(start_deg + i * step_deg) for i in range(len(views))]
    if posed:
        notes.append("angle_deg 0 for every view: unused, each view has its pose from the camera file")
        return [0.0] * len(views)
    raise SessionError(f"{views[0].parent}: give --step DEG (the views' names are not angles, and no camera file gives their poses)")


def _view_poses(given, views, rel, notes):
    """Each view's ``(R, t)`` from a camera file, or None when it holds intrinsics only."""
    if not given.poses:
        return None
    if not given.named:
        if len(given.poses) != len(views):
            raise SessionError(f"{given.path}: {len(given.poses)} numbered poses for {len(views)} views; "
                               "they are matched in name order, so the counts must be equal")
        return list(given.poses.values())
    by_name = {}
    for key, pose in given.poses.items():
        by_name.setdefault(key, pose)
        by_name.setdefault(Path(key).name, pose)
    out, used = [], set()
    for p in views:
        pose = by_name.get(rel(p), by_name.get(p.name))
        if pose is None:
            some = ", ".join(list(given.poses)[:3])
            raise SessionError(f"{p}: no camera for this image in {given.path} (it names {some}, ...); "
                               "remove the image from the folder or give a camera file that has it")
        out.append(pose)
        used.add(id(pose))
    unused = [k for k, v in given.poses.items() if id(v) not in used]
    if unused:
        notes.append(f"{len(unused)} cameras of {given.path.name} have no image here (ignored): {', '.join(unused[:5])}")
    return out


def _roi_seen_by_all(camera, Rs, ts, *, n=48):
    """The box of the points every camera sees in front of it (None when they see nothing in common).

    The axes' nearest common point (least squares) is the centre of a cube of
    points sampled ``n`` a side, as large as the widest image footprint there;
    the box bounds the samples that project inside every image.
    """
    import numpy as np

    Rs, ts = np.asarray(Rs, np.float64), np.asarray(ts, np.float64)
    centres = -np.einsum("nji,nj->ni", Rs, ts)  # -R^T t
    axes = Rs[:, 2, :]  # the optical axis (camera +Z) in the world frame
    A = np.zeros((3, 3))
    b = np.zeros(3)
    for c, d in zip(centres, axes):
        P = np.eye(3) - np.outer(d, d)
        A += P
        b += P @ c
    if len(Rs) < 2 or np.linalg.cond(A) > 1e8:
        return None
    X0 = np.linalg.solve(A, b)
    w, h = camera.image_size
    reach = max(np.linalg.norm(X0 - centres, axis=1)) * max(w, h) / min(camera.K[0, 0], camera.K[1, 1])
    g = np.linspace(-reach, reach, n)
    pts = X0 + np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    seen = np.ones(len(pts), bool)
    for R, t in zip(Rs, ts):
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
            uv, z = camera.with_pose(R, t).project(pts, return_depth=True)
        seen &= (z > 0) & (uv[:, 0] >= -0.5) & (uv[:, 0] <= w - 0.5) & (uv[:, 1] >= -0.5) & (uv[:, 1] <= h - 0.5)
    if not seen.any():
        return None
    cell = g[1] - g[0]
    lo, hi = pts[seen].min(axis=0) - cell, pts[seen].max(axis=0) + cell
    return [round(float(v), 1) for v in (*lo, *hi)]
