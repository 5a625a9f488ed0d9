"""Open the rig a user names (``sim`` or a serial port; ``sim``, a camera index, a URL or a folder) and capture."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ..validate import read_json
from ..camera import Camera
from ._audit import AUDIT_LIMIT_DEG
from ._cameras import FolderCamera, OpenCVCamera
from ._errors import CaptureError
from ._mdrive import MDriveTurntable
from ._session import capture_session, console_prompt

__all__ = ["run_capture", "read_intrinsics"]


def read_intrinsics(path: str | Path, image_size: tuple[int, int] | None = None) -> Camera:
    """Intrinsics from a ``calibration.json`` (``camera``) or a ``session.json`` (``camera``).

    Returns
    -------
    organlab.camera.Camera
    """
    p = Path(path)
    doc = read_json(p, error=CaptureError, fix="give a calibration.json or session.json with 'camera'")
    try:
        cam = doc["camera"]
        return Camera(cam["K"], cam["dist"], image_size=image_size or cam.get("image_size") or doc.get("image_size"))
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise CaptureError(f"{p}: no usable 'camera' with 'K' and 'dist' ({e}); give a calibration.json or session.json") from None


def _open_camera(spec, rig, *, settle_frames, average):
    if spec == "sim":
        if rig is None:
            raise CaptureError("--camera sim needs --turntable sim (the simulated camera sees the simulated table)")
        return rig.camera(settle_frames=settle_frames, average=average)
    if spec.startswith("folder:"):
        return FolderCamera(spec[len("folder:"):])
    return OpenCVCamera(spec, settle_frames=settle_frames, average=average)


def run_capture(
    out: str | Path,
    *,
    turntable: str = "sim",
    camera: str | None = None,
    step_deg: float = 10.0,
    n_background: int = 20,
    n_intrinsic: int = 0,
    board: bool = True,
    intrinsics_file: str | Path | None = None,
    drive: dict | None = None,
    audit_limit_deg: float | None = None,
    stop_on_flag: bool = True,
    settle_frames: int = 3,
    average: int = 1,
    rig: Any = None,
    sim_faults: Sequence[dict] = (),
    on_view: Callable[[int, float, np.ndarray], object] | None = None,
    prompt: Callable[[str, str, int | None], object] | None = None,
    say: Callable[[str], object] | None = None,
    progress: Callable[[int, int], object] | None = None,
) -> Path:
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
    rig : organlab.synthetic.SimRig, optional
        The simulated rig, needed with ``turntable="sim"`` (the CLI makes it;
        a simulator is test data, so the capture stage does not build one);
        closed at the end.
    sim_faults : sequence of dict
        Faults injected into the simulated controller
        (:meth:`organlab.synthetic.MDriveSimulator.inject` keywords, with ``kind``).
    Others : see :func:`~organlab.capture.capture_session`.

    Returns
    -------
    Path
    """
    camera = camera or ("sim" if turntable == "sim" else "0")
    if turntable == "sim" and rig is None:
        raise CaptureError("turntable 'sim' needs the simulated rig: rig=organlab.synthetic.SimRig(...)")
    if turntable != "sim" and rig is not None:
        raise CaptureError("rig= is the simulated rig: give it with turntable='sim'")
    table = cam = None
    try:
        reference = None
        if turntable == "sim":
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
