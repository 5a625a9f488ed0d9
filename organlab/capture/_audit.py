"""Angle audit: the table angle measured from the board lying on it, at every stop.

The board lies flat on the table, so between two stops its pose in the
camera changes by a rotation about its own normal, by the angle the table
turned.  Its pose at each stop comes from the detected corners and the
camera intrinsics (``cv2.solvePnP``); the measured angle of stop ``k`` is the
commanded angle of the first (reference) stop plus the rotation from the
reference pose to the pose at ``k`` about the board normal.  Neither the
board's place on the table nor the camera's pose needs to be known.
"""

from __future__ import annotations

import numpy as np

from ..calibration import board_points, detect_board
from ..camera import Camera
from ..session import Pattern
from ._errors import CaptureError

__all__ = ["board_rotation", "AngleAudit", "audited_angles"]

#: Default limit, deg.  On the simulated rig (320x240 and 640x480, noise 1.5
#: grey levels) the audit error stays below 0.05 deg (measured in
#: tests/test_capture.py); one microstep of a 90:1 table is 1e-4 deg, a full
#: step 0.02 deg, so 0.5 deg means about 25 lost full steps or a slipping plate.
AUDIT_LIMIT_DEG = 0.5


def board_rotation(image: np.ndarray, camera: Camera, pattern: Pattern) -> np.ndarray | None:
    """Board-to-camera rotation of the checkerboard in ``image``, or None when no oriented board is found.

    Parameters
    ----------
    image : (H, W) or (H, W, 3) uint8
    camera : organlab.camera.Camera
        Intrinsics (``K``, ``dist``); the pose is not used.
    pattern : organlab.session.Pattern

    Returns
    -------
    R_cam_board : (3, 3) float64 or None
        Maps board-frame directions (board frame of
        :func:`organlab.calibration.board_points`, Z toward the camera) to
        the camera frame.
    """
    import cv2

    corners = detect_board(image, pattern, require_orientation=True)
    if corners is None:
        return None
    obj = board_points(pattern)
    ok, rvec, _ = cv2.solvePnP(obj.astype(np.float64), corners.astype(np.float64), camera.K, camera.dist,
                               flags=cv2.SOLVEPNP_ITERATIVE)
    if not ok:
        return None
    return cv2.Rodrigues(rvec)[0]


class AngleAudit:
    """Compares each stop's commanded angle with the angle measured from the board image.

    Parameters
    ----------
    camera : organlab.camera.Camera
        Intrinsics of the capture camera.
    pattern : organlab.session.Pattern
    limit_deg : float
        A stop whose measured angle differs from the commanded one by more
        than this is flagged.
    """

    def __init__(self, camera: Camera, pattern: Pattern, *, limit_deg: float = AUDIT_LIMIT_DEG) -> None:
        if not limit_deg > 0:
            raise CaptureError(f"audit limit must be > 0 deg, got {limit_deg}")
        self.camera = camera
        self.pattern = pattern
        self.limit_deg = float(limit_deg)
        self.reference = None  # (commanded angle, R_cam_board)

    def check(self, image: np.ndarray, commanded_deg: float) -> dict:
        """Audit one stop.

        Returns
        -------
        dict
            ``commanded_deg``, ``measured_deg`` (None when no board was
            found), ``error_deg`` (measured - commanded, wrapped to
            [-180, 180)), ``flagged`` (bool) and ``reason``.  The first stop
            with a board becomes the reference (error 0 by definition).
        """
        R = board_rotation(image, self.camera, self.pattern)
        out = {"commanded_deg": float(commanded_deg), "measured_deg": None, "error_deg": None, "flagged": False, "reason": ""}
        if R is None:
            out.update(flagged=True, reason="no board found in the image (moved, covered or out of view?)")
            return out
        if self.reference is None:
            self.reference = (float(commanded_deg), R)
            out.update(measured_deg=float(commanded_deg), error_deg=0.0, reason="reference stop")
            return out
        a0, R0 = self.reference
        M = R0.T @ R  # rotation about the board normal (board frame Z), by the angle the table turned
        turned = np.degrees(np.arctan2(M[1, 0] - M[0, 1], M[0, 0] + M[1, 1]))
        measured = a0 + turned
        err = (measured - commanded_deg + 180.0) % 360.0 - 180.0
        out.update(measured_deg=float((measured) % 360.0), error_deg=float(err))
        if abs(err) > self.limit_deg:
            out.update(flagged=True, reason=f"measured {measured % 360.0:.2f} deg for commanded {commanded_deg:g} deg "
                                            f"({err:+.2f} deg, limit {self.limit_deg:g}): lost steps, a slipping plate or a moved board")
        return out


def audited_angles(doc: dict, angles_deg: np.ndarray | list) -> np.ndarray:
    """Each view's table-angle error measured by the capture's angle audit, or NaN where none was.

    The audit (``session.json`` ``capture.audit``, written by
    :func:`organlab.capture.capture_session`) measures the angle at every stop
    of the turntable board images; the views are taken at the same stops.
    Pose refinement (:func:`organlab.poses.refine_poses`) uses these as its
    prior for the views' angles.

    Parameters
    ----------
    doc : dict
        The session document (``Session.raw``).
    angles_deg : (n,) float
        The views' commanded table angles, degrees.

    Returns
    -------
    (n,) float64
        ``measured - commanded``, degrees, wrapped to [-180, 180); NaN for a
        view whose stop has no audit entry (no audit, no board found there,
        or a flagged stop).

    Examples
    --------
    >>> doc = {"capture": {"audit": [{"commanded_deg": 0.0, "measured_deg": 0.0, "error_deg": 0.0},
    ...                              {"commanded_deg": 10.0, "measured_deg": 10.4, "error_deg": 0.4}]}}
    >>> audited_angles(doc, [0.0, 10.0, 20.0]).round(2).tolist()
    [0.0, 0.4, nan]
    """
    angles = np.asarray(angles_deg, dtype=np.float64).ravel()
    out = np.full(len(angles), np.nan)
    cap = doc.get("capture") if isinstance(doc, dict) else None
    entries = cap.get("audit") if isinstance(cap, dict) else None
    if not isinstance(entries, list):
        return out
    found = {}
    for e in entries:
        try:
            a, err = float(e["commanded_deg"]), e.get("error_deg")
        except (KeyError, TypeError, ValueError):
            continue
        if err is None or not np.isfinite(float(err)) or e.get("flagged"):
            continue
        found[round(a % 360.0, 6)] = float(err)
    for i, a in enumerate(angles):
        if np.isfinite(a):
            out[i] = found.get(round(a % 360.0, 6), np.nan)
    return out
