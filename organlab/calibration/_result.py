"""One calibration result: :class:`Calibration`, its file form ``calibration.json``, and the session glue.

A :class:`Calibration` holds the intrinsics (fitted, or given in ``session.json``), the turntable
fit when there was one, the board pattern and a *fingerprint* of what it was computed from (the
board images' bytes, the pattern, the image size, given intrinsics).  The fingerprint lets a later
run tell whether a saved calibration still belongs to a session: a ``calibration.json`` computed
with another square size, from other board images or at another image size is never used silently.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..camera import Camera, nearest_rotation, rot_z
from ..validate import array as _array
from ..validate import number as _number
from ..validate import read_json
from ..errors import CalibrationError
from ..session import Pattern, Session, load_session, write_json
from ._board import board_points
from ._common import _project, _rms, _rodrigues
from ._intrinsics import IntrinsicCalibration, calibrate_intrinsics
from ._turntable import TurntableCalibration, calibrate_turntable

FORMAT = "organlab.calibration/1"

#: A turntable fit RMS beyond this multiple of the intrinsic RMS is a warning.  Measured on the
#: sample session: 0.039 / 0.022 px = 1.8x; with 3 of its 10 turntable boards moved by (6, 3) px
#: and kept in the fit, 1.79 / 0.022 px = 80x; with them set aside, 1.8x again.
TURNTABLE_RMS_FACTOR = 5.0

#: A stored RMS is reproduced when the RMS recomputed from the stored corners, camera and poses is
#: within this many px of it, plus :data:`VERIFY_REL` of it.  Measured on a synthetic small session
#: (organlab synth --small): the corners are stored to 4 decimals, and the recomputed RMS equals the
#: stored one to < 1e-4 px (intrinsic 0.0342 px, turntable 0.0549 px); fx and fy changed by +1 %
#: give 0.80 px and 0.62 px, by +8 % 6.39 px and 4.95 px.
VERIFY_ABS_PX = 0.01
VERIFY_REL = 0.05
#: Plausible intrinsics: focal lengths within this factor of the image's larger side (either way),
#: an aspect fx/fy within [1/2, 2], the principal point inside the image, |k_i| below 100,
#: an RMS below 50 px.
PLAUSIBLE_FOCAL_FACTOR = 100.0


@dataclass(frozen=True, eq=False)
class Calibration:
    """The calibration of a session's camera and turntable.

    Attributes
    ----------
    camera : Camera
        Intrinsics (``K``, ``dist``, ``image_size``), identity pose.
    intrinsics : IntrinsicCalibration or None
        The intrinsic fit (per-image errors, uncertainties, corners); None when the
        intrinsics were given in ``session.json``.
    turntable : TurntableCalibration or None
        The turntable fit (camera pose at table angle 0, axis, per-image errors); None when
        every view has a given pose.
    pattern : Pattern or None
        The board the fits used.
    fingerprint : dict or None
        What the calibration was computed from (:func:`session_fingerprint`); None for a
        file written before fingerprints existed.
    """

    camera: Camera
    intrinsics: IntrinsicCalibration | None = None
    turntable: TurntableCalibration | None = None
    pattern: Pattern | None = None
    fingerprint: dict | None = None

    # ------------------------------------------------------------ reading
    @property
    def rms_px(self) -> float | None:
        """Intrinsic reprojection RMS, px (None when the intrinsics were given)."""
        return None if self.intrinsics is None else self.intrinsics.rms_px

    @property
    def turntable_rms_px(self) -> float | None:
        """Turntable joint-fit RMS, px (None without a turntable fit)."""
        return None if self.turntable is None else self.turntable.rms_px

    def cameras(self, session: Session | str | Path) -> list[Camera]:
        """The camera of every view of ``session``.

        A view's pose is its given ``pose`` when ``session.json`` has one, otherwise the
        turntable's ``R = R_cam @ Rz(angle)``, ``t = t_cam``.

        Parameters
        ----------
        session : Session

        Returns
        -------
        list of Camera, one per view, world to camera, mm
        """
        session = _as_session(session)
        if tuple(self.camera.image_size) != tuple(session.image_size):
            raise CalibrationError(
                f"{session.json_path}: image_size: the calibration is for {_wxh(self.camera.image_size)} images, "
                f"the session's are {_wxh(session.image_size)}; recalibrate (organlab reconstruct --recalibrate)"
            )
        cams = []
        for i, v in enumerate(session.views):
            if v.pose is not None:
                cams.append(self.camera.with_pose(*v.pose))
            elif self.turntable is not None:
                cams.append(self.turntable.camera.at_table_angle(v.angle_deg))
            else:
                raise CalibrationError(
                    f"{session.json_path}: views[{i}].pose: no pose and no turntable calibration; "
                    f"run 'organlab calibrate {session.root}'"
                )
        return cams

    def mismatch(self, session: Session | str | Path) -> list[str]:
        """Why this calibration does not belong to ``session`` (empty when it does).

        Compared: the image size; and, when the session has board images, the pattern, the
        board images' content and the intrinsics given in ``session.json``.

        Returns
        -------
        list of str
        """
        session = _as_session(session)
        why = []
        if tuple(self.camera.image_size) != tuple(session.image_size):
            why.append(f"it is for {_wxh(self.camera.image_size)} images, the session's are {_wxh(session.image_size)}")
        if not (session.intrinsic_images or session.turntable_images):
            return why
        if self.fingerprint is None:
            return why + ["it has no fingerprint (written by an older organlab), so it cannot be checked"]
        now = session_fingerprint(session)
        if self.fingerprint.get("pattern") != now["pattern"]:
            why.append(f"its pattern {_pat(self.fingerprint.get('pattern'))} differs from the session's {_pat(now['pattern'])}")
        if self.fingerprint.get("board_images") != now["board_images"]:
            why.append("it was computed from other board images (or angles) than the session's")
        if self.fingerprint.get("camera_given") != now["camera_given"]:
            why.append("the intrinsics given in session.json changed")
        return why

    def verify(self, session: Session | None = None) -> list[str]:
        """Why the numbers of this calibration cannot be trusted (empty when they can).

        The fingerprint covers what a calibration was computed *from*; this checks what
        it *says*.  The stored corners of every board image are reprojected with the
        stored camera and the stored poses (each intrinsic image's ``rvec``/``tvec``;
        the turntable's ``R_cam``, ``t_cam``, board offset and table angles) and the RMS
        found must reproduce the stored ones (:data:`VERIFY_ABS_PX`, :data:`VERIFY_REL`);
        the intrinsics must be plausible (:data:`PLAUSIBLE_FOCAL_FACTOR`); intrinsics
        marked as given in ``session.json`` must equal the session's.

        A file whose corners, camera and poses were all changed together so that they
        agree cannot be told from a real calibration (docs/trust.md).

        Parameters
        ----------
        session : Session, optional
            For the intrinsics it gives.

        Returns
        -------
        list of str
        """
        why = _implausible(self.camera)
        if why:
            return why
        if session is not None and self.intrinsics is None and session.camera is not None:
            if not (np.allclose(self.camera.K, session.camera["K"], rtol=1e-9, atol=1e-9)
                    and np.allclose(self.camera.dist, session.camera["dist"], rtol=1e-9, atol=1e-12)):
                why.append("its intrinsics are marked as given in session.json but differ from the session's camera")
        pattern = self.pattern if self.pattern is not None else getattr(session, "pattern", None)
        if (self.intrinsics is not None or self.turntable is not None) and pattern is None:
            return why + [f"it has no pattern, so its numbers {_CANNOT}"]
        if self.intrinsics is not None:
            why += _verify_intrinsics(self.intrinsics, self.camera, pattern)
        if self.turntable is not None:
            why += _verify_turntable(self.turntable, pattern)
        return why

    # ------------------------------------------------------------ file form
    def to_dict(self) -> dict:
        """JSON-ready: the content of ``calibration.json`` (``docs/session-format.md``)."""
        out = {"format": FORMAT}
        if self.pattern is not None:
            out["pattern"] = {"inner_corners": list(self.pattern.inner_corners), "square_size": self.pattern.square_size}
        if self.intrinsics is not None:
            out["camera"] = self.intrinsics.to_dict()
        else:
            out["camera"] = dict(self.camera.intrinsics_dict(), rms_px=None, source="session.json")
        if self.turntable is not None:
            out["turntable"] = self.turntable.to_dict()
        if self.fingerprint is not None:
            out["fingerprint"] = dict(self.fingerprint)
        return out

    @classmethod
    def from_dict(cls, d: dict, *, image_size: tuple[int, int] | None = None,
                  where: str | Path = "calibration.json") -> Calibration:
        """Build from the content of a ``calibration.json``, checking it.

        Parameters
        ----------
        d : dict
        image_size : (2,) int, optional
            ``(width, height)`` px, used when ``d['camera']`` has none (older files).
        where : str
            Named in error messages (the file).

        Raises
        ------
        CalibrationError
            One line per problem, each naming ``where`` and the key.
        """
        return _from_dict(cls, d, image_size, str(where))

    def save(self, path: str | Path) -> Path:
        """Write ``calibration.json`` atomically (a temporary file, then renamed).

        Returns
        -------
        Path
        """
        path = Path(path)
        tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
        _remove_stale_temporaries(path)
        try:
            write_json(tmp, self.to_dict())
            os.replace(tmp, path)
        except OSError as e:
            tmp.unlink(missing_ok=True)
            raise CalibrationError(f"{path}: cannot write the calibration ({e.strerror}); choose a writable folder") from None
        return path

    @classmethod
    def load(cls, path: str | Path, *, image_size: tuple[int, int] | None = None) -> Calibration:
        """Read and check a ``calibration.json``.

        Raises
        ------
        CalibrationError
            Missing file, invalid JSON, or a wrong shape: one line per problem.
        """
        path = Path(path)
        if path.is_dir():
            path = path / "calibration.json"
        if not path.is_file():
            raise CalibrationError(f"{path}: no such calibration file")
        d = read_json(path, error=CalibrationError, fix="recalibrate (organlab calibrate)")
        return cls.from_dict(d, image_size=image_size, where=path)

    def warnings(self) -> list[str]:
        """What a user must know before trusting this calibration, one line each (list of str).

        Turntable images set aside (their board does not agree with the others':
        moved between stops, or a wrong angle), and a turntable fit whose RMS is
        beyond :data:`TURNTABLE_RMS_FACTOR` times the intrinsic RMS.
        """
        out = []
        t = self.turntable
        if t is None:
            return out
        if t.flagged:
            off = ", ".join(f"{n} {t.per_image_rms.get(n, float('nan')):.2f} px" for n in t.flagged)
            out.append(f"turntable images set aside, their board disagrees with the other {len(t.per_image_rms) - len(t.flagged)} "
                       f"images' fit (moved between stops, or a wrong angle): {off}")
        if self.rms_px and t.rms_px > TURNTABLE_RMS_FACTOR * self.rms_px:
            out.append(f"turntable fit RMS {t.rms_px:.3f} px is more than {TURNTABLE_RMS_FACTOR:g}x the intrinsic RMS "
                       f"{self.rms_px:.3f} px: the board moved on the table or the angles are wrong; check the "
                       "turntable check figures (organlab calibrate)")
        return out

    def summary(self) -> list[str]:
        """A few lines for a terminal."""
        K = self.camera.K
        lines = []
        if self.intrinsics is None:
            lines.append("intrinsics given in session.json")
        else:
            lines.append(f"intrinsics RMS {self.rms_px:.3f} px over {len(self.intrinsics.per_image_rms)} images"
                         + (f" ({len(self.intrinsics.rejected)} rejected)" if self.intrinsics.rejected else ""))
        lines.append(f"fx {K[0, 0]:.2f}, fy {K[1, 1]:.2f}, cc ({K[0, 2]:.2f}, {K[1, 2]:.2f}), "
                     f"kc {[round(float(k), 5) for k in self.camera.dist]}")
        if self.turntable is not None:
            t = self.turntable
            lines.append(f"turntable RMS {t.rms_px:.3f} px over {len(t.per_image_rms) - len(t.flagged)} images"
                         + (f" (flagged: {', '.join(t.flagged)})" if t.flagged else ""))
        return lines


def _remove_stale_temporaries(path):
    """Remove ``.NAME.tmpPID`` files beside ``path`` left by a process that no longer runs (a kill -9)."""
    for p in path.parent.glob(f".{path.name}.tmp*"):
        pid = p.name[len(f".{path.name}.tmp"):]
        if not pid.isdigit() or int(pid) == os.getpid():
            continue
        try:
            os.kill(int(pid), 0)
        except ProcessLookupError:
            p.unlink(missing_ok=True)
        except OSError:  # alive, someone else's
            pass


# ================================================================= session glue
def session_fingerprint(session: Session) -> dict:
    """What a calibration of ``session`` is computed from, hashed.

    Returns
    -------
    dict
        ``image_size``, ``pattern`` (or None), ``board_images`` (SHA-256 over every board
        image's name, bytes and table angle, in session order), ``camera_given`` (the
        intrinsics given in ``session.json``, or None).
    """
    session = _as_session(session)
    h = hashlib.sha256()
    items = [(p, None) for p in session.intrinsic_images] + list(session.turntable_images)
    for p, angle in items:
        h.update(session.relpath(p).encode())
        h.update(Path(p).read_bytes())
        h.update(repr(None if angle is None else float(angle)).encode())
    pat = session.pattern
    given = None if session.camera is None else {
        "K": np.asarray(session.camera["K"], float).tolist(), "dist": np.asarray(session.camera["dist"], float).tolist()}
    return {
        "image_size": list(session.image_size),
        "pattern": None if pat is None else {"inner_corners": list(pat.inner_corners), "square_size": float(pat.square_size)},
        "board_images": h.hexdigest(),
        "camera_given": given,
    }


def calibrate(session: Session | str | Path, *, progress: Callable[[int, int], object] | None = None) -> Calibration:
    """Calibrate a session from its board images.

    Intrinsics come from ``session.json``'s ``camera`` when given (no fit), otherwise from
    ``calibration.intrinsic_images``; the turntable fit runs when
    ``calibration.turntable_images`` are given.  Nothing is written: see
    :meth:`Calibration.save`.

    Parameters
    ----------
    session : Session or str or Path
    progress : callable(done, total), optional
        Over all calibration images.

    Returns
    -------
    Calibration

    Raises
    ------
    CalibrationError

    Examples
    --------
    >>> import tempfile
    >>> import organlab as ol
    >>> from organlab.synthetic import with_true_cameras
    >>> s = ol.load_session(with_true_cameras("sample_sessions/aaa_phantom", tempfile.mkdtemp() + "/aaa", step=6))
    >>> cal = ol.calibrate(s)  # the session gives the intrinsics: the turntable is fitted on its 10 board images
    >>> cal.intrinsics is None, f"{cal.turntable.rms_px:.2f} px", cal.turntable.flagged
    (True, '0.04 px', [])
    """
    session = _as_session(session)
    where = session.json_path
    need_intr = session.camera is None
    n_intr = len(session.intrinsic_images) if need_intr else 0
    n_tt = len(session.turntable_images)
    if need_intr and n_intr == 0:
        raise CalibrationError(f"{where}: no intrinsics: give 'camera' or 'calibration.intrinsic_images'")
    if (n_intr or n_tt) and session.pattern is None:
        raise CalibrationError(
            f"{where}: pattern is required to calibrate from board images: {{'inner_corners': [cols, rows], 'square_size': mm}}")
    total = n_intr + n_tt

    def sub(offset):
        return None if progress is None else (lambda done, _n: progress(offset + done, total))

    intr = None
    camera = session.given_camera()
    if need_intr:
        imgs = [session.read(p, key=f"calibration.intrinsic_images[{i}]", grey=True) for i, p in enumerate(session.intrinsic_images)]
        names = [session.relpath(p) for p in session.intrinsic_images]
        try:
            intr = calibrate_intrinsics(imgs, session.pattern, image_size=session.image_size, names=names, progress=sub(0))
        except CalibrationError as e:
            raise CalibrationError(f"{where}: calibration.intrinsic_images: {e}") from None
        camera = intr.camera
    tt = None
    if n_tt:
        imgs = [session.read(p, key=f"calibration.turntable_images[{i}].image", grey=True)
                for i, (p, _) in enumerate(session.turntable_images)]
        names = [session.relpath(p) for p, _ in session.turntable_images]
        angles = [a for _, a in session.turntable_images]
        try:
            tt = calibrate_turntable(imgs, angles, camera, session.pattern, names=names, progress=sub(n_intr))
        except CalibrationError as e:
            raise CalibrationError(f"{where}: calibration.turntable_images: {e}") from None
    return Calibration(camera, intr, tt, session.pattern, session_fingerprint(session))


def needs_calibration(session: Session) -> bool:
    """True when the session lacks given intrinsics, or a view lacks a given pose."""
    session = _as_session(session)
    return session.camera is None or any(v.pose is None for v in session.views)


def calibration_for(session: Session | str | Path, *, calibration: Calibration | None = None, recalibrate: bool = False,
                    progress: Callable[[int, int], object] | None = None) -> tuple[Calibration, str]:
    """The calibration a reconstruction of ``session`` should use, and how it was obtained.

    In order: ``calibration`` when given (checked against the session: refused when it was
    computed from other board images, another pattern or image size); nothing to calibrate
    when ``session.json`` gives the intrinsics and every pose; the session's own
    ``calibration.json`` when it matches the session (:meth:`Calibration.mismatch`);
    otherwise (or with ``recalibrate``) a new :func:`calibrate`.  Nothing is written.

    Parameters
    ----------
    session : Session or str or Path
    calibration : Calibration or str or Path, optional
        A calibration (or its ``calibration.json``) to use instead of the session's own.
    recalibrate : bool
        Calibrate even when the session has a matching ``calibration.json``.
    progress : callable(done, total), optional
        Passed to :func:`calibrate` when it runs.

    Returns
    -------
    calibration : Calibration
    how : str
        ``'computed'``, ``'given'``, ``'session.json'``, ``'reused, verified'`` or
        ``'recomputed: <why the saved one was not used>'``.

    Examples
    --------
    >>> import tempfile
    >>> import organlab as ol
    >>> from organlab.synthetic import with_true_cameras
    >>> s = ol.load_session(with_true_cameras("sample_sessions/aaa_phantom", tempfile.mkdtemp() + "/aaa", step=6))
    >>> cal, how = ol.calibration_for(s)  # session.json gives the camera and every pose: nothing to fit
    >>> how, len(cal.cameras(s))
    ('session.json', 6)
    """
    session = _as_session(session)
    if calibration is not None:
        if not isinstance(calibration, Calibration):
            calibration = Calibration.load(calibration, image_size=session.image_size)
        why = calibration.mismatch(session)
        if why:
            raise CalibrationError(
                f"{session.json_path}: the given calibration does not belong to this session: {'; '.join(why)}; "
                "recalibrate (organlab reconstruct --recalibrate) or give the right calibration.json")
        why = calibration.verify(session)
        wrong = [w for w in why if _CANNOT not in w]
        if wrong:
            raise CalibrationError(
                f"{session.json_path}: the given calibration cannot be trusted: {'; '.join(wrong)}; "
                "recalibrate (organlab reconstruct --recalibrate) or give the right calibration.json")
        return calibration, ("given, not verified: " + "; ".join(why)) if why else "given, verified"
    if not needs_calibration(session):
        return Calibration(session.given_camera(), fingerprint=session_fingerprint(session)), "session.json"
    if session.calibration is not None and not recalibrate:
        saved = Calibration.from_dict(session.calibration, image_size=session.image_size, where=session.calibration_path)
        why = saved.mismatch(session)
        if saved.turntable is None and any(v.pose is None for v in session.views):
            why.append("it has no turntable fit and some views have no pose")
        checked = saved.verify(session)
        boards = bool(session.intrinsic_images or session.turntable_images)
        if not why and not checked:
            return saved, "reused, verified"
        if not why and not boards and all(_CANNOT in w for w in checked):
            return saved, f"reused, NOT verified: {'; '.join(checked)}"
        why += checked
        if not boards:
            raise CalibrationError(f"{session.calibration_path}: does not match the session ({'; '.join(why)}) "
                                   "and the session has no board images to recalibrate from")
        return calibrate(session, progress=progress), f"recomputed: {session.calibration_path.name} not used: {'; '.join(why)}"
    return calibrate(session, progress=progress), "computed"


# ================================================================= verification
_CANNOT = "cannot be checked"


def _implausible(camera):
    K, (w, h) = camera.K, camera.image_size
    side = max(w, h)
    fx, fy = K[0, 0], K[1, 1]
    why = []
    if not (side / PLAUSIBLE_FOCAL_FACTOR <= min(fx, fy) and max(fx, fy) <= side * PLAUSIBLE_FOCAL_FACTOR):
        why.append(f"its focal lengths fx {fx:g}, fy {fy:g} px are implausible for {w}x{h} images")
    elif not 0.5 <= fx / fy <= 2.0:
        why.append(f"its aspect fx/fy = {fx / fy:.3g} is implausible (a pixel 2x wider than tall)")
    if not (0 <= K[0, 2] <= w and 0 <= K[1, 2] <= h):
        why.append(f"its principal point ({K[0, 2]:g}, {K[1, 2]:g}) px is outside the {w}x{h} image")
    if np.abs(camera.dist).max() > 100:
        why.append(f"its distortion {np.round(camera.dist, 3).tolist()} is implausible")
    return why


def _reproduces(found, stored):
    return abs(found - stored) <= VERIFY_ABS_PX + VERIFY_REL * stored


def _verify_intrinsics(intr, camera, pattern):
    obj = board_points(pattern)
    used = [n for n in intr.per_image_rms if n in intr.corners and n in intr.extrinsics]
    if not used or len(used) < len(intr.per_image_rms):
        return ["its intrinsic images have no stored corners or poses (written by an older organlab), so its numbers "
                "cannot be checked"]
    res = []
    for n in used:
        c = intr.corners[n]
        if c.shape != (obj.shape[0], 2):
            return [f"camera.images.{n}: {c.shape[0]} corners but the pattern has {obj.shape[0]}"]
        rv, tv = intr.extrinsics[n]
        if rv.shape != (3,) or tv.shape != (3,):
            return [f"camera.images.{n}: rvec and tvec must be 3 numbers each"]
        pc = obj @ _rodrigues(rv)[0].T + tv
        if np.any(pc[:, 2] <= 0):
            return [f"camera.images.{n}: its board is behind the camera"]
        res.append(_project(camera.K, camera.dist, pc) - c)
    found = _rms(np.stack(res))
    if intr.rms_px is None or not _reproduces(found, intr.rms_px):
        return [f"its stored corners reprojected with its camera and poses give an RMS of {found:.3g} px, "
                f"not the {_g(intr.rms_px)} px it states (its numbers were changed)"]
    return []


def _verify_turntable(tt, pattern):
    obj = board_points(pattern)
    names = [n for n in tt.per_image_rms if n not in tt.flagged]
    if not names or any(n not in tt.corners or n not in tt.angles_deg for n in names):
        return ["its turntable images have no stored corners or angles (written by an older organlab), so its "
                f"numbers {_CANNOT}"]
    off = np.asarray(tt.board_offset_mm, dtype=np.float64).ravel()
    if off.shape != (2,) or not np.all(np.isfinite(off)):
        return ["turntable.axis.board_offset_mm must be 2 finite numbers"]
    cam = tt.camera
    res = []
    for n in names:
        c = tt.corners[n]
        if c.shape != (obj.shape[0], 2):
            return [f"turntable.images.{n}: {c.shape[0]} corners but the pattern has {obj.shape[0]}"]
        Xw = (obj + [off[0], off[1], 0.0]) @ rot_z(tt.angles_deg[n]).T
        pc = Xw @ cam.R.T + cam.t
        if np.any(pc[:, 2] <= 0):
            return [f"turntable.images.{n}: its board is behind the camera"]
        res.append(_project(cam.K, cam.dist, pc) - c)
    found = _rms(np.stack(res))
    if tt.rms_px is None or not _reproduces(found, tt.rms_px):
        return [f"its stored turntable corners reprojected with its camera, axis and angles give an RMS of "
                f"{found:.3g} px, not the {_g(tt.rms_px)} px it states (its numbers were changed)"]
    return []


# ================================================================= file form, read
def _as_session(session):
    return session if isinstance(session, Session) else load_session(session)


def _wxh(size):
    return f"{size[0]}x{size[1]}"


def _pat(p):
    return "none" if not p else f"{p['inner_corners'][0]}x{p['inner_corners'][1]} of {p['square_size']:g} mm"


class _Problems:
    """Collects one line per problem in a calibration.json."""

    def __init__(self, where):
        self.where, self.lines = where, []

    def add(self, key, message):
        self.lines.append(f"{self.where}: {key}: {message}")

    def array(self, value, shape, key, *, required=True):
        if value is None:
            if required:
                self.add(key, f"is missing; expected {_shape_text(shape)}")
            return None
        try:
            a = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError, OverflowError):
            self.add(key, f"must be {_shape_text(shape)} numbers, got {_short(value)}")
            return None
        if a.shape != shape:
            self.add(key, f"must be {_shape_text(shape)}, got shape {a.shape}")
            return None
        if not np.all(np.isfinite(a)):
            self.add(key, "must hold finite numbers")
            return None
        return a

    def number(self, value, key, *, required=False):
        if value is None:
            if required:
                self.add(key, "is missing")
            return None
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value < 0:
            self.add(key, f"must be a finite number >= 0, got {_short(value)}")
            return None
        return float(value)

    def raise_if_any(self):
        if self.lines:  # one line: the first problem, and how many more
            hint = "; fix it or recalibrate (organlab calibrate, or reconstruct --recalibrate)"
            more = f" (and {len(self.lines) - 1} more)" if len(self.lines) > 1 else ""
            raise CalibrationError(self.lines[0] + more + hint)


def _shape_text(shape):
    return {(3, 3): "a 3x3 matrix", (5,): "5 numbers [k1, k2, p1, p2, k3]", (3,): "3 numbers", (2,): "2 numbers"}.get(shape, str(shape))


def _short(v):
    s = repr(v)
    return s if len(s) < 40 else s[:37] + "..."


def _from_dict(cls, d, image_size, where):
    pr = _Problems(where)
    if not isinstance(d, dict):
        raise CalibrationError(f"{where}: must be a JSON object with 'camera' (and 'turntable'); recalibrate")
    cam_d = d.get("camera")
    if not isinstance(cam_d, dict):
        pr.add("camera", f"must be an object with K, dist, image_size, got {_short(cam_d)}")
        pr.raise_if_any()
    K = pr.array(cam_d.get("K"), (3, 3), "camera.K")
    dist = pr.array(cam_d.get("dist", [0, 0, 0, 0, 0]), (5,), "camera.dist")
    size = cam_d.get("image_size", image_size)
    if not (isinstance(size, (list, tuple)) and len(size) == 2
            and all(isinstance(s, int) and not isinstance(s, bool) and 0 < s <= 1_000_000 for s in size)):
        pr.add("camera.image_size", f"must be [width, height] in px, got {_short(size)}")
    tt_d = d.get("turntable")
    if tt_d is not None and not isinstance(tt_d, dict):
        pr.add("turntable", f"must be an object with R_cam, t_cam, got {_short(tt_d)}")
        tt_d = None
    R = t = None
    if tt_d is not None:
        R = pr.array(tt_d.get("R_cam"), (3, 3), "turntable.R_cam")
        t = pr.array(tt_d.get("t_cam"), (3,), "turntable.t_cam")
    pattern = _pattern(d.get("pattern"), pr)
    fp = d.get("fingerprint")
    if fp is not None and not isinstance(fp, dict):
        pr.add("fingerprint", "must be an object")
        fp = None
    if fp is not None and fp.get("pattern") is not None and _pattern(fp["pattern"], _Problems(where)) is None:
        pr.add("fingerprint.pattern", f"must be {{'inner_corners': [cols, rows], 'square_size': mm}}, got {_short(fp['pattern'])}")
        fp = None
    pr.raise_if_any()
    try:
        camera = Camera(K, dist, image_size=tuple(size))
    except ValueError as e:
        pr.add("camera", str(e))
        pr.raise_if_any()
    tt_cam = None
    if tt_d is not None:
        try:  # printed to a few digits: within 1e-4 of orthonormal, replaced by the nearest rotation
            tt_cam = camera.with_pose(nearest_rotation(R)[0], t)
        except ValueError as e:
            pr.add("turntable.R_cam", str(e))
    pr.raise_if_any()
    if cam_d.get("source") not in (None, "session.json", "calibrated"):
        pr.add("camera.source", f"must be 'calibrated' or 'session.json', got {_short(cam_d.get('source'))}")
    intr = None if cam_d.get("source") == "session.json" else _intrinsics_from(cam_d, camera, pr)
    tt = None if tt_d is None else _turntable_from(tt_d, tt_cam, pr)
    pr.raise_if_any()
    return cls(camera, intr, tt, pattern, fp)


def _pattern(p, pr):
    if p is None:
        return None
    ic = p.get("inner_corners") if isinstance(p, dict) else None
    sq = p.get("square_size") if isinstance(p, dict) else None
    ok_ic = isinstance(ic, list) and len(ic) == 2 and all(isinstance(v, int) and not isinstance(v, bool) and 2 <= v <= 1000
                                                          for v in ic)
    ok_sq = isinstance(sq, (int, float)) and not isinstance(sq, bool) and math.isfinite(sq) and 0 < sq < 1e6
    if not (ok_ic and ok_sq):
        pr.add("pattern", f"must be {{'inner_corners': [cols, rows] (2-1000), 'square_size': mm > 0}}, got {_short(p)}")
        return None
    return Pattern(tuple(ic), float(sq))


def _per_image(images, pr, key):
    if images is None:
        return {}
    if not isinstance(images, dict):
        pr.add(key, "must be an object keyed by image name")
        return {}
    bad = [n for n, e in images.items() if not isinstance(e, dict)]
    if bad:
        pr.add(f"{key}.{_short(bad[0])}", "must be an object")
    return {n: e for n, e in images.items() if isinstance(e, dict)}


def _checked(pr, fn, *args, **kw):
    """``fn(*args, **kw)`` of organlab.validate, its error collected as one problem (None then)."""
    try:
        return fn(*args, error=CalibrationError, **kw)
    except CalibrationError as e:
        pr.lines.append(f"{pr.where}: {e}")
        return None


def _entries(images, pr, key, *, angle=False):
    """Per-image rms, poses, corners (and angles) of the stored images, each checked."""
    rms, ext, corners, angles = {}, {}, {}, {}
    for n, e in images.items():
        k = f"{key}.{n}"
        if "rms_px" in e:
            v = _checked(pr, _number, e["rms_px"], f"{k}.rms_px", lo=0)
            if v is not None:
                rms[n] = v
        if "rvec" in e or "tvec" in e:
            rv = _checked(pr, _array, e.get("rvec"), (3,), f"{k}.rvec")
            tv = _checked(pr, _array, e.get("tvec"), (3,), f"{k}.tvec")
            if rv is not None and tv is not None:
                ext[n] = (rv, tv)
        if "corners_px" in e:
            c = _checked(pr, _array, e["corners_px"], (-1, 2), f"{k}.corners_px")
            if c is not None:
                corners[n] = c
        if angle and "angle_deg" in e:
            a = _checked(pr, _number, e["angle_deg"], f"{k}.angle_deg", lo=-1e6, hi=1e6)
            if a is not None:
                angles[n] = a
    return rms, ext, corners, angles


def _std(value, pr, key, shapes):
    if value is None:
        return {}
    if not isinstance(value, dict):
        pr.add(key, f"must be an object, got {_short(value)}")
        return {}
    out = {}
    for k, shape in shapes.items():
        if k in value:
            a = _checked(pr, _array, value[k], shape, f"{key}.{k}", lo=0)
            if a is not None:
                out[k] = a
    return out


def _reasons(value, pr, key):
    """``rejected``: an object of image name to reason (text)."""
    if value is None:
        return {}
    if isinstance(value, list) and not value:
        return {}
    if not isinstance(value, dict) or not all(isinstance(v, str) for v in value.values()):
        pr.add(key, f"must be an object of image name to reason, got {_short(value)}")
        return {}
    return dict(value)


def _names_list(value, pr, key, allowed=None):
    if value is None:
        return []
    if not isinstance(value, list) or not all(isinstance(v, str) for v in value) or (
            allowed is not None and not set(value) <= set(allowed)):
        pr.add(key, f"must be a list of {'image names' if allowed is None else 'names among ' + str(sorted(allowed))}, "
                    f"got {_short(value)}")
        return []
    return list(value)


def _intrinsics_from(cam_d, camera, pr):
    images = _per_image(cam_d.get("images"), pr, "camera.images")
    rms = pr.number(cam_d.get("rms_px"), "camera.rms_px", required=True)  # summary() and verify() use it
    std = _std(cam_d.get("std"), pr, "camera.std", {"fc": (2,), "cc": (2,), "alpha_c": (), "kc": (5,)})
    if "alpha_c" in std:
        std["alpha_c"] = float(std["alpha_c"])
    per, ext, corners, _ = _entries(images, pr, "camera.images")
    return IntrinsicCalibration(
        camera=camera,
        rms_px=rms,
        per_image_rms=per,
        std=std,
        rejected=_reasons(cam_d.get("rejected"), pr, "camera.rejected"),
        extrinsics=ext,
        corners=corners,
        fixed=tuple(_names_list(cam_d.get("fixed"), pr, "camera.fixed", allowed=("alpha_c", "k3", "k2", "p1", "p2", "k1"))),
    )


def _turntable_from(tt_d, camera, pr):
    images = _per_image(tt_d.get("images"), pr, "turntable.images")
    axis = tt_d.get("axis") or {}
    if not isinstance(axis, dict):
        pr.add("turntable.axis", f"must be an object, got {_short(axis)}")
        axis = {}
    off = _checked(pr, _array, axis.get("board_offset_mm", [0.0, 0.0]), (2,), "turntable.axis.board_offset_mm")
    per, _, corners, angles = _entries(images, pr, "turntable.images", angle=True)
    return TurntableCalibration(
        camera=camera,
        rms_px=pr.number(tt_d.get("rms_px"), "turntable.rms_px", required=True),
        per_image_rms=per,
        flagged=_names_list(tt_d.get("flagged"), pr, "turntable.flagged"),
        rejected=_reasons(tt_d.get("rejected"), pr, "turntable.rejected"),
        angles_deg=angles,
        board_offset_mm=np.zeros(2) if off is None else off,
        std=_std(tt_d.get("std"), pr, "turntable.std",
                 {"rvec_cam": (3,), "t_cam": (3,), "board_offset_mm": (2,), "camera_center_mm": (3,)}),
        corners=corners,
    )


def _g(v):
    return "no" if v is None else f"{v:.3g}"
