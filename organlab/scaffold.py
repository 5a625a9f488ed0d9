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

Views are sorted by name (numbers in names compared as numbers) and get the
angles ``start + i * step``.
"""

from __future__ import annotations

import re
from pathlib import Path

from .errors import SessionError

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


def init_session(folder, *, step_deg, start_deg=0.0, inner_corners=(9, 6), square_size=20.0, roi=None, name=None,
                 backdrop=None, force=False):
    """Write ``folder/session.json`` for the images in ``folder``.

    Parameters
    ----------
    folder : str or Path
        The session folder (see the module docstring for the sub-folders).
    step_deg : float
        Table rotation between consecutive views, degrees (negative for a
        table turning the other way).
    start_deg : float
        Angle of the first view, degrees.
    inner_corners : (2,) int
        Board's inner corners ``(columns, rows)``.
    square_size : float, mm
        Board's square edge.
    roi : (6,) float, mm, optional
        ``xmin, ymin, zmin, xmax, ymax, zmax`` in the world frame (default a
        200 x 200 x 200 mm box standing on the table: check it).
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
        No images, an existing ``session.json`` without ``force``, bad numbers,
        or a result that :func:`~organlab.session.load_session` rejects (then
        nothing is left written).
    """
    import math

    from .session import FORMAT, load_session, save_session

    root = Path(folder).absolute()
    sj = root / "session.json"
    if not root.is_dir():
        raise SessionError(f"{root}: not a folder; give the folder that holds the images")
    if sj.exists() and not force:
        raise SessionError(f"{sj}: exists; edit it, or give --force to write a new one")
    if not (isinstance(step_deg, (int, float)) and math.isfinite(step_deg) and step_deg != 0):
        raise SessionError(f"--step must be a finite, non-zero number of degrees, got {step_deg!r}")
    if not (math.isfinite(start_deg) and math.isfinite(square_size) and square_size > 0):
        raise SessionError(f"--start must be finite and --square a finite number of mm > 0, got {start_deg}, {square_size}")
    views = _find(root, "views") or _images(root)
    if not views:
        raise SessionError(f"{root}: no images ({', '.join(IMAGE_SUFFIXES)}) in views/ nor in the folder itself")
    rel = lambda p: p.relative_to(root).as_posix()  # noqa: E731
    notes = []
    if len(views) * abs(step_deg) > 360 + 1e-9:
        notes.append(f"{len(views)} views at {step_deg:g} degrees cover more than a turn: check --step")
    doc = {
        "format": FORMAT,
        "name": name or root.name,
        "units": "mm",
        "image_size": _image_size(views[0]),
        "views": [{"image": rel(p), "angle_deg": float(start_deg + i * step_deg)} for i, p in enumerate(views)],
    }
    background = _find(root, "background")
    if background:
        doc["background_images"] = [rel(p) for p in background]
    if backdrop is None and not background:
        backdrop = "border"
        notes.append("no background frames (background/): views keyed against the colour of the image border "
                     "(backdrop 'border'); give --backdrop R,G,B for a known backdrop colour, or add frames of the empty scene")
    if backdrop is not None:
        doc["backdrop"] = {"color": backdrop if isinstance(backdrop, str) else [int(v) for v in backdrop]}
    intrinsics, turntable = _find(root, "intrinsics"), _find(root, "turntable")
    if intrinsics or turntable:
        doc["pattern"] = {"type": "checkerboard", "inner_corners": [int(v) for v in inner_corners], "square_size": float(square_size)}
        notes.append(f"pattern: {inner_corners[0]}x{inner_corners[1]} inner corners, {square_size:g} mm squares: "
                     "check them against your board (a wrong square size scales the whole model)")
        cal = {}
        if intrinsics:
            cal["intrinsic_images"] = [rel(p) for p in intrinsics]
        if turntable:
            stems = [p.stem for p in turntable]
            if all(re.fullmatch(r"-?\d+(\.\d+)?", s) for s in stems):
                angles = [float(s) for s in stems]
            else:
                angles = [float(start_deg + i * step_deg) for i in range(len(turntable))]
                notes.append("turntable image angles taken as index x step (their names are not numbers): check them")
            cal["turntable_images"] = [{"image": rel(p), "angle_deg": a} for p, a in zip(turntable, angles)]
        doc["calibration"] = cal
    else:
        notes.append("no board images (calibration/intrinsics/, calibration/turntable/): give 'camera' and view poses")
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
    except SessionError:
        if backup is None:
            sj.unlink()
        else:
            sj.write_bytes(backup)
        raise
    return sj, notes
