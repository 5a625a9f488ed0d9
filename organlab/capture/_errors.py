"""Errors of the capture stage: one line each, naming the device and the fix."""

from __future__ import annotations

from ..errors import OrganlabError

__all__ = [
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


class CaptureError(OrganlabError):
    """A capture cannot go on (the images taken so far are kept and listed)."""


class TurntableError(CaptureError):
    """The turntable controller refused a command or is in an unexpected state."""


class NoReplyError(TurntableError):
    """The controller did not answer within the timeout, after every retry."""


class GarbledReplyError(TurntableError):
    """The controller's answers could not be read, after every retry."""


class DisconnectedError(NoReplyError):
    """The serial port went away (cable or USB adapter unplugged)."""


class StallError(TurntableError):
    """The motor stalled during a move (the controller's stall flag is set)."""


class PositionError(TurntableError):
    """The position read back after a move is not the commanded one (lost steps)."""


class CameraError(CaptureError):
    """The camera cannot be opened or returned no frame."""


class AngleAuditError(CaptureError):
    """The table angle measured from a board image disagrees with the commanded angle."""
