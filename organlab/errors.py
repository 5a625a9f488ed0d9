"""Exceptions raised by organlab for bad input.

Every error a user can cause (a missing image, bad JSON, an undetectable
board, ...) is an :class:`OrganlabError`.  Its message is one line that names
the file and what to do about it; the command-line interface prints that line
and exits non-zero, without a traceback.
"""

__all__ = ["OrganlabError", "SessionError", "CalibrationError", "SettingsError"]


class OrganlabError(Exception):
    """Base class of the errors caused by the user's input."""


class SessionError(OrganlabError, ValueError):
    """A session folder or its ``session.json`` is not valid."""


class CalibrationError(OrganlabError, ValueError):
    """A calibration cannot be computed from the given images."""


class SettingsError(SessionError):
    """A reconstruction setting is not valid (:class:`organlab.engine.Settings`).

    The message names the parameter (``threshold must be ...``), as the library
    calls it; :attr:`parameter` holds the name so that a face can translate it
    (the CLI to its flag, :meth:`for_flag`).
    """

    def __init__(self, parameter: str, message: str):
        super().__init__(f"{parameter} {message}")
        self.parameter = parameter
        self.message = message

    def for_flag(self, flag: str) -> str:
        """The message with the parameter's name replaced by ``flag`` (e.g. ``'--threshold'``)."""
        return f"{flag} {self.message}"
