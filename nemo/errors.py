"""User-facing errors.

Every problem caused by the user's input (wrong file, missing axis, empty mask, bad option)
is raised as :class:`NemoError` with a message that names the problem and the fix. The CLI
prints such messages on one line and exits with status 2; anything else is a bug.
"""

from __future__ import annotations


class NemoError(Exception):
    """An error in the user's input or configuration, with a message meant for people."""


class ObjectTooSmallError(NemoError):
    """A length of the analysis (patch, averaging or contour radius) does not fit on the object.

    Raised apart so that a frame of several objects (``mesh.keep: all``) can leave that object
    out of the step, with a warning and a quality flag, and go on with the others. ``reason``
    says what does not fit, without the advice to the user (the message).
    """

    def __init__(self, message: str, reason: str | None = None):
        super().__init__(message)
        self.reason = reason or message


class NemoWarning(UserWarning):
    """A recoverable problem the user should know about (missing calibration, fallback)."""
