"""Loading and validating session folders (``organlab.session/1``).

The format is specified in ``docs/session-format.md``.  A session is
checked when it is loaded, so that a bad one fails at once with a single
clear message (:class:`~organlab.errors.SessionError`) naming the file and
the key, instead of half-way through a reconstruction.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .validate import inside, printable, read_json
from .preflight import image_header_size
from .camera import Camera, nearest_rotation
from .errors import SessionError

__all__ = [
    "FORMAT",
    "DEFAULT_PATTERN",
    "DEFAULT_ROI",
    "Pattern",
    "View",
    "Session",
    "load_session",
    "read_image",
    "save_session",
    "write_json",
]

FORMAT = "organlab.session/1"

#: Images above this many pixels are checked at load from their headers only (not decoded twice).
_DECODE_CHECK_MAX_PX = 50_000_000

#: The views', masks' and background frames' images decoded by the load's check are kept for the run's
#: first read of each (so a run decodes each image once) while they take at most this many bytes in all.
_KEEP_DECODED_BYTES = 160_000_000

#: Largest roi coordinate accepted, mm: an roi of 1e308 mm overflowed the grid's shape.
ROI_LIMIT_MM = 1e5


@dataclass(frozen=True)
class Pattern:
    """Calibration board: ``inner_corners`` ``(columns, rows)``, ``square_size`` in mm."""

    inner_corners: tuple
    square_size: float
    type: str = "checkerboard"


#: The board of a new session when none is named: 9 x 6 inner corners, 20 mm squares
#: (``organlab capture``, ``organlab init`` and the synthetic sessions start from it).
DEFAULT_PATTERN = Pattern((9, 6), 20.0)
#: The region of interest of a new session when none is named, mm, world frame.
DEFAULT_ROI = {"min": [-70.0, -70.0, 0.0], "max": [70.0, 70.0, 200.0]}


@dataclass(frozen=True)
class View:
    """One turntable stop.

    Attributes
    ----------
    image : Path
        Absolute path of the view's image.
    angle_deg : float
        Table angle, right-handed about +Z.
    pose : tuple of ((3, 3) float64, (3,) float64) or None
        Given world-to-camera ``(R, t)``, mm.
    mask : Path or None
        Given silhouette image (non-zero = specimen).
    """

    image: Path
    angle_deg: float
    pose: tuple | None = None
    mask: Path | None = None


@dataclass(frozen=True)
class Session:
    """A validated session folder.  Paths are absolute."""

    root: Path
    name: str
    image_size: tuple
    roi_min: np.ndarray
    roi_max: np.ndarray
    views: tuple
    pattern: Pattern | None = None
    intrinsic_images: tuple = ()
    turntable_images: tuple = ()  # of (Path, angle_deg)
    background_images: tuple = ()
    camera: dict | None = None  # {"K": (3,3), "dist": (5,)}
    reference: dict = field(default_factory=dict)
    calibration: dict | None = None  # contents of calibration.json when present
    raw: dict = field(default_factory=dict)
    backdrop: dict | None = None  # {"color": (3,) float RGB | "border" | "frames", "shadows": bool}
    notes: tuple = ()  # of str: what loading corrected (e.g. a re-orthonormalised rotation)
    # path -> (file signature, decoded image) from the load's check, given to the first read (see _check_images)
    _decoded: dict = field(default_factory=dict, repr=False, compare=False)

    def __getstate__(self):  # a pickled session (sent to a worker) leaves its decoded images behind
        return {**self.__dict__, "_decoded": {}}

    def __setstate__(self, state):
        self.__dict__.update(state)

    @property
    def json_path(self) -> Path:
        return self.root / "session.json"

    @property
    def calibration_path(self) -> Path:
        return self.root / "calibration.json"

    def relpath(self, path: str | Path) -> str:
        """Path relative to the session folder, with ``/``, for messages and reports."""
        try:
            return Path(path).relative_to(self.root).as_posix()
        except ValueError:
            return str(path)

    def read(self, path: str | Path, *, key: str = "image", grey: bool = False) -> np.ndarray:
        """Read one of the session's images, checking it exists and has the session's size."""
        kept = self._decoded.pop(str(path), None) if self._decoded else None
        if kept is not None and kept[0] == _signature(path):  # decoded by the load's check, file unchanged
            return _finish_image(kept[1], self.image_size, grey, self.json_path, key, self.relpath(path))
        return read_image(path, size=self.image_size, key=key, grey=grey, session=self)

    def images(self, *, grey: bool = False) -> list[np.ndarray]:
        """The views' images, read and checked, in view order.

        Returns
        -------
        list of (H, W, 3) uint8 RGB (or (H, W) uint8 with ``grey=True``)
        """
        return [self.read(v.image, key=f"views[{i}].image", grey=grey) for i, v in enumerate(self.views)]

    def save(self, folder: str | Path | None = None) -> Path:
        """Write this session's ``session.json`` (its document, :attr:`raw`) into ``folder`` (default its own).

        Through :func:`save_session`, the one writer of ``session.json``.
        """
        return save_session(self.root if folder is None else folder, self.raw)

    def given_camera(self) -> Camera | None:
        """The intrinsics given in ``session.json`` as a :class:`Camera`, or None."""
        if self.camera is None:
            return None
        return Camera(self.camera["K"], self.camera["dist"], image_size=self.image_size)


def _fail(session_json, key, message):
    raise SessionError(f"{session_json}: {key}: {message}")


def _matrix(value, shape, where, key):
    try:
        a = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        _fail(where, key, f"must be a numeric array of shape {shape}")
    if a.shape != shape or not np.all(np.isfinite(a)):
        _fail(where, key, f"must be a finite numeric array of shape {shape}, got {list(a.shape)}")
    return a


def read_image(path, *, size=None, key="image", grey=False, session=None):
    """Read an 8-bit PNG or JPEG image, with a clear error when it cannot be used.

    Parameters
    ----------
    path : str or Path
    size : (2,) int, optional
        Expected ``(width, height)``.
    key : str
        The session key that names this image (for the message).
    grey : bool
        Return a grey ``(H, W)`` image instead of the stored channels.

    Returns
    -------
    image : (H, W) or (H, W, 3) uint8
        Colour images are RGB.
    """
    path = Path(path)
    where = session.json_path if session is not None else path
    shown = session.relpath(path) if session is not None else str(path)
    _check_file(path, size, where, key, shown)
    return _finish_image(_decode(path, where, key, shown), size, grey, where, key, shown)


def _check_file(path, size, where, key, shown):
    """Fail unless ``path`` is a file whose header (when readable) gives ``size``; before decoding."""
    if not path.is_file():
        _fail(where, key, f"image '{shown}' does not exist; check the path (relative to the session folder)")
    header = image_header_size(path)  # before decoding: a 20000x20000 PNG is 1.2 MB on disk, 1.2 GB decoded
    if size is not None and header is not None and header != tuple(size):
        _fail(where, key, f"image '{shown}' is {header[0]}x{header[1]} px but image_size is {size[0]}x{size[1]}; "
                          "every image of a session must have the same size")
    return header


def _decode(path, where, key, shown):
    """The image at ``path`` decoded as stored, 8 bits, alpha dropped (BGR order for colour)."""
    import cv2

    data = np.fromfile(str(path), dtype=np.uint8)
    img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
    if img is None:
        _fail(where, key, f"image '{shown}' cannot be read (corrupt or not PNG/JPEG); re-export or recapture it")
    if img.dtype != np.uint8:
        img = (img / 257).astype(np.uint8) if img.dtype == np.uint16 else img.astype(np.uint8)
    if img.ndim == 3 and img.shape[2] == 4:
        img = img[:, :, :3]
    return img


def _finish_image(img, size, grey, where, key, shown):
    """:func:`read_image`'s result from :func:`_decode`'s: RGB or grey, and its size checked."""
    import cv2

    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY if grey else cv2.COLOR_BGR2RGB)
    _check_size(img, size, where, key, shown)
    return img


def _check_size(img, size, where, key, shown):
    if size is not None and (img.shape[1], img.shape[0]) != tuple(size):
        _fail(
            where,
            key,
            f"image '{shown}' is {img.shape[1]}x{img.shape[0]} px but image_size is "
            f"{size[0]}x{size[1]}; every image of a session must have the same size",
        )


def _image_at_angle(item, key, where, hint):
    """Validate ``{'image': path, 'angle_deg': number}``; return ``(path, angle)``."""
    if not isinstance(item, dict) or not isinstance(item.get("image"), str):
        _fail(where, key, "must be {'image': path, 'angle_deg': number, ...}")
    a = item.get("angle_deg")
    if not isinstance(a, (int, float)) or isinstance(a, bool) or not np.isfinite(a) or abs(a) > 1e6:
        _fail(where, key + ".angle_deg", f"is missing or not a number (degrees, |angle| <= 1e6); {hint}")
    return item["image"], float(a)


def _image_list(raw, key, root, where, outside=False):
    items = raw
    if not isinstance(items, list) or not all(isinstance(s, str) for s in items):
        _fail(where, key, "must be a list of image paths (strings)")
    return tuple(_inside(root, s, f"{key}[{i}]", where, outside) for i, s in enumerate(items))


def _inside(root, relative, key, where, outside):
    """A path a session names, inside the session folder (symlinks followed) unless ``outside``."""
    return inside(root, relative, key, error=SessionError, where=str(where), allow_outside=outside)


def load_session(path: str | Path, *, check_images: bool = True, allow_outside_paths: bool = False) -> Session:
    """Load and validate a session folder.

    Parameters
    ----------
    path : str or Path
        The session folder (or its ``session.json``).
    check_images : bool
        Also open every image the session names and check its size (decoded: the views, masks and
        background frames; the board images by their header, decoded when calibrating).
    allow_outside_paths : bool
        Accept image paths that lead out of the session folder (absolute, ``..``, a
        symlink out); refused by default, so that a session reads only its own files.

    Returns
    -------
    Session

    Raises
    ------
    SessionError
        With one line naming the file and key at fault.
    """
    root, sj, raw = _read_session_json(path)
    size = _image_size(raw, sj)
    roi_min, roi_max = _roi(raw, sj)
    pattern = _pattern(raw, sj)
    intrinsic, turntable, background = _board_and_background_images(raw, root, sj, allow_outside_paths)
    camera = _camera(raw, size, sj)
    calibration = _calibration_json(root / "calibration.json")
    views, notes = _views(raw, root, sj, allow_outside_paths)
    backdrop = _parse_backdrop(raw.get("backdrop"), sj, background)
    _check_turntable_plate(raw.get("turntable_plate"), sj)
    _check_needs(sj, views, camera, intrinsic, turntable, background, pattern, calibration, backdrop)
    session = Session(
        root=root,
        name=_name(raw, root, sj),
        image_size=size,
        roi_min=roi_min,
        roi_max=roi_max,
        views=tuple(views),
        pattern=pattern,
        intrinsic_images=intrinsic,
        turntable_images=tuple(turntable),
        background_images=background,
        camera=camera,
        reference=_reference(raw, sj),
        calibration=calibration,
        raw=raw,
        backdrop=backdrop,
        notes=tuple(notes),
    )
    if check_images:
        _check_images(session)
    return session


def _read_session_json(path):
    root = Path(path)
    if root.name == "session.json":
        root = root.parent
    root = root.resolve()
    sj = root / "session.json"
    if root.exists() and not root.is_dir():
        raise SessionError(f"{root}: is a file, not a session folder; give the folder that holds session.json")
    if not root.is_dir():
        raise SessionError(f"{root}: session folder does not exist")
    if not sj.is_file():
        raise SessionError(f"{sj}: no session.json in this folder; is it a session folder?")
    raw = read_json(sj, error=SessionError, fix="fix it (docs/session-format.md)")
    if not isinstance(raw, dict):
        _fail(sj, "(top level)", "must be a JSON object")
    if raw.get("format") != FORMAT:
        _fail(sj, "format", f"must be exactly '{FORMAT}', got {raw.get('format')!r}")
    if raw.get("units") != "mm":
        _fail(sj, "units", f"must be 'mm', got {raw.get('units')!r}")
    return root, sj, raw


def _name(raw, root, sj):
    """The session's name, its control characters escaped (it is printed to terminals)."""
    name = raw.get("name", root.name)
    if not isinstance(name, str) or len(name) > 200:
        _fail(sj, "name", f"must be text of at most 200 characters, got {printable(repr(name)[:40])}")
    return printable(name)


def _image_size(raw, sj):
    size = raw.get("image_size")
    if (
        not isinstance(size, list)
        or len(size) != 2
        or not all(isinstance(s, int) and not isinstance(s, bool) and 0 < s <= 1_000_000 for s in size)
    ):
        _fail(sj, "image_size", f"must be [width, height] in pixels (integers 1-1000000), got {printable(repr(size)[:60])}")
    return tuple(size)


def _roi(raw, sj):
    roi = raw.get("roi")
    if not isinstance(roi, dict) or "min" not in roi or "max" not in roi:
        _fail(sj, "roi", "must be {'min': [x, y, z], 'max': [x, y, z]} in mm")
    roi_min = _matrix(roi["min"], (3,), sj, "roi.min")
    roi_max = _matrix(roi["max"], (3,), sj, "roi.max")
    if np.abs(np.concatenate([roi_min, roi_max])).max() > ROI_LIMIT_MM:
        _fail(sj, "roi", f"coordinates beyond +-{ROI_LIMIT_MM:g} mm (a {ROI_LIMIT_MM / 1000:g} m turntable); give the "
                         f"box around the specimen in mm, got {roi_min.tolist()} to {roi_max.tolist()}")
    bad = [("xyz"[i]) for i in range(3) if roi_min[i] >= roi_max[i]]
    if bad:
        _fail(sj, "roi", f"min must be < max on every axis; not on {', '.join(bad)} ({roi_min.tolist()} vs {roi_max.tolist()})")
    return roi_min, roi_max


def _pattern(raw, sj):
    if raw.get("pattern") is None:
        return None
    p = raw["pattern"]
    if not isinstance(p, dict):
        _fail(sj, "pattern", "must be an object")
    if p.get("type", "checkerboard") != "checkerboard":
        _fail(sj, "pattern.type", f"only 'checkerboard' is supported, got {p.get('type')!r}")
    ic = p.get("inner_corners")
    if not (isinstance(ic, list) and len(ic) == 2 and all(isinstance(v, int) and not isinstance(v, bool) and 2 <= v <= 1000
                                                          for v in ic)):
        _fail(sj, "pattern.inner_corners", f"must be [columns, rows] of inner corners (integers >= 2), got {ic!r}")
    sq = p.get("square_size")
    if not (isinstance(sq, (int, float)) and not isinstance(sq, bool) and np.isfinite(sq) and 0 < sq < 1e6):
        _fail(sj, "pattern.square_size", f"must be a positive number of mm, got {sq!r}")
    return Pattern(tuple(ic), float(sq))


def _board_and_background_images(raw, root, sj, outside=False):
    cal = raw.get("calibration") or {}
    if not isinstance(cal, dict):
        _fail(sj, "calibration", "must be an object")
    intrinsic = _image_list(cal.get("intrinsic_images", []), "calibration.intrinsic_images", root, sj, outside)
    tt_raw = cal.get("turntable_images", [])
    if not isinstance(tt_raw, list):
        _fail(sj, "calibration.turntable_images", "must be a list of {'image': ..., 'angle_deg': ...}")
    turntable = []
    for i, item in enumerate(tt_raw):
        key = f"calibration.turntable_images[{i}]"
        image, a = _image_at_angle(item, key, sj, "give the table angle of every turntable image")
        turntable.append((_inside(root, image, key + ".image", sj, outside), a))
    background = _image_list(raw.get("background_images", []), "background_images", root, sj, outside)
    return intrinsic, turntable, background


def _camera(raw, size, sj):
    if raw.get("camera") is None:
        return None
    c = raw["camera"]
    if not isinstance(c, dict):
        _fail(sj, "camera", "must be {'K': 3x3, 'dist': [k1, k2, p1, p2, k3]}")
    K = _matrix(c.get("K"), (3, 3), sj, "camera.K")
    dist = _matrix(c.get("dist", [0, 0, 0, 0, 0]), (5,), sj, "camera.dist")
    try:
        Camera(K, dist, image_size=size)
    except ValueError as e:
        _fail(sj, "camera", str(e))
    return {"K": K, "dist": dist}


def _calibration_json(cj):
    """The content of the session's calibration.json (checked in full where it is used), or None."""
    if not cj.is_file():
        return None
    calibration = read_json(cj, error=SessionError, fix="delete it and run 'organlab calibrate' again")
    if not isinstance(calibration, dict) or "camera" not in calibration:
        raise SessionError(f"{cj}: has no 'camera'; delete it and run 'organlab calibrate' again")
    if not isinstance(calibration["camera"], dict):
        raise SessionError(f"{cj}: camera must be an object with K and dist; delete it and run 'organlab calibrate' again")
    for k in ("K", "dist"):
        if k not in calibration["camera"]:
            raise SessionError(f"{cj}: camera.{k} is missing; delete it and run 'organlab calibrate' again")
    return calibration


def _views(raw, root, sj, outside=False):
    views_raw = raw.get("views")
    if not isinstance(views_raw, list):
        _fail(sj, "views", "is required: a list of {'image': path, 'angle_deg': number} (may be empty)")
    views = []
    notes = []
    for i, v in enumerate(views_raw):
        key = f"views[{i}]"
        image, a = _image_at_angle(v, key, sj, "give the table angle of every view")
        pose = None
        if v.get("pose") is not None:
            p = v["pose"]
            if not isinstance(p, dict):
                _fail(sj, key + ".pose", "must be {'R': 3x3, 't': [3]}")
            R = _matrix(p.get("R"), (3, 3), sj, key + ".pose.R")
            t = _matrix(p.get("t"), (3,), sj, key + ".pose.t")
            try:
                R_orth, err = nearest_rotation(R)
            except ValueError as e:
                _fail(sj, key + ".pose.R", f"{e}; give the rotation with more digits")
            if err > 1e-12:
                notes.append(f"{key}.pose.R re-orthonormalised (max |R R^T - I| was {err:.2g})")
            R = R_orth
            pose = (R, t)
        mask = None
        if v.get("mask") is not None:
            if not isinstance(v["mask"], str):
                _fail(sj, key + ".mask", "must be an image path")
            mask = _inside(root, v["mask"], key + ".mask", sj, outside)
        views.append(View(_inside(root, image, key + ".image", sj, outside), a, pose, mask))
    return views, notes


def _check_needs(sj, views, camera, intrinsic, turntable, background, pattern, calibration, backdrop):
    """What each view needs: intrinsics, a pose or a turntable, a mask or background frames."""
    have_intrinsics = camera is not None or bool(intrinsic) or calibration is not None
    have_turntable = bool(turntable) or bool(calibration and calibration.get("turntable"))
    if views and not have_intrinsics:
        _fail(sj, "camera", "no intrinsics: give 'camera', or 'calibration.intrinsic_images' to calibrate from")
    for i, v in enumerate(views):
        if v.pose is None and not have_turntable:
            _fail(
                sj,
                f"views[{i}].pose",
                "this view has no pose and the session has no turntable calibration; "
                "give 'pose' or 'calibration.turntable_images'",
            )
    if (intrinsic or turntable) and pattern is None and calibration is None:
        if camera is None or any(v.pose is None for v in views):
            _fail(sj, "pattern", "is required to calibrate from board images: {'inner_corners': [cols, rows], 'square_size': mm}")
    if any(v.mask is None for v in views) and not background and backdrop is None:
        _fail(sj, "background_images", "views without 'mask' need background frames or a 'backdrop' for the silhouettes")


def _reference(raw, sj):
    reference = raw.get("reference") or {}
    if not isinstance(reference, dict):
        _fail(sj, "reference", "must be an object, e.g. {'volume_mm3': 180000}")
    v = reference.get("volume_mm3")
    if "volume_mm3" in reference and not (isinstance(v, (int, float)) and not isinstance(v, bool) and np.isfinite(v) and v > 0):
        _fail(sj, "reference.volume_mm3", f"must be a finite positive number of mm3, got {printable(repr(v)[:40])}")
    return dict(reference)


def _check_turntable_plate(value, sj):
    """The optional ``turntable_plate`` key: ``{"diameter_mm": > 0, "top_z_mm": number (default 0)}``."""
    if value is None:
        return
    if not isinstance(value, dict):
        _fail(sj, "turntable_plate", "must be an object, e.g. {'diameter_mm': 250.0} (measured with a ruler)")
    for key, positive in (("diameter_mm", True), ("top_z_mm", False)):
        v = value.get(key)
        if v is None and not positive:
            continue
        if not (isinstance(v, (int, float)) and not isinstance(v, bool) and np.isfinite(v) and (v > 0 or not positive)):
            what = "a finite positive number of mm" if positive else "a finite number of mm"
            _fail(sj, f"turntable_plate.{key}", f"must be {what}, got {printable(repr(v)[:40])}")


def _parse_backdrop(value, sj, background):
    """The ``backdrop`` key (docs/session-format.md, Backdrop): None or ``{"color": ..., "shadows": bool}``."""
    if value is None:
        return None
    if not isinstance(value, dict) or "color" not in value:
        _fail(sj, "backdrop", "must be an object {'color': [r, g, b] | 'border' | 'frames'} (optional 'shadows': true/false)")
    unknown = sorted(set(value) - {"color", "shadows"})
    if unknown:
        _fail(sj, "backdrop", f"unknown key(s) {unknown}; allowed: 'color', 'shadows'")
    color = value["color"]
    if isinstance(color, str):
        if color not in ("border", "frames"):
            _fail(sj, "backdrop.color", f"must be [r, g, b] (0-255), 'border' or 'frames', got {color!r}")
        if color == "frames" and not background:
            _fail(sj, "backdrop.color", "'frames' needs background_images; use 'border' or a colour [r, g, b]")
    else:
        rgb = _matrix(color, (3,), sj, "backdrop.color")
        if np.any(rgb < 0) or np.any(rgb > 255):
            _fail(sj, "backdrop.color", f"must be RGB in 0-255, got {rgb.tolist()}")
        color = tuple(float(c) for c in rgb)
    shadows = value.get("shadows", True)
    if not isinstance(shadows, bool):
        _fail(sj, "backdrop.shadows", f"must be true or false, got {shadows!r}")
    return {"color": color, "shadows": shadows}


def _check_images(s):
    items = [(p, f"calibration.intrinsic_images[{i}]") for i, p in enumerate(s.intrinsic_images)]
    items += [(p, f"calibration.turntable_images[{i}].image") for i, (p, _) in enumerate(s.turntable_images)]
    items += [(p, f"background_images[{i}]") for i, p in enumerate(s.background_images)]
    for i, v in enumerate(s.views):
        items.append((v.image, f"views[{i}].image"))
        if v.mask is not None:
            items.append((v.mask, f"views[{i}].mask"))
    big = s.image_size[0] * s.image_size[1] > _DECODE_CHECK_MAX_PX
    if big:
        for p, key in items:
            if image_header_size(p) != tuple(s.image_size):
                s.read(p, key=key)  # fails with the message naming its size
        return  # headers checked; decoding is left to the run (after its memory pre-flight)
    # the run's inputs (views, masks, background frames) are kept for its first read, within a budget
    # (decoding on threads was tried: 10-25 % more CPU, no shorter under load)
    n_boards = len(s.intrinsic_images) + len(s.turntable_images)
    budget = _KEEP_DECODED_BYTES
    for k, (p, key) in enumerate(items):  # what Session.read checks, without its colour conversion
        sig = _signature(p)
        where, shown = s.json_path, s.relpath(p)
        header = _check_file(Path(p), s.image_size, where, key, shown)
        if k < n_boards and header is not None:  # a board image: there, its size from its header; decoded (and a
            continue  # corrupt one named) by the calibration, which a run with a calibration given skips (25 of
            # the sample's 81 decodes: 0.1 s CPU of the command, issue 24)
        img = _decode(p, where, key, shown)
        _check_size(img, s.image_size, where, key, shown)
        if k >= n_boards and sig is not None and img.nbytes <= budget:
            budget -= img.nbytes
            s._decoded[str(p)] = (sig, img)


def _signature(path):
    """What tells a file changed since it was decoded: device, inode, size, modification time (ns); None if gone."""
    try:
        st = os.stat(path)
    except OSError:
        return None
    return (st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns)


def write_json(path, obj):
    """Write ``obj`` as indented JSON (numpy arrays and scalars converted; strict JSON: non-finite numbers as null)."""
    try:
        text = json.dumps(obj, indent=2, default=_json_default, allow_nan=False)
    except ValueError:  # strict JSON always: a non-finite number (NaN, inf) is written as null
        text = json.dumps(_finite_or_null(obj, _json_default), indent=2, default=_json_default, allow_nan=False)
    Path(path).write_text(text + "\n", encoding="utf-8")


def save_session(folder: str | Path, doc: dict) -> Path:
    """Write a ``session.json`` document into ``folder``, atomically: the one writer of ``session.json``.

    Used by :meth:`Session.save`, the capture (rewritten after every image),
    ``organlab init`` and ``organlab.synthetic``.  The document is written to
    a temporary file beside it, flushed to disk and renamed over
    ``session.json``, so that a crash never leaves half a file; ``format`` is
    set to :data:`FORMAT` when the document has none (``doc`` itself is not
    changed).  Numpy arrays and scalars and paths are converted as
    :func:`write_json` converts them.

    Parameters
    ----------
    folder : str or Path
        The session folder (created when missing).
    doc : dict
        The document (``docs/session-format.md``).

    Returns
    -------
    Path
        ``folder/session.json``.
    """
    if not isinstance(doc, dict):
        raise TypeError(f"doc must be a dict (the session.json document), got {type(doc).__name__}")
    out = Path(folder)
    out.mkdir(parents=True, exist_ok=True)
    path = out / "session.json"
    doc = doc if "format" in doc else {"format": FORMAT, **doc}
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "w", encoding="utf-8") as f:
        f.write(json.dumps(doc, indent=2, default=_json_default) + "\n")
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)
    return path


def _json_default(o):
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, Path):
        return o.as_posix()
    raise TypeError(f"cannot serialise {type(o).__name__}")


def _finite_or_null(o, default):
    if isinstance(o, dict):
        return {k: _finite_or_null(v, default) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_finite_or_null(v, default) for v in o]
    if isinstance(o, (np.ndarray, np.generic)):
        return _finite_or_null(default(o), default)
    if isinstance(o, float) and not np.isfinite(o):
        return None
    return o
