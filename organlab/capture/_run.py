"""Open the rig a user names (``sim`` or a serial port; ``sim``, a camera index, a URL or a folder) and capture."""

from __future__ import annotations

from pathlib import Path

from .._validate import read_json
from ._errors import CaptureError

__all__ = ["run_capture", "read_intrinsics"]


def read_intrinsics(path, image_size=None):
    """Intrinsics from a ``calibration.json`` (``camera``) or a ``session.json`` (``camera``).

    Returns
    -------
    organlab.camera.Camera
    """
    from ..camera import Camera

    p = Path(path)
    doc = read_json(p, error=CaptureError, fix="give a calibration.json or session.json with 'camera'")
    try:
        cam = doc["camera"]
        return Camera(cam["K"], cam["dist"], image_size=image_size or cam.get("image_size") or doc.get("image_size"))
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise CaptureError(f"{p}: no usable 'camera' with 'K' and 'dist' ({e}); give a calibration.json or session.json") from None


def _open_camera(spec, rig, *, settle_frames, average):
    from ._cameras import FolderCamera, OpenCVCamera

    if spec == "sim":
        if rig is None:
            raise CaptureError("--camera sim needs --turntable sim (the simulated camera sees the simulated table)")
        return rig.camera(settle_frames=settle_frames, average=average)
    if spec.startswith("folder:"):
        return FolderCamera(spec[len("folder:"):])
    return OpenCVCamera(spec, settle_frames=settle_frames, average=average)


def run_capture(
    out,
    *,
    turntable="sim",
    camera=None,
    step_deg=10.0,
    n_background=20,
    n_intrinsic=0,
    board=True,
    intrinsics_file=None,
    drive=None,
    audit_limit_deg=None,
    stop_on_flag=True,
    settle_frames=3,
    average=1,
    sim_options=None,
    sim_faults=(),
    on_view=None,
    prompt=None,
    say=None,
    progress=None,
):
    """Capture with the named devices; the command ``organlab capture`` calls this.

    Parameters
    ----------
    out : str or Path
        Session folder (a stopped capture there is continued).
    turntable : str
        ``"sim"`` (simulated MDrive on a pty) or a serial port name.
    camera : str, optional
        ``"sim"``, a device index (``"0"``), a URL, or ``"folder:DIR"``;
        default ``"sim"`` with the simulated table, else ``"0"``.
    drive : dict, optional
        Keyword arguments of :class:`~organlab.capture.MDriveTurntable`
        (``steps_per_rev``, ``microsteps``, ``gear_ratio``, ``baudrate``,
        ``device_name``, ``home_switch``, ...).
    sim_options : dict, optional
        Keyword arguments of :class:`~organlab.capture.SimRig`.
    sim_faults : sequence of dict
        Faults injected into the simulated controller
        (:meth:`~organlab.capture.MDriveSimulator.inject` keywords, with ``kind``).
    Others : see :func:`~organlab.capture.capture_session`.

    Returns
    -------
    Path
    """
    from ._audit import AUDIT_LIMIT_DEG
    from ._mdrive import MDriveTurntable
    from ._session import capture_session, console_prompt
    from ._simrig import SimRig

    camera = camera or ("sim" if turntable == "sim" else "0")
    rig = table = cam = None
    try:
        reference = None
        if turntable == "sim":
            rig = SimRig(**(sim_options or {}))
            for f in sim_faults:
                f = dict(f)
                rig.controller.inject(f.pop("kind"), **f)
            table = rig.turntable(**(drive or {}))
            reference = {"volume_mm3": rig.volume_mm3, "source": f"simulated specimen '{rig.specimen.name}' (exact)"}
        else:
            table = MDriveTurntable(turntable, **(drive or {}))
        cam = _open_camera(str(camera), rig, settle_frames=settle_frames, average=average)
        intr = None
        if intrinsics_file is not None:
            intr = read_intrinsics(intrinsics_file)
        elif rig is not None and n_intrinsic == 0 and camera == "sim":
            intr = rig.camera_model  # the simulated camera's true intrinsics, as from an earlier calibration
        if prompt is None:
            prompt = rig.prompt if (rig is not None and camera == "sim") else console_prompt
        return capture_session(
            out, table, cam, step_deg=step_deg, n_background=n_background, n_intrinsic=n_intrinsic, board=board,
            intrinsics=intr, reference=reference, audit_limit_deg=audit_limit_deg or AUDIT_LIMIT_DEG,
            stop_on_flag=stop_on_flag, prompt=prompt, on_view=on_view, say=say, progress=progress,
        )
    finally:
        for thing in (cam, table, rig):
            if thing is not None:
                thing.close()
