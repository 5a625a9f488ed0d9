"""Exceptions raised by organlab for bad input.

Every error a user can cause (a missing image, bad JSON, an undetectable
board, ...) is an :class:`OrganlabError`.  Its message is one line that names
the file and what to do about it; the command-line interface prints that line
and exits non-zero, without a traceback.
"""

__all__ = ["OrganlabError", "SessionError", "CalibrationError"]


class OrganlabError(Exception):
    """Base class of the errors caused by the user's input."""


class SessionError(OrganlabError, ValueError):
    """A session folder or its ``session.json`` is not valid."""


class CalibrationError(OrganlabError, ValueError):
    """A calibration cannot be computed from the given images."""
