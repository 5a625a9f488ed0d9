"""Capture: turntable and camera control over a real serial link, a simulated rig, crash-safe sessions.

* :class:`Turntable` (the interface) and :class:`MDriveTurntable` (MCode over
  pyserial: set-up, absolute/relative moves, waiting, homing, read-back
  verification, retries); every exchange goes to a :class:`SerialLog`.
* Cameras: :class:`OpenCVCamera` (device index or URL; settling, averaging),
  :class:`FolderCamera` (replay), :class:`SimCamera`.
* The simulated rig (a simulated MDrive controller on a pty pair with
  injectable faults, and a camera rendering the synthetic phantom and board)
  is test data: :class:`organlab.synthetic.SimRig`, passed as ``rig=``.
* :func:`capture_session`: background, hand-held board, board on the table at
  every stop (audited at once by :class:`AngleAudit`), views; ``session.json``
  rewritten atomically after every image; a second run continues.

See ``docs/capture.md``.
"""

from ._audit import AUDIT_LIMIT_DEG, AngleAudit, audited_angles, board_rotation
from ._cameras import CaptureCamera, FolderCamera, OpenCVCamera
from ._errors import (
    AngleAuditError,
    CameraError,
    CaptureError,
    DisconnectedError,
    GarbledReplyError,
    NoReplyError,
    PositionError,
    StallError,
    TurntableError,
)
from ._mdrive import MDriveTurntable, SerialLog, Turntable
from ._run import read_intrinsics, run_capture
from ._session import capture_session, console_prompt, stop_angles

__all__ = [
    "Turntable",
    "MDriveTurntable",
    "SerialLog",
    "CaptureCamera",
    "OpenCVCamera",
    "FolderCamera",
    "AngleAudit",
    "board_rotation",
    "audited_angles",
    "AUDIT_LIMIT_DEG",
    "capture_session",
    "run_capture",
    "read_intrinsics",
    "console_prompt",
    "stop_angles",
    "CaptureError",
    "TurntableError",
    "NoReplyError",
    "GarbledReplyError",
    "DisconnectedError",
    "StallError",
    "PositionError",
    "CameraError",
    "AngleAuditError",
]
