"""Crash-safe capture of a session folder (``organlab.session/1``).

Order of a capture, each stage asking the operator first (:func:`console_prompt`):

1. ``background``: frames of the empty scene (specimen and board off the table);
2. ``intrinsics`` (optional): the board held by hand at varied poses in front of the camera;
3. ``turntable``: the board lying on the table, one image at every stop, each
   audited at once (:class:`~organlab.capture.AngleAudit`);
4. ``views``: the specimen on the table, one image at every stop, at exactly
   the angles of the board images.

``session.json`` is rewritten atomically (temporary file, fsync,
``os.replace``) after every image, so a capture that dies keeps every image it
took, listed.  Running the same capture again continues with the first image
missing; an image file is never overwritten (a name already taken gets a
suffix).  The capture's settings, the audit, the driver's events (retries,
corrected lost steps) and the last error are kept under ``capture`` in
``session.json``; every serial exchange goes to ``capture/serial.log``.
"""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import numpy as np

from ..errors import OrganlabError
from ..session import FORMAT, Pattern, save_session
from ._audit import AUDIT_LIMIT_DEG, AngleAudit
from ._errors import AngleAuditError, CameraError, CaptureError

__all__ = ["capture_session", "console_prompt", "stop_angles"]

STAGES = ("background", "intrinsics", "turntable", "views")
_MESSAGES = {
    "background": "remove the specimen and the board from the table (empty scene for the background)",
    "intrinsics": "hold the board in front of the camera at a new pose (tilted, toward an image corner)",
    "turntable": "lay the calibration board flat on the table (it must not move until all stops are taken)",
    "views": "remove the board and stand the specimen on the table",
}
LOG_NAME = "capture/serial.log"


def console_prompt(stage, message, index=None):
    """Ask the operator on the terminal and wait for Enter."""
    input(f"[{stage}] {message}, then press Enter ")


def stop_angles(step_deg):
    """The table stops ``0, step, 2 step, ...`` below 360 deg.

    Returns
    -------
    list of float, deg
    """
    step = float(step_deg)
    if not 0 < step <= 180:
        raise CaptureError(f"--step must be in (0, 180] deg, got {step_deg}")
    n = int(np.floor(360.0 / step - 1e-9)) + 1
    return [round(i * step, 6) for i in range(n)]


def _angle_name(a):
    return f"{int(round(a)):03d}" if abs(a - round(a)) < 1e-9 else f"{a:07.3f}".replace(".", "_")


def _free_name(root, rel):
    """``rel`` or, when that file exists (a crash before it was listed), ``stem_1``, ``stem_2``...: never overwrite."""
    p = Path(rel)
    k = 0
    cand = rel
    while (root / cand).exists():
        k += 1
        cand = (p.parent / f"{p.stem}_{k}{p.suffix}").as_posix()
    return cand


def _write_png(root, rel, image):
    import cv2

    path = root / rel
    path.parent.mkdir(parents=True, exist_ok=True)
    ok, buf = cv2.imencode(".png", image[:, :, ::-1] if image.ndim == 3 else image)
    if not ok:
        raise CaptureError(f"{path}: could not encode the image as PNG")
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as f:
        f.write(buf.tobytes())
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def _new_doc(root, *, name, pattern, roi, reference, intrinsics, settings):
    doc = {
        "format": FORMAT,
        "name": name or root.name,
        "units": "mm",
        "image_size": None,
        "pattern": {"type": "checkerboard", "inner_corners": list(pattern.inner_corners), "square_size": float(pattern.square_size)},
        "calibration": {"intrinsic_images": [], "turntable_images": []},
        "background_images": [],
        "views": [],
        "roi": {"min": [float(v) for v in roi["min"]], "max": [float(v) for v in roi["max"]]},
        "capture": dict(settings, complete=False, audit=[], flagged=[], events=[], log=LOG_NAME),
    }
    if reference is not None:
        doc["reference"] = dict(reference)
    if intrinsics is not None:
        doc["camera"] = {"K": np.asarray(intrinsics.K).tolist(), "dist": np.asarray(intrinsics.dist).tolist()}
    return doc


def _load_doc(root, settings):
    sj = root / "session.json"
    try:
        doc = json.loads(sj.read_text(encoding="utf-8"))
    except (OSError, ValueError) as e:
        raise CaptureError(f"{sj}: cannot be read ({e}); capture into a new folder") from None
    cap = doc.get("capture") if isinstance(doc, dict) else None
    if not isinstance(cap, dict):
        raise CaptureError(f"{sj}: not a session made by 'organlab capture' (no 'capture' key); capture into a new folder")
    for key in ("step_deg", "n_background", "n_intrinsic", "board"):
        if cap.get(key) != settings[key]:
            raise CaptureError(f"{sj}: capture.{key} is {cap.get(key)!r} but this run asks {settings[key]!r}; "
                               f"run with the same settings to continue, or capture into a new folder")
    return doc


def _todo(doc, angles):
    """Remaining (stage, index or angle) items, in capture order."""
    cap = doc["capture"]
    cal = doc["calibration"]
    items = [("background", i) for i in range(len(doc["background_images"]), cap["n_background"])]
    items += [("intrinsics", i) for i in range(len(cal["intrinsic_images"]), cap["n_intrinsic"])]
    if cap["board"]:
        done = {round(e["angle_deg"], 6) for e in cal["turntable_images"]}
        items += [("turntable", a) for a in angles if round(a, 6) not in done]
    done = {round(e["angle_deg"], 6) for e in doc["views"]}
    items += [("views", a) for a in angles if round(a, 6) not in done]
    return items


class _Capture:
    """State of one capture run (private worker of :func:`capture_session`)."""

    def __init__(self, root, doc, turntable, camera, *, pattern, audit_limit_deg, stop_on_flag, prompt, on_view, say, progress):
        self.root, self.doc, self.table, self.camera = root, doc, turntable, camera
        self.pattern, self.limit, self.stop_on_flag = pattern, audit_limit_deg, stop_on_flag
        self.prompt, self.on_view, self.say, self.progress = prompt, on_view, say, progress
        self.audit = None
        self.n_events = len(getattr(turntable, "events", []))

    def save(self):
        events = getattr(self.table, "events", [])
        if len(events) > self.n_events:
            self.doc["capture"]["events"].extend(events[self.n_events:])
            self.n_events = len(events)
        save_session(self.root, self.doc)  # atomically: temporary file, fsync, rename

    def grab(self, rel):
        image = self.camera.grab()
        if image.ndim != 3 or image.dtype != np.uint8:
            raise CameraError(f"{getattr(self.camera, 'name', 'camera')}: frames must be RGB uint8, got {image.dtype} {image.shape}")
        size = [int(image.shape[1]), int(image.shape[0])]
        if self.doc["image_size"] is None:
            self.doc["image_size"] = size
        elif self.doc["image_size"] != size:
            raise CameraError(f"{getattr(self.camera, 'name', 'camera')}: image is {size[0]}x{size[1]} but the session's "
                              f"images are {self.doc['image_size'][0]}x{self.doc['image_size'][1]}; use the same camera and size")
        rel = _free_name(self.root, rel)
        _write_png(self.root, rel, image)
        return rel, image

    def audit_camera(self):
        """Intrinsics for the audit: given ones, else calibrated from this session's hand-held board images."""
        from ..camera import Camera

        if "camera" in self.doc:
            return Camera(self.doc["camera"]["K"], self.doc["camera"]["dist"], image_size=self.doc["image_size"])
        names = self.doc["calibration"]["intrinsic_images"]
        if len(names) < 3:
            return None
        from ..calibration import calibrate_intrinsics
        from ..session import read_image

        imgs = [read_image(self.root / n, grey=True) for n in names]
        try:
            return calibrate_intrinsics(imgs, self.pattern, image_size=tuple(self.doc["image_size"]), names=names).camera
        except OrganlabError as e:  # CalibrationError: the capture goes on, without the audit
            self.say(f"capture: angle audit off: intrinsics could not be calibrated from the hand-held images ({e})")
            return None

    def start_audit(self):
        cam = self.audit_camera()
        if cam is None:
            self.say("capture: angle audit off: no intrinsics (give them, or capture hand-held board images first)")
            self.doc["capture"]["audit_limit_deg"] = None
            return
        self.audit = AngleAudit(cam, self.pattern, limit_deg=self.limit)
        self.doc["capture"]["audit_limit_deg"] = self.limit
        from ..session import read_image

        for e in self.doc["calibration"]["turntable_images"][:1]:  # the reference stop of an earlier run
            self.audit.check(read_image(self.root / e["image"]), e["angle_deg"])

    def stop(self, stage, angle):
        read_back = self.table.move_to(angle)
        base = "calibration/turntable" if stage == "turntable" else "views"
        rel, image = self.grab(f"{base}/{_angle_name(angle)}.png")
        entry = {"image": rel, "angle_deg": float(angle), "read_back_deg": round(float(read_back), 6)}
        if stage == "views":
            self.doc["views"].append(entry)
            self.save()
            if self.on_view is not None:
                self.on_view(len(self.doc["views"]) - 1, float(angle), image)
            return
        result = self.audit.check(image, angle) if self.audit is not None else None
        if result is None or not result["flagged"]:
            self.doc["calibration"]["turntable_images"].append(entry)
            if result is not None:
                self.doc["capture"]["audit"].append(dict(result, image=rel))
            self.save()
            return
        # flagged: kept on disk and listed under capture.flagged, not used for calibration; retaken next run
        self.doc["capture"]["flagged"].append(dict(result, image=rel))
        self.save()
        msg = f"angle audit: {rel}: {result['reason']}"
        self.say(f"capture: FLAGGED {msg}")
        if self.stop_on_flag:
            raise AngleAuditError(f"{self.root / 'session.json'}: {msg}; check the table and the board, then run again to continue")

    def run(self, items):
        total = len(items)
        stage_now = None
        for k, (stage, what) in enumerate(items):
            if stage != stage_now or stage == "intrinsics":
                self.prompt(stage, _MESSAGES[stage], what if stage == "intrinsics" else None)
                if stage == "turntable" and stage_now != "turntable":
                    self.start_audit()
                stage_now = stage
            if stage == "background":
                rel, _ = self.grab(f"background/{what:02d}.png")
                self.doc["background_images"].append(rel)
                self.save()
            elif stage == "intrinsics":
                rel, _ = self.grab(f"calibration/intrinsics/{what:02d}.png")
                self.doc["calibration"]["intrinsic_images"].append(rel)
                self.save()
            else:
                self.stop(stage, what)
            self.progress(k + 1, total)


def capture_session(
    out,
    turntable,
    camera,
    *,
    step_deg=10.0,
    n_background=20,
    n_intrinsic=0,
    board=True,
    intrinsics=None,
    pattern=None,
    roi=None,
    reference=None,
    name=None,
    audit_limit_deg=AUDIT_LIMIT_DEG,
    stop_on_flag=True,
    prompt=console_prompt,
    on_view=None,
    say=None,
    progress=None,
):
    """Capture a session folder, or continue one that stopped.

    Parameters
    ----------
    out : str or Path
        The session folder (created).  When it holds a capture's
        ``session.json``, the capture continues with the first missing image.
    turntable : Turntable
        An open table (e.g. :class:`~organlab.capture.MDriveTurntable`); it is
        homed first when it has a home switch, otherwise a new capture takes
        its current position as 0.  Not closed here.
    camera : CaptureCamera
        Not closed here.
    step_deg : float
        Table step between stops, deg (stops at ``0, step, ...`` below 360).
    n_background : int
        Frames of the empty scene (the thesis took 20).
    n_intrinsic : int
        Hand-held board images for the intrinsic calibration (0 when
        ``intrinsics`` are given or calibrated elsewhere).
    board : bool
        Take a board image on the table at every stop (turntable calibration and angle audit).
    intrinsics : organlab.camera.Camera, optional
        Known intrinsics; written as the session's ``camera`` and used by the audit.
    pattern : organlab.session.Pattern, optional
        The board (default 9 x 6 inner corners, 20 mm squares).
    roi : dict, optional
        ``{"min": [x, y, z], "max": [x, y, z]}``, mm, world frame (default
        ``organlab.synthetic.DEFAULT_ROI``).
    reference : dict, optional
        Independent measurements, e.g. ``{"volume_mm3": ...}``.
    name : str, optional
    audit_limit_deg : float
        Largest accepted difference between the angle measured from a board
        image and the commanded angle.
    stop_on_flag : bool
        Stop the capture (:class:`AngleAuditError`) at a flagged stop, before
        more images are taken; otherwise only flag it.
    prompt : callable(stage, message, index)
        Asks the operator to prepare ``stage``; the simulated rig's
        :meth:`~organlab.capture.SimRig.prompt` does it itself.
    on_view : callable(index, angle_deg, image), optional
        Called after each view is saved (e.g. a live viewer).
    say : callable(str), optional
        Where flags and notes are printed (default: stderr).
    progress : callable(done, total), optional

    Returns
    -------
    Path
        The session folder, its ``session.json`` complete.

    Raises
    ------
    CaptureError
        Any failure of the table, camera or audit; every image taken so far
        is on disk and listed, and ``capture.last_error`` says what happened.
    """
    from ..synthetic import DEFAULT_PATTERN, DEFAULT_ROI
    from ._mdrive import SerialLog

    root = Path(out)
    pattern = DEFAULT_PATTERN if pattern is None else (pattern if isinstance(pattern, Pattern) else Pattern(*pattern))
    say = say if say is not None else (lambda s: print(s, file=sys.stderr))
    angles = stop_angles(step_deg)
    for label, v in (("n_background", n_background), ("n_intrinsic", n_intrinsic)):
        if int(v) < 0:
            raise CaptureError(f"{label} must be >= 0, got {v}")
    settings = {"step_deg": float(step_deg), "n_background": int(n_background), "n_intrinsic": int(n_intrinsic), "board": bool(board),
                "turntable": repr(turntable), "camera": getattr(camera, "name", type(camera).__name__)}
    root.mkdir(parents=True, exist_ok=True)
    if (root / "session.json").exists():
        doc = _load_doc(root, settings)
        doc["capture"].update(turntable=settings["turntable"], camera=settings["camera"])
    else:
        doc = _new_doc(root, name=name, pattern=pattern, roi=roi or DEFAULT_ROI, reference=reference, intrinsics=intrinsics, settings=settings)
    log = getattr(turntable, "log", None)
    if isinstance(log, SerialLog) and log.path is None:
        log.path = root / LOG_NAME
        log.path.parent.mkdir(parents=True, exist_ok=True)
        with open(log.path, "a", encoding="utf-8") as f:
            f.write("".join(line + "\n" for line in log.lines))
    run = _Capture(root, doc, turntable, camera, pattern=pattern, audit_limit_deg=audit_limit_deg, stop_on_flag=stop_on_flag,
                   prompt=prompt, on_view=on_view, say=say, progress=progress or (lambda done, total: None))
    items = _todo(doc, angles)
    try:
        if items and any(stage in ("turntable", "views") for stage, _ in items):
            if turntable.has_home_switch:
                turntable.home()
            elif not doc["calibration"]["turntable_images"] and not doc["views"]:
                turntable.zero()
        run.save()
        run.run(items)
    except CaptureError as e:
        doc["capture"]["last_error"] = str(e)
        run.save()
        raise
    doc["capture"]["complete"] = True
    doc["capture"].pop("last_error", None)
    run.save()
    return root
